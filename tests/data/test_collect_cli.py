"""`yawil collect`'s flags take their defaults from CollectConfig (one place for each default)."""

from __future__ import annotations

from dataclasses import fields

import pytest

from yawil.cli import build_parser
from yawil.data.collect_cli import config_from_args
from yawil.data.collect_config import CollectConfig


def test_flag_defaults_are_the_dataclass_defaults() -> None:
    args = build_parser().parse_args(["collect", "--out", "somewhere"])
    assert config_from_args(args) == CollectConfig()


def test_flags_reach_the_config() -> None:
    args = build_parser().parse_args(["collect", "--out", "x", "--vehicles", "3-7", "--pedestrians", "4", "--noise", "0.2",
                                      "--straight-keep", "1", "--on-collision", "discard", "--town", "town02"])
    cfg = config_from_args(args)
    changed = {f.name for f in fields(CollectConfig) if getattr(cfg, f.name) != getattr(CollectConfig(), f.name)}
    assert changed == {"vehicles", "pedestrians", "noise_fraction", "straight_keep", "on_collision", "town"}
    assert (cfg.vehicles, cfg.pedestrians, cfg.noise_fraction, cfg.on_collision) == ((3, 7), (4, 4), 0.2, "discard")


def test_the_guidance_reference_flag(capsys: pytest.CaptureFixture[str]) -> None:
    assert build_parser().parse_args(["collect", "--out", "x"]).guidance_reference == "route"  # the paper's
    assert build_parser().parse_args(["collect", "--out", "x", "--guidance-reference", "ego"]).guidance_reference == "ego"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["collect", "--out", "x", "--guidance-reference", "north"])
    assert "invalid choice: 'north'" in capsys.readouterr().err
