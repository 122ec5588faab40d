"""`yawil data check|stats|subset`: bad files named, Figure 7 written, subset selection exact."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from yawil.cli import main
from yawil.data.check import check_dataset
from yawil.data.dataset import DrivingDataset
from yawil.data.manifest import read_manifest
from yawil.data.stats import compute_stats, write_stats
from yawil.data.subset import select_rows, write_subset
from yawil.data.synthetic import write_synthetic_dataset
from yawil.sim.types import RoadOption

K = 3
L, R, S, F = (int(RoadOption.LEFT), int(RoadOption.RIGHT), int(RoadOption.STRAIGHT), int(RoadOption.LANEFOLLOW))


def test_check_names_truncated_and_nan_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = write_synthetic_dataset(tmp_path, episodes=4, frames=6, k=K)
    assert check_dataset(tmp_path).ok
    assert main(["data", "check", str(tmp_path)]) == 0
    p0, p1, p2 = (m.path_of(e) for e in m.episodes[:3])
    with open(p0, "r+b") as f:
        f.truncate(os.path.getsize(p0) - 1000)
    with h5py.File(p1, "r+") as f:
        f["speed"][4] = np.nan
    with h5py.File(p2, "r") as f:  # overwrite the compressed bytes of one image chunk
        offset = f["image"].id.get_chunk_info(3).byte_offset
    with open(p2, "r+b") as f:
        f.seek(offset + 16)
        f.write(b"\xff" * 1024)
    (tmp_path / "episodes" / "ep_000099.h5").write_bytes(b"orphan")
    report = check_dataset(tmp_path)
    assert not report.ok and set(report.bad) == {f"episodes/ep_00000{i}.h5" for i in range(3)}
    assert "truncated" in report.bad["episodes/ep_000000.h5"][0]
    assert report.bad["episodes/ep_000001.h5"] == ["speed: NaN or inf at 1 row(s), first row 4"]
    assert "cannot be decoded" in report.bad["episodes/ep_000002.h5"][0]
    assert check_dataset(tmp_path, images=False).bad.keys() == {"episodes/ep_000000.h5", "episodes/ep_000001.h5"}
    assert any("ep_000099.h5 is not in the manifest" in n for n in report.notes)
    assert report.frames == 6
    capsys.readouterr()
    assert main(["data", "check", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "BAD episodes/ep_000001.h5" in out and out.rstrip().endswith("FAILED")


def test_check_catches_a_flipped_byte_that_still_decodes(tmp_path: Path) -> None:
    """64 bytes inverted inside an image chunk: lzf may still decode it, the fletcher32 checksum does not pass."""
    m = write_synthetic_dataset(tmp_path, episodes=2, frames=6, k=K)
    path = m.path_of(m.episodes[0])
    with h5py.File(path, "r") as f:
        info = f["image"].id.get_chunk_info(2)
    with open(path, "r+b") as f:
        f.seek(info.byte_offset + info.size // 2)
        data = f.read(64)
        f.seek(info.byte_offset + info.size // 2)
        f.write(bytes(255 - b for b in data))
    bad = check_dataset(tmp_path).bad
    assert list(bad) == ["episodes/ep_000000.h5"] and "cannot be decoded" in bad["episodes/ep_000000.h5"][0]


def test_check_out_of_range_and_missing(tmp_path: Path) -> None:
    m = write_synthetic_dataset(tmp_path, episodes=2, frames=5, k=K)
    with h5py.File(m.path_of(m.episodes[0]), "r+") as f:
        f["steer"][1] = 1.5
        f["command"][2] = 7
    m.path_of(m.episodes[1]).unlink()
    bad = check_dataset(tmp_path).bad
    assert "steer: 1 value(s) out of [-1.0, 1.0], first 1.5 at row 1" in bad["episodes/ep_000000.h5"][0]
    assert "command: 1 invalid value(s), first 7 at row 2" in bad["episodes/ep_000000.h5"][0]
    assert "missing" in bad["episodes/ep_000001.h5"][0]


def test_stats_counts_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    m = write_synthetic_dataset(tmp_path / "d", episodes=4, frames=10, k=K)
    st = compute_stats(tmp_path / "d")
    assert st.frames == 40 and st.by_weather() == m.by_weather()
    assert st.by_option() == {name: m.by_command()[name] for name in ("LEFT", "RIGHT", "STRAIGHT", "LANEFOLLOW")}
    assert all(int(h.sum()) == 40 for h in st.histograms.values())
    png = write_stats(tmp_path / "d", tmp_path / "fig" / "stats.png")
    assert png == tmp_path / "fig" / "stats.png" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "by road option: LEFT" in capsys.readouterr().out
    assert main(["data", "stats", str(tmp_path / "d")]) == 0
    assert (tmp_path / "d" / "stats.png").stat().st_size > 10_000


def test_subset_selection_rules() -> None:
    command = np.array([L, R, S, F, F, L])
    curve = np.array([0, 0, 0, 0, 1, 1], dtype=np.uint8)  # a LEFT frame flagged as curve is still a junction turn
    assert select_rows(command, curve, "road-option-turns").tolist() == [True, True, True, True, False, True]
    assert select_rows(command, curve, "lane-follow-turns").tolist() == [False, False, True, True, True, False]
    assert select_rows(command, curve, "all").all()
    with pytest.raises(ValueError, match="subset must be one of"):
        select_rows(command, curve, "turns")


def test_subset_writes_a_dataset(tmp_path: Path) -> None:
    full = tmp_path / "full"
    write_synthetic_dataset(full, episodes=3, frames=30, k=K)
    assert main(["data", "subset", str(full), "--only", "road-option-turns", "--out", str(tmp_path / "s1")]) == 0
    write_subset(full, tmp_path / "s2", "lane-follow-turns")
    src = DrivingDataset(full)
    s1, s2 = DrivingDataset(tmp_path / "s1"), DrivingDataset(tmp_path / "s2")
    ro, lft = src.labels("road_option"), src.labels("lane_follow_turn")
    assert len(s1) == int((~lft).sum()) and not s1.labels("lane_follow_turn").any()
    assert len(s2) == int((~np.isin(ro, (L, R))).sum()) and not np.isin(s2.labels("road_option"), (L, R)).any()
    assert s2.labels("lane_follow_turn").sum() == lft.sum() > 0
    # Rows are copies of the source's: same (episode, frame) keys, same images and labels.
    key = {(e, f): i for i, (e, f) in enumerate(zip(src.labels("episode"), src.labels("frame"), strict=True))}
    for i in (0, len(s2) // 2, len(s2) - 1):
        a = s2[i]
        b = src[key[(int(a["episode"]), int(a["frame"]))]]
        for name in a:
            assert bool((a[name] == b[name]).all()), name
    assert check_dataset(tmp_path / "s2").ok
    assert read_manifest(tmp_path / "s1").config["subset"]["only"] == "road-option-turns"
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary directory was renamed away
    # Same subset again: nothing to do; another subset into an existing directory: refused.
    assert main(["data", "subset", str(full), "--only", "road-option-turns", "--out", str(tmp_path / "s1")]) == 0
    assert main(["data", "subset", str(full), "--only", "all", "--out", str(tmp_path / "s1")]) == 2
