"""The `yawil` command: sub-commands listed, unknown options rejected clearly."""

from __future__ import annotations

import subprocess
import sys

import pytest

from yawil.cli import COMMANDS, build_parser, main


def test_help_lists_available_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    parser = build_parser()
    available = parser._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    for name in available:
        assert name in out
    assert set(available) <= set(COMMANDS)


def test_unknown_option_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--no-such-option"])
    assert exc.value.code == 2
    assert "unrecognized arguments: --no-such-option" in capsys.readouterr().err


def test_no_command_prints_help_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: yawil" in capsys.readouterr().out


def test_console_script_runs() -> None:
    out = subprocess.run([sys.executable, "-m", "yawil.cli", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("yawil ")


def test_bad_input_is_one_line_not_a_traceback(capsys) -> None:  # type: ignore[no-untyped-def]
    from yawil.cli import main

    assert main(["sim", "view", "--town", "town02", "--weather", "Rainy"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Rainy" in err[0] and err[0].startswith("yawil sim:")
