"""One output rule for every file option: a file that exists is replaced only with --force, and a file inside a
folder that a yawil stage owns (a dataset, a run, a results folder, a zoo model) never; the refusal comes before
any work, in one line naming the file, and the file keeps its bytes."""

from __future__ import annotations

import contextlib
import io
import time
from pathlib import Path

import pytest

from yawil.cli import main
from yawil.fileio import check_output_file, owning_folder


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    data = tmp_path / "data"
    data.mkdir()
    (data / "manifest.json").write_text('{"episodes": []}')
    (data / "episodes").mkdir()
    (data / "ep_000000.h5").write_bytes(b"episode")
    (tmp_path / "web").mkdir()  # a user's folder that happens to hold a manifest.json is no dataset
    (tmp_path / "web" / "manifest.json").write_text("{}")
    (tmp_path / "web" / "app.js").write_text("js")
    run = tmp_path / "run"
    (run / "sub").mkdir(parents=True)
    (run / "sub" / "notes.txt").write_text("a run's notes")
    (run / ".yawil.lock").write_text("")
    for name in ("best.pt", "last.pt"):
        (run / name).write_bytes(b"weights")
    (tmp_path / "mine.csv").write_text("a user's file")
    return tmp_path


def _run(argv: list[str]) -> tuple[int, list[str]]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = main(argv)
        except SystemExit as exit_:
            rc = exit_.code if isinstance(exit_.code, int) else 2  # as `yawil.cli.entry` gives a one-line exit
            if not isinstance(exit_.code, int):
                err.write(str(exit_.code))
    return rc, [line for line in err.getvalue().splitlines() if line.strip()]


# (argv with {t}, the file that must keep its bytes, text of the one line)
CASES = [
    (["data", "stats", "{t}/data", "--out", "{t}/data/manifest.json"], "data/manifest.json", "bookkeeping"),
    (["data", "stats", "{t}/data", "--out", "{t}/data/ep_000000.h5", "--force"], "data/ep_000000.h5", "inside"),
    (["data", "stats", "{t}/data", "--out", "{t}/mine.csv"], "mine.csv", "--force"),
    (["export", "{t}/run/best.pt", "--onnx", "{t}/run/best.pt", "--force"], "run/best.pt", "inside"),
    (["export", "{t}/run/best.pt", "--onnx", "{t}/mine.csv"], "mine.csv", "--force"),
    (["trace", "straight/training/ClearNoon/0/0", "--agent", "expert", "--out", "{t}/run/last.pt"], "run/last.pt",
     "inside"),
    (["trace", "straight/training/ClearNoon/0/0", "--agent", "expert", "--out", "{t}/mine.csv"], "mine.csv",
     "--force"),
    (["select", "{t}/run/best.pt", "--out", "{t}/sel", "--link", "{t}/run/sub/../last.pt", "--force"], "run/last.pt",
     "inside"),
    (["select", "{t}/run/best.pt", "--out", "{t}/sel", "--link", "{t}/mine.csv/x.pt"], "mine.csv", "is a file"),
    (["data", "stats", "{t}/data", "--out", "{t}/mine.csv/x.png"], "mine.csv", "is a file"),
]


@pytest.mark.parametrize("argv, kept, text", CASES, ids=[" ".join(c[0][:2]) + f" {i}" for i, c in enumerate(CASES)])
def test_a_file_option_never_replaces_a_file_it_did_not_make(tree: Path, argv: list[str], kept: str,
                                                              text: str) -> None:
    before = (tree / kept).read_bytes()
    t0 = time.perf_counter()
    rc, lines = _run([a.replace("{t}", str(tree)) for a in argv])
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    assert kept.split("/")[-1] in lines[0]
    assert (tree / kept).read_bytes() == before
    assert time.perf_counter() - t0 < 30.0  # refused before any work (seconds of imports on a loaded machine)
    assert not (tree / "sel").exists()


def test_the_rule_itself(tree: Path) -> None:
    assert owning_folder(tree / "data" / "x.png") == tree / "data"
    assert owning_folder(tree / "run" / "sub" / "x.png") == tree / "run"  # a folder inside a run is the run's
    assert owning_folder(tree / "mine.csv") is None and owning_folder(tree / "web" / "app.js") is None
    assert check_output_file(tree / "web" / "app.js", "--out", force=True) == tree / "web" / "app.js"
    with pytest.raises(ValueError, match="inside"):  # a new file inside a dataset: its readers would find it
        check_output_file(tree / "data" / "notes.png", "--out", force=True)
    own = (tree / "data" / "stats.png",)
    assert check_output_file(tree / "data" / "stats.png", "--out", own=own) == tree / "data" / "stats.png"
    (tree / "data" / "stats.png").write_bytes(b"png")
    check_output_file(tree / "data" / "stats.png", "--out", own=own)  # the command's own product, replaced
    with pytest.raises(ValueError, match="inside"):
        check_output_file(tree / "data" / "stats.png", "--out", force=True)
    assert check_output_file(tree / "mine.csv", "--out", force=True) == tree / "mine.csv"
    with pytest.raises(ValueError, match="is a folder"):
        check_output_file(tree / "run", "--out", force=True)


# folder options: (argv with {t}, the file that must keep its bytes, text of the one line)
FOLDER_CASES = [
    (["report", "{t}/run", "--out", "{t}/web"], "web/app.js", "--force"),
    (["report", "{t}/run", "--out", "{t}/run", "--force"], "run/best.pt", "results or model folder"),
    (["report", "{t}/run", "--out", "{t}/mine.csv"], "mine.csv", "is a file"),
    (["explain", "--checkpoint", "{t}/run/best.pt", "--frames", "{t}/data", "--out", "{t}/web"], "web/app.js",
     "--force"),
    (["explain", "--checkpoint", "{t}/run/best.pt", "--episode", "--out", "{t}/mine.csv"], "mine.csv", "is a file"),
    (["sim", "view", "--out", "{t}/web"], "web/app.js", "--force"),
    (["sim", "view", "--out", "{t}/data", "--force"], "data/ep_000000.h5", "dataset"),
    # a subfolder of a yawil output holds that output's files: --force wrote beside them
    (["sim", "view", "--out", "{t}/run/sub", "--force"], "run/sub/notes.txt", "inside"),
    (["report", "{t}/run", "--out", "{t}/run/sub", "--force"], "run/sub/notes.txt", "inside"),
    (["explain", "--checkpoint", "{t}/run/best.pt", "--frames", "{t}/data", "--out", "{t}/run/sub", "--force"],
     "run/sub/notes.txt", "inside"),
]


@pytest.mark.parametrize("argv, kept, text", FOLDER_CASES,
                         ids=[" ".join(c[0][:2]) + f" {i}" for i, c in enumerate(FOLDER_CASES)])
def test_a_folder_option_never_writes_over_a_users_files(tree: Path, argv: list[str], kept: str, text: str) -> None:
    before = (tree / kept).read_bytes()
    rc, lines = _run([a.replace("{t}", str(tree)) for a in argv])
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    assert (tree / kept).read_bytes() == before
    assert sorted(p.name for p in (tree / "web").iterdir()) == ["app.js", "manifest.json"]
    assert sorted(p.name for p in (tree / "run" / "sub").iterdir()) == ["notes.txt"]


def test_the_folder_rule_itself(tree: Path) -> None:
    from yawil.fileio import OUTPUT_MARKER, check_output_folder, claim_output_folder

    assert check_output_folder(tree / "new", "--out", "report") == tree / "new"
    (tree / "empty").mkdir()
    check_output_folder(tree / "empty", "--out", "report")
    claim_output_folder(tree / "new", "report")
    (tree / "new" / "report.html").write_text("old report")
    check_output_folder(tree / "new", "--out", "report")  # the same command regenerates its own folder
    with pytest.raises(ValueError, match="yawil report"):
        check_output_folder(tree / "new", "--out", "explain")  # another command's folder needs --force
    check_output_folder(tree / "web", "--out", "report", force=True)  # a user's folder with --force
    (tree / "web" / OUTPUT_MARKER).write_text("not json")
    with pytest.raises(ValueError, match="entries"):
        check_output_folder(tree / "web", "--out", "report")


# a new file or folder inside a folder a stage owns, and a pipeline folder that holds what the pipeline did not
# write: (argv with {t}, the path that must not appear, text of the one line)
NEW_PATH_CASES = [
    (["data", "stats", "{t}/data", "--out", "{t}/data/episodes/x.png"], "data/episodes/x.png", "inside"),
    (["export", "{t}/run/best.pt", "--onnx", "{t}/run/model.onnx"], "run/model.onnx", "inside"),
    (["trace", "straight/training/ClearNoon/0/0", "--agent", "expert", "--out", "{t}/data/t.csv"], "data/t.csv",
     "inside"),
    (["results", "--out", "{t}/run/results.md"], "run/results.md", "inside"),
    (["select", "{t}/run/best.pt", "--out", "{t}/sel", "--link", "{t}/run/chosen.pt"], "run/chosen.pt", "inside"),
    (["report", "{t}/run", "--out", "{t}/run/report"], "run/report", "inside"),
    (["sim", "view", "--out", "{t}/data/episodes/view"], "data/episodes/view", "inside"),
    (["collect", "--out", "{t}/data/episodes/more", "--frames", "10"], "data/episodes/more", "inside"),
    (["train", "--data", "{t}/data", "--out", "{t}/run/again"], "run/again", "inside"),
    (["bench", "--agent", "expert", "--out", "{t}/data/bench"], "data/bench", "inside"),
    (["dagger", "--out", "{t}/run/dagger"], "run/dagger", "inside"),
    (["data", "subset", "{t}/data", "--out", "{t}/run/subset", "--only", "all"], "run/subset", "inside"),
    (["select", "{t}/run/best.pt", "--out", "{t}/web"], "web/.yawil-output", "entries"),
    (["select", "{t}/run/best.pt", "--out", "{t}/data"], "data/.yawil-output", "dataset"),
    (["demo", "--out", "{t}/web"], "web/.yawil-output", "entries"),
    (["demo", "--out", "{t}/run/demo"], "run/demo", "inside"),
    (["select", "{t}/run/best.pt", "{t}/run/best.pt", "--out", "{t}/sel"], "sel", "differ"),  # refused: no folder
    (["zoo", "pack", "{t}/run/best.pt", "--name", "m", "--data", "{t}/data", "--card", "{t}/mine.csv", "--out",
      "{t}/run/zoo"], "run/zoo", "inside"),
    (["reproduce", "--out", "{t}/web"], "web/.yawil-output", "entries"),
    (["experiment", "square", "--out", "{t}/web"], "web/.yawil-output", "entries"),
]


@pytest.mark.parametrize("argv, absent, text", NEW_PATH_CASES,
                         ids=[" ".join(c[0][:2]) + f" {i}" for i, c in enumerate(NEW_PATH_CASES)])
def test_nothing_is_written_inside_another_stages_folder(tree: Path, argv: list[str], absent: str,
                                                         text: str) -> None:
    t0 = time.perf_counter()
    rc, lines = _run([a.replace("{t}", str(tree)) for a in argv])
    assert rc == 2 and len(lines) == 1 and text in lines[0], lines
    assert not (tree / absent).exists()
    assert sorted(p.name for p in (tree / "web").iterdir()) == ["app.js", "manifest.json"]
    assert time.perf_counter() - t0 < 30.0  # refused before any work


def test_a_pipeline_folder_is_claimed_and_resumed(tree: Path) -> None:
    from yawil.fileio import OUTPUT_MARKER, check_pipeline_folder, claimed_output_folder

    assert check_pipeline_folder(tree / "new", "--out", "demo") == tree / "new"
    with pytest.raises(ValueError), claimed_output_folder(tree / "new" / "x", "demo"):
        raise ValueError("refused before the first stage")
    assert not (tree / "new").exists()  # the claim is undone: no folder, no mark
    with claimed_output_folder(tree / "new", "demo"):
        (tree / "new" / "data").mkdir()  # killed in its first stage: the mark alone says whose folder it is
    check_pipeline_folder(tree / "new", "--out", "demo")
    with pytest.raises(ValueError, match="entries yawil select did not write"):
        check_pipeline_folder(tree / "new", "--out", "select")
    (tree / "old" / "stages").mkdir(parents=True)  # a folder from before the mark: its stages/ says it
    check_pipeline_folder(tree / "old", "--out", "demo", signature=("stages", "data"))
    (tree / "older" / "data").mkdir(parents=True)  # one stopped in its first stage: its data/
    check_pipeline_folder(tree / "older", "--out", "demo", signature=("stages", "data"))
    assert not (tree / "old" / OUTPUT_MARKER).exists()
    with pytest.raises(ValueError, match="is a file"):
        check_pipeline_folder(tree / "mine.csv", "--out", "demo")


def test_an_unwritable_place_is_refused_before_the_work(tree: Path) -> None:
    with pytest.raises(ValueError, match="cannot write in /proc"):
        check_output_file("/proc/x.png", "--out")
    assert not list(tree.glob("**/.yawil-probe-*"))
    check_output_file(tree / "deep" / "er" / "x.png", "--out")  # the writers make missing folders
    assert not (tree / "deep").exists() and not list(tree.glob(".yawil-probe-*"))


def test_a_bad_readme_is_refused_before_the_page_is_written(tree: Path) -> None:
    (tree / "README.md").write_text("no markers here\n")
    rc, lines = _run(["results", "--out", str(tree / "page.md"), "--readme", str(tree / "README.md")])
    assert rc == 2 and len(lines) == 1 and "--readme" in lines[0], lines
    assert not (tree / "page.md").exists()


@pytest.mark.parametrize("argv", [["demo"], ["experiment", "square"], ["reproduce"], ["collect", "--frames", "10"],
                                  ["dagger"], ["sim", "view"], ["sim", "routes"], ["bench", "routes"],
                                  ["explain", "--checkpoint", "x", "--episode"]])
def test_a_negative_seed_names_the_option_and_leaves_nothing(tmp_path: Path, argv: list[str]) -> None:
    out = tmp_path / "fresh"
    rc, lines = _run([*argv, "--seed", "-1", "--out", str(out)])
    assert rc == 2 and "argument --seed: expected an integer >= 0, got '-1'" in lines[-1], lines
    assert not out.exists()
