"""The one model-input contract (`yawil.policy.inputs`): a dataset batch, a stored frame and an Observation of the
same frame give the same network inputs, and a fixed checkpoint acts the same through the agent, the heat maps
and the ONNX graph."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from test_agent import GC, K, observation
from yawil.agent import Agent
from yawil.data.dataset import DrivingDataset
from yawil.data.reader import open_episode
from yawil.explain import attention
from yawil.policy.checkpoint import Norm
from yawil.policy.inputs import InputSpec, guidance_key, input_names
from yawil.policy.runtime import resolve_runtime
from yawil.sim.types import RoadOption, command_index

torch.set_num_threads(1)

CASES = [("yaw-guided", {"guidance_dim": K}), ("xy-guided", {"guidance_dim": 2 * K}), ("cil", {})]


def _batch_of(x_image: np.ndarray, speed: float, option: int, guidance: dict[str, np.ndarray]) -> dict[str, Any]:
    """One frame as the DataLoader gives it: image uint8 [1, 3, H, W], speed [1, 1], command a branch index."""
    return {
        "image": torch.from_numpy(np.ascontiguousarray(x_image.transpose(2, 0, 1)))[None],
        "speed": torch.tensor([[speed]], dtype=torch.float32),
        "command": torch.tensor([command_index(option)], dtype=torch.int64),
        "action": torch.zeros(1, 3),
        **{guidance_key(kind): torch.from_numpy(v.copy())[None] for kind, v in guidance.items()},
    }


@pytest.mark.parametrize("channels_last", ["auto", "off"])
@pytest.mark.parametrize(("name", "cfg"), CASES)
def test_a_batch_and_an_observation_of_one_frame_give_the_same_inputs(
    tiny_checkpoint: Any, name: str, cfg: dict[str, Any], channels_last: str
) -> None:
    path, norm = tiny_checkpoint(name, guidance=GC, spread=True, dropout=0.0, **cfg)
    agent = Agent.from_checkpoint(path, precision="fp32", channels_last=channels_last)
    obs = observation(RoadOption.LEFT, speed=4.25, seed=3)
    x, g_raw, cmd = agent.model_inputs(obs)
    assert obs.image is not None
    guidance: dict[str, np.ndarray] = {}
    if agent.kind is not None:
        assert g_raw is not None
        guidance[agent.kind] = g_raw
    raw = _batch_of(obs.image, obs.speed, int(obs.command), guidance)
    y = InputSpec.of(agent.model, norm, resolve_runtime("cpu", "fp32", channels_last)).from_batch(raw)
    assert list(x.named()) == list(y.named()) == input_names(agent.model)
    for key, a in x.named().items():
        b = y.named()[key]
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b), key
    assert x.image.dtype == torch.float32 and float(x.image.max()) <= 1.0
    assert x.speed_raw is not None and y.speed_raw is not None and torch.equal(x.speed_raw, y.speed_raw)
    if channels_last == "auto":  # both in channels_last memory, as the model is
        assert x.image.is_contiguous(memory_format=torch.channels_last)
        assert y.image.is_contiguous(memory_format=torch.channels_last)
    else:  # the batch stays NCHW; the frame is a permuted view of the camera's HWC buffer (as it always was)
        assert y.image.is_contiguous()
    assert (cmd is None) == (agent.kind is not None) and (g_raw is None) == (agent.kind is None)
    if cmd is not None:
        assert x.command is not None and int(x.command[0]) == cmd == command_index(RoadOption.LEFT)
    # the dict form of Agent.inputs is the same tensors by name
    d, _, _ = Agent.from_checkpoint(path, precision="fp32", channels_last=channels_last).inputs(obs)
    assert list(d) == ["image", "speed", "guidance", "command"]
    assert all((v is None) == (x.as_dict()[k] is None) for k, v in d.items())


def test_a_stored_frame_and_its_dataset_sample_give_the_same_inputs(tiny_dataset: Any) -> None:
    ds = DrivingDataset(tiny_dataset(episodes=1, frames=4, k=K))
    raw = default_collate([ds[0], ds[1], ds[2]])
    norm = Norm(2.0, 3.0, tuple(np.linspace(-0.2, 0.2, K)), tuple(np.linspace(0.5, 2.0, K)))
    runtime = resolve_runtime("cpu", "fp32", "auto")
    for uses_command in (False, True):
        spec = InputSpec(norm, "yaw", uses_command, runtime)
        batch = spec.from_batch(raw)
        with open_episode(ds.episodes[0].path) as ep:
            frames = [spec.from_record(ep[i]) for i in range(3)]
        for i, f in enumerate(frames):
            for key, a in f.named().items():
                assert torch.equal(a[0], batch.named()[key][i]), (i, key)
    with pytest.raises(ValueError, match="guidance kind"):
        guidance_key("heading")


def test_a_fixed_checkpoint_acts_the_same_through_agent_explain_and_onnx(tmp_path: Path, tiny_checkpoint: Any) -> None:
    pytest.importorskip("onnxruntime")
    import onnxruntime as ort

    from yawil.learn.export import export_onnx

    path, _ = tiny_checkpoint("yaw-guided", guidance=GC, spread=True, guidance_dim=K, dropout=0.0)
    agent = Agent.from_checkpoint(path, precision="fp32")
    session = ort.InferenceSession(str(export_onnx(path, tmp_path / "m.onnx")), providers=["CPUExecutionProvider"])
    agent.reset()
    for seed, speed in ((0, 0.0), (1, 3.5), (2, 7.0)):
        obs = observation(speed=speed, seed=seed)
        control = agent.act(obs)
        assert agent.last is not None and agent.last.guidance is not None
        x = agent.spec.from_frame(obs.image, obs.speed, agent.last.guidance)  # the inputs the agent acted on
        # heat maps: the same frame as a stored record (its guidance as the collector would store it)
        record = SimpleNamespace(image=obs.image, speed=obs.speed, command=int(obs.command),
                                 guidance_yaw=agent.last.guidance, guidance_xy=None, guidance_sim_yaw=None)
        item = attention.explain_record(agent, record)
        assert (item.steer, item.throttle, item.brake) == (control.steer, control.throttle, control.brake)
        assert item.speed == agent.last.speed
        # ONNX: the contract's inputs by name, in the graph's order
        feeds = {k: np.ascontiguousarray(v.numpy()) for k, v in x.named().items()}
        assert [i.name for i in session.get_inputs()] == list(feeds)
        actions = session.run(["actions"], feeds)[0][0]
        np.testing.assert_allclose(actions, agent.last.actions, atol=1e-5)
