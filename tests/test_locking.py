"""One writer per output folder: a second one is refused at once, in one line; a killed holder frees it."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from yawil.locking import LOCK_FILE, folder_lock

HOLD = "import sys, time\nfrom yawil.locking import folder_lock\nwith folder_lock(sys.argv[1], 'x'):\n    print('held', flush=True)\n    time.sleep(60)\n"


def _holder(folder: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_and_a_killed_one_leaves_no_stale_lock(tmp_path: Path) -> None:
    proc = _holder(tmp_path)
    try:
        with pytest.raises(ValueError, match="another yawil process is writing this results folder"):
            with folder_lock(tmp_path, "results folder"):
                pass
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    with folder_lock(tmp_path, "results folder"):  # the kernel dropped the killed holder's lock
        assert (tmp_path / LOCK_FILE).exists()


@pytest.mark.parametrize("command", ["bench", "train", "collect", "dagger"])
def test_every_writer_takes_the_lock(tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]) -> None:
    """The CLI of each long job answers a held folder with one line and exit 2, before any work."""
    from yawil.cli import main
    from yawil.data.synthetic import write_synthetic_dataset

    data = tmp_path / "data"
    write_synthetic_dataset(data, episodes=2, frames=4, seed=0)
    out = tmp_path / "out"
    argv = {
        "bench": ["bench", "--suite", "corl2017", "--tasks", "straight", "--routes", "0:1", "--seeds", "1",
                  "--agent", "expert", "--no-camera", "--no-progress", "--out", str(out)],
        "train": ["train", "--model", "yaw-guided", "--data", str(data), "--out", str(out), "--max-steps", "1",
                  "--no-progress"],
        "collect": ["collect", "--town", "town01", "--frames", "10", "--out", str(out), "--quiet"],
        "dagger": ["dagger", "--out", str(out), "--expert-data", str(data), "--rounds", "0", "--round0-steps", "1",
                   "--no-progress"],
    }[command]
    t0 = time.perf_counter()
    with folder_lock(out, "x"):
        try:
            rc = main(argv)
            err = capsys.readouterr().err.strip()
        except SystemExit as exit_:  # the commands that end with their own one-line SystemExit
            rc, err = 2, str(exit_)
    assert rc == 2 and "another yawil process" in err and "\n" not in err, err
    assert time.perf_counter() - t0 < 30


def test_a_refused_command_leaves_no_folder_behind(tmp_path: Path) -> None:
    """A folder the lock made and nothing was written into goes again (its lone lock file would mark the path
    as a yawil run); a folder that existed, or got a file, stays."""
    with pytest.raises(ValueError, match="bad data"), folder_lock(tmp_path / "new" / "run", "training run"):
        raise ValueError("bad data")
    assert not (tmp_path / "new" / "run").exists()
    (tmp_path / "mine").mkdir()
    with folder_lock(tmp_path / "mine", "training run"):
        pass
    assert (tmp_path / "mine").is_dir()
    with folder_lock(tmp_path / "made", "training run") as folder:
        (folder / "config.json").write_text("{}")
    assert (tmp_path / "made" / "config.json").is_file()


@pytest.mark.parametrize("what, sig", [("dataset", "manifest.json"), ("training run", "config.yaml"),
                                       ("results folder", "run.json"), ("DAgger run", "dagger.json")])
def test_a_work_folder_is_new_empty_or_of_its_own_kind(tmp_path: Path, what: str, sig: str) -> None:
    """A user's folder (or another stage's) is refused before anything is written there; its own kind resumes."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's file")
    with pytest.raises(ValueError, match=f"no {sig}, so it is not a yawil {what}"), folder_lock(mine, what):
        pass
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]  # no lock file left behind either
    (mine / sig).write_text("{}")
    with folder_lock(mine, what):
        pass
    (tmp_path / "empty").mkdir()
    with folder_lock(tmp_path / "empty", what):
        pass
