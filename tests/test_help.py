"""`--help` of the commands says what is true: commands that exist, the help of the action asked about, each
default once, every choice listed (issue 14)."""

from __future__ import annotations

import re

import pytest

from yawil.cli import main


def _help(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: ")
    return out


def _options(text: str) -> dict[str, str]:
    """Option -> its help text, whitespace collapsed (argparse wraps lines at the terminal width)."""
    blocks: dict[str, str] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"  (-{1,2}[\w-]+)", line)
        if m:
            current = m.group(1)
            blocks[current] = line
        elif current and line.startswith("    "):
            blocks[current] += " " + line
        else:
            current = None
    return {k: " ".join(v.split()) for k, v in blocks.items()}


@pytest.fixture(autouse=True)
def _columns(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "100")


def test_train_names_a_command_that_exists(capsys: pytest.CaptureFixture[str]) -> None:
    text = " ".join(_help(capsys, "train").split())
    assert "models list" not in text
    assert "`yawil models`" in text
    assert _help(capsys, "models").startswith("usage: yawil models")  # the command it names


@pytest.mark.parametrize(
    ("action", "has", "lacks"),
    [("routes", ["--town", "--routes-dir", "--seed"], ["--suite", "--agent"]),
     ("validate", ["--town", "--routes-dir"], ["--seed", "--suite", "--agent"])],
)
def test_bench_action_help(capsys: pytest.CaptureFixture[str], action: str, has: list[str], lacks: list[str]) -> None:
    text = _help(capsys, "bench", action)
    assert text.startswith(f"usage: yawil bench {action} ")
    opts = _options(text)
    assert set(has) <= set(opts) and not set(lacks) & set(opts)
    assert "route" in text.split("options:")[0].lower()  # its own description


def test_bench_help_is_still_the_whole_command(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (("bench",), ("bench", "run")):
        opts = _options(_help(capsys, *argv))
        assert {"--suite", "--agent", "--town", "--seed"} <= set(opts)


@pytest.mark.parametrize(
    ("which", "has", "lacks"),
    [("noise", ["--profile", "--out", "--noise-seeds", "--models"], ["--seed"]),
     ("square", ["--profile", "--out", "--seed"], ["--noise-seeds", "--models"])],
)
def test_experiment_action_help(capsys: pytest.CaptureFixture[str], which: str, has: list[str],
                                lacks: list[str]) -> None:
    text = _help(capsys, "experiment", which)
    assert text.startswith(f"usage: yawil experiment {which} ")
    opts = _options(text)
    assert set(has) <= set(opts) and not set(lacks) & set(opts)
    assert f"table{1 if which == 'square' else 2}.md" in " ".join(text.split())


def test_collect_help(capsys: pytest.CaptureFixture[str]) -> None:
    text = _help(capsys, "collect")
    flat = " ".join(text.split())
    assert "%%" not in text and "about 10% of the frames" in flat
    assert "(default: None)" not in text and "(default: False)" not in text
    opts = _options(text)
    assert "default" not in opts["--out"] and "required" in opts["--out"]
    for opt, help_text in opts.items():
        assert help_text.count("default") <= 1, (opt, help_text)  # no "(default 2000) (default: 2000)"
    assert "(default 10-30)" in opts["--vehicles"] and "(default 2000)" in opts["--port"]


def test_sim_view_lists_the_weathers(capsys: pytest.CaptureFixture[str]) -> None:
    from yawil.sim.cli import WEATHER_NAMES
    from yawil.sim.weather import WEATHERS

    assert WEATHER_NAMES == tuple(WEATHERS)  # the help's list is the simulator's
    opts = _options(_help(capsys, "sim", "view"))
    for name in WEATHERS:
        assert name in opts["--weather"]
    assert "(default ClearNoon)" in opts["--weather"]
