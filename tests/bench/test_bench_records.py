"""The results file: append-only JSON lines, resume with a truncated last line, run identity."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from yawil.bench.records import (
    EPISODES_FILE,
    PROTOCOL,
    RUN_FILE,
    EpisodeLog,
    check_run_info,
    episode_key,
    iter_results,
    read_records,
)


def _rec(i: int) -> dict:
    return {"protocol": PROTOCOL, "task": "straight", "condition": "training", "weather": "ClearNoon", "route_id": i,
            "seed": 0, "success": True, "km_driven": 0.1}


def test_append_and_resume(tmp_path: Path) -> None:
    with EpisodeLog(tmp_path) as log:
        for i in range(3):
            log.append(_rec(i))
    log2 = EpisodeLog(tmp_path)
    assert len(log2.records) == 3 and "straight/training/ClearNoon/1/0" in log2
    with pytest.raises(ValueError, match="already"):
        log2.append(_rec(1))
    log2.close()


def test_partial_last_line_is_ignored_and_cut(tmp_path: Path) -> None:
    with EpisodeLog(tmp_path) as log:
        log.append(_rec(0))
        log.append(_rec(1))
    path = tmp_path / EPISODES_FILE
    full = path.read_bytes()
    path.write_bytes(full + json.dumps(_rec(2)).encode()[:25])  # killed mid-write
    assert [r["route_id"] for r in read_records(path)] == [0, 1]
    with EpisodeLog(tmp_path) as log:
        assert path.read_bytes() == full  # the partial line was cut
        log.append(_rec(2))
    lines = path.read_text().splitlines()
    assert [json.loads(x)["route_id"] for x in lines] == [0, 1, 2]


def test_complete_json_without_newline_is_partial(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / EPISODES_FILE
    path.write_text(json.dumps(_rec(0)) + "\n" + json.dumps(_rec(1)))
    assert len(read_records(path)) == 1
    assert len(list(iter_results(tmp_path))) == 1  # the report's reading says what it leaves out
    err = capsys.readouterr().err
    assert "line 2 is an unfinished record" in err and err.count("\n") == 1


def test_corrupt_middle_line_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / EPISODES_FILE
    path.write_text(json.dumps(_rec(0)) + "\n{oops\n" + json.dumps(_rec(1)) + "\n")
    with pytest.raises(ValueError, match=r"episodes.jsonl: line 2"):
        read_records(path)


def test_duplicate_keys_in_file_are_an_error(tmp_path: Path) -> None:
    path = tmp_path / EPISODES_FILE
    path.write_text(json.dumps(_rec(0)) + "\n" + json.dumps(_rec(0)) + "\n")
    with pytest.raises(ValueError, match="repeats"):
        EpisodeLog(tmp_path)


def test_key_and_run_identity(tmp_path: Path) -> None:
    assert episode_key(_rec(4)) == "straight/training/ClearNoon/4/0"
    with pytest.raises(ValueError, match="route_id"):
        episode_key({"task": "x", "condition": "y", "weather": "w", "seed": 0})
    check_run_info(tmp_path, {"agent": "expert", "agent_options": {}})
    check_run_info(tmp_path, {"agent": "expert", "agent_options": {}})
    with pytest.raises(ValueError, match="another --out"):
        check_run_info(tmp_path, {"agent": "/x/best.pt", "agent_options": {}})


def test_a_changed_checkpoint_or_label_is_refused_on_resume(tmp_path: Path) -> None:
    from yawil.bench.runner import AgentSpec

    ckpt = tmp_path / "best.pt"
    ckpt.write_bytes(b"weights one")
    spec = AgentSpec(str(ckpt))
    info = {"agent": spec.identity(), "agent_options": {}, "label": "a", "agent_sha256": spec.content_hash()}
    out = tmp_path / "r"
    out.mkdir()
    check_run_info(out, info)
    check_run_info(out, info, label_given=True)
    with pytest.raises(ValueError, match="label"):
        check_run_info(out, {**info, "label": "b"}, label_given=True)
    check_run_info(out, {**info, "label": "b"})  # the default label (the folder's name) is not a choice
    ckpt.write_bytes(b"weights two")  # another model written to the same path
    assert spec.content_hash() != info["agent_sha256"]
    with pytest.raises(ValueError, match="has changed"):
        check_run_info(out, {**info, "agent_sha256": spec.content_hash()})
    assert AgentSpec("expert").content_hash() is None


def test_a_moved_checkpoint_resumes_its_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Records name a checkpoint under the working folder relatively (a repository's records read the same on every
    clone), and a resume compares the weights, so a clone elsewhere resumes; other weights at the path are refused."""
    import shutil

    from yawil.bench.runner import AgentSpec

    for clone in ("a", "b"):
        (tmp_path / clone / "runs").mkdir(parents=True)
    (tmp_path / "a" / "runs" / "best.pt").write_bytes(b"weights one")
    shutil.copy(tmp_path / "a" / "runs" / "best.pt", tmp_path / "b" / "runs" / "best.pt")
    out = tmp_path / "r"
    out.mkdir()
    for clone in ("a", "b"):
        monkeypatch.chdir(tmp_path / clone)
        spec = AgentSpec("runs/best.pt")
        assert spec.identity() == "runs/best.pt"
        check_run_info(out, {"agent": str(tmp_path / clone / "runs" / "best.pt"), "agent_options": {},
                             "agent_sha256": spec.content_hash()})  # the absolute path of a moved clone
    (tmp_path / "b" / "runs" / "best.pt").write_bytes(b"weights two")
    with pytest.raises(ValueError, match="another --out"):
        check_run_info(out, {"agent": "runs/best.pt", "agent_options": {}, "agent_sha256": spec.content_hash()})
    assert AgentSpec(str(tmp_path / "b" / "runs" / "best.pt")).identity() == "runs/best.pt"


def test_iter_results_refuses_a_repeated_episode(tmp_path: Path) -> None:
    (tmp_path / EPISODES_FILE).write_text(json.dumps(_rec(0)) + "\n" + json.dumps(_rec(1)) + "\n" + json.dumps(_rec(0)) + "\n")
    with pytest.raises(ValueError, match="record 3 repeats episode straight/training/ClearNoon/0/0"):
        list(iter_results(tmp_path))


@pytest.mark.parametrize("change, message", [
    ({"success": "yes"}, "success='yes', expected true or false"),
    ({"route_id": -3}, "route_id=-3, expected an integer >= 0"),
    ({"km_driven": None}, "km_driven=None"),
    ({"red_lights": -1}, "red_lights=-1"),
])
def test_iter_results_refuses_a_record_it_cannot_count(tmp_path: Path, change: dict, message: str) -> None:
    (tmp_path / EPISODES_FILE).write_text(json.dumps(_rec(0)) + "\n" + json.dumps({**_rec(1), **change}) + "\n")
    with pytest.raises(ValueError, match=f"record 2: {message}"):
        list(iter_results(tmp_path))
    rec = _rec(2)
    del rec["success"]
    (tmp_path / EPISODES_FILE).write_text(json.dumps(rec) + "\n")
    with pytest.raises(ValueError, match="field 'success' is missing"):
        list(iter_results(tmp_path))


def test_iter_results_needs_a_results_folder(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="episodes.jsonl"):
        list(iter_results(tmp_path))


def test_results_of_another_protocol_are_refused(tmp_path: Path) -> None:
    """Protocol 1 (each route in one weather, one timeout): refused on resume and by the report's reader."""
    check_run_info(tmp_path, {"agent": "expert", "agent_options": {}})
    assert json.loads((tmp_path / RUN_FILE).read_text())["protocol"] == PROTOCOL
    (tmp_path / RUN_FILE).write_text(json.dumps({"agent": "expert", "agent_options": {}}))  # written before protocol 2
    with pytest.raises(ValueError, match="protocol 1 .*new folder"):
        check_run_info(tmp_path, {"agent": "expert", "agent_options": {}})
    old = {k: v for k, v in _rec(0).items() if k != "protocol"}
    (tmp_path / EPISODES_FILE).write_text(json.dumps(old) + "\n")
    with pytest.raises(ValueError, match="record 1: written under benchmark protocol 1"):
        list(iter_results(tmp_path))
