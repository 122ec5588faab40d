"""Where a driving network's forward pass runs at drive time: one call per simulation step for a batch of episodes.

    engine = make_engine(model, runtime, "auto")      # torch (bf16 CPUs, CUDA), onnxruntime (fp32 CPUs)
    out = engine.run(x, attention=False)             # x: ModelInputs of B frames -> NetOutput (numpy, B rows)

Engines (chosen by measurement, docs/decisions.md "Inference engines"; figures in docs/performance.md):
- `torch`: the model itself, eager, under the Runtime's autocast (the trainer's numerics); bf16 + channels_last
  on CPUs with native bf16, the CUDA engine.
- `onnxruntime`: the model exported to ONNX (batch-norm folded by ORT's graph optimiser), fp32.
- `openvino` (opt-in, `pip install openvino`): the model converted by OpenVINO, bf16 where the CPU has native
  bf16: the fastest float engine at batch 1 on the CPUs measured, but a process that has run it crashed (SIGSEGV)
  at a later fork in the test suite, so it is never chosen by `auto`.
- `openvino-int8` (opt-in, `pip install openvino nncf`): the same graph with int8 convolutions, quantized after
  training on expert frames (`yawil.policy.quantize`): a different driver from the float engines (close, not
  equal), so it is only used when asked for and its label goes into every record.
`auto` picks torch on a CPU with native bf16 and on CUDA, onnxruntime on any other CPU: on the CPUs measured
these are the fastest engines whose row of a batch does not depend on the other rows or the batch size (bit for
bit), which the benchmark's determinism needs (an episode drives the same alone or among others); torch fp32 is
not (1e-7 between batch 1 and 8), ONNX Runtime fp32 is.

A graph engine compiles one static-shape graph per batch size it meets (OpenVINO; a fraction of a second each),
keeps the attention maps as outputs and copies them only when asked.
"""

from __future__ import annotations

import io
import warnings
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from yawil.policy.inputs import ModelInputs, example_inputs, input_names
from yawil.policy.runtime import Runtime
from yawil.policy.speed import ENGINES


@dataclass(frozen=True)
class NetOutput:
    """One forward pass of B rows, as float32 numpy arrays."""

    actions: np.ndarray  # [B, 3] steer, throttle, brake
    speed: np.ndarray  # [B] predicted speed, normalised (Norm.speed_inverse gives m/s)
    aux: np.ndarray | None  # [B, n] raw aux outputs (models built with aux=true)
    branches: np.ndarray | None  # [B, 4, 3] command models
    attention: list[np.ndarray]  # [B, h, w] per attended layer; [] unless asked for (or the model has none)


def graph_outputs(model: Any, image_size: tuple[int, int] = (88, 200)) -> list[str]:
    """The outputs of the model's graph, in order: actions, pred_speed, then aux, branches (where the model has
    them) and attention_0.. (ONNX forbids reusing the input name `speed`, hence pred_speed)."""
    with torch.no_grad():
        out = ModelInputs(**example_inputs(model, 1, image_size=image_size)).forward(model)
    return (["actions", "pred_speed"] + (["aux"] if out.aux is not None else [])
            + (["branches"] if out.branches is not None else []) + [f"attention_{i}" for i in range(len(out.attention))])


def graph_module(model: Any) -> torch.nn.Module:
    """The model with positional inputs (`input_names`) and a flat tuple of outputs (`graph_outputs`): what ONNX
    export and OpenVINO's converter trace."""
    names = input_names(model)

    class Flat(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
            out = ModelInputs(**dict(zip(names, args, strict=True))).forward(self.model)
            extra = [t for t in (out.aux, out.branches) if t is not None]
            return (out.actions, out.speed, *extra, *out.attention)

    return Flat().eval()


Calibration = tuple[Callable[[], list[list[np.ndarray]]], dict[str, Any]]
"""What an int8 engine is calibrated on: a maker of frames (input lists, batch 1 each) and what describes them
(for the cache key)."""


class Engine(ABC):
    """Runs one network on a batch of prepared inputs."""

    name: str
    precision: str

    @property
    def label(self) -> str:
        """engine-precision, as records and tables name it (e.g. openvino-bf16)."""
        return f"{self.name}-{self.precision}"

    @property
    def option(self) -> str:
        """The --engine value that makes this engine here (int8 is an engine of its own, the rest a precision)."""
        return self.label if self.precision == "int8" else self.name

    @abstractmethod
    def run(self, x: ModelInputs, attention: bool = False) -> NetOutput:
        """The outputs of B rows; attention maps only when `attention`."""


class TorchEngine(Engine):
    name = "torch"

    def __init__(self, model: torch.nn.Module, runtime: Runtime) -> None:
        self.model, self.runtime, self.precision = model, runtime, runtime.precision

    @torch.inference_mode()
    def run(self, x: ModelInputs, attention: bool = False) -> NetOutput:
        with self.runtime.autocast():
            out = x.forward(self.model)

        def np32(t: torch.Tensor) -> np.ndarray:
            return t.float().cpu().numpy()

        return NetOutput(np32(out.actions), np32(out.speed)[:, 0], None if out.aux is None else np32(out.aux),
                         None if out.branches is None else np32(out.branches),
                         [np32(a) for a in out.attention] if attention else [])


class GraphEngine(Engine):
    """A traced graph run by OpenVINO or ONNX Runtime on the CPU, one thread pool of `threads` (torch's count)."""

    def __init__(self, model: torch.nn.Module, kind: str, precision: str, threads: int,
                 image_size: tuple[int, int] = (88, 200), calibration: Calibration | None = None,
                 float_hint: str = "bf16") -> None:
        self.name, self.precision, self.threads = kind, precision, max(1, int(threads))
        self._hint = {"bf16": "bf16", "fp32": "f32", "int8": "bf16" if float_hint == "bf16" else "f32"}[precision]
        self.inputs = input_names(model)
        self.outputs = graph_outputs(model, image_size)
        example = tuple(example_inputs(model, 1, image_size=image_size).values())
        self._shapes = [list(t.shape[1:]) for t in example]  # one row's shape of each input
        flat = graph_module(model)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on shape checks traced as constants: intended
            if kind == "openvino":
                import openvino as ov

                self._ov = ov
                self._graph = ov.convert_model(flat, example_input=example)
                if precision == "int8":
                    self._graph = self._quantized(calibration)
            else:
                buf = io.BytesIO()
                dynamic = {n: {0: "batch"} for n in self.inputs + self.outputs}
                torch.onnx.export(flat, example, buf, input_names=self.inputs,  # type: ignore[arg-type]
                                  output_names=self.outputs, dynamic_axes=dynamic, opset_version=17, dynamo=False)
                self._onnx = buf.getvalue()
        self._compiled: dict[int, Any] = {}

    def _quantized(self, calibration: Calibration | None) -> Any:
        """The batch-1 graph with int8 convolutions (cached by weights, shapes and calibration)."""
        from yawil.policy.quantize import graph_key, int8_graph

        if calibration is None:
            raise ValueError("engine 'openvino-int8' needs calibration frames (an Agent gives them)")
        make, about = calibration
        graph = self._graph.clone()
        graph.reshape({i: [1, *shape] for i, shape in enumerate(self._shapes)})
        return int8_graph(graph, make, graph_key(graph, about))

    def _session(self, batch: int) -> Any:
        """The compiled graph: OpenVINO one per batch size (static shapes), ONNX Runtime one for all."""
        key = batch if self.name == "openvino" else 0
        if key not in self._compiled:
            self._compiled[key] = self._compile(batch)
        return self._compiled[key]

    def _compile(self, batch: int) -> Any:
        if self.name == "openvino":
            graph = self._graph.clone()
            graph.reshape({i: [batch, *shape] for i, shape in enumerate(self._shapes)})
            compiled = self._ov.Core().compile_model(graph, "CPU", {
                "INFERENCE_NUM_THREADS": self.threads, "INFERENCE_PRECISION_HINT": self._hint, "NUM_STREAMS": 1,
                "PERFORMANCE_HINT": "LATENCY", "ENABLE_CPU_PINNING": False})  # pinned, two workers share core 0
            return compiled.create_infer_request()
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads = self.threads, 1
        opts.log_severity_level = 3
        return ort.InferenceSession(self._onnx, opts, providers=["CPUExecutionProvider"])

    def run(self, x: ModelInputs, attention: bool = False) -> NetOutput:
        feed = [np.ascontiguousarray(t.detach().cpu().numpy()) for t in x.named().values()]
        batch = feed[0].shape[0]
        if self.name == "openvino":
            request = self._session(batch)
            request.infer(feed)
            got = [request.get_output_tensor(i).data for i in range(len(self.outputs))]
        else:
            got = self._session(batch).run(None, dict(zip(self.inputs, feed, strict=True)))
        by = dict(zip(self.outputs, got, strict=True))

        def take(name: str) -> np.ndarray | None:
            return np.array(by[name], dtype=np.float32) if name in by else None  # a copy: the request reuses its memory

        maps = [np.array(by[n], dtype=np.float32) for n in self.outputs if n.startswith("attention")] if attention else []
        actions, speed = take("actions"), take("pred_speed")
        assert actions is not None and speed is not None
        return NetOutput(actions, speed[:, 0], take("aux"), take("branches"), maps)


def resolve_engine(name: str, runtime: Runtime) -> tuple[str, str]:
    """(engine, precision) of `--engine NAME` on this runtime. The runtime's precision says the numerics (bf16
    where the CPU has it natively, else fp32; `resolve_runtime`), the engine their implementation: `auto` is
    torch for bf16 and on CUDA, onnxruntime for fp32 (the module's docstring says why)."""
    if name not in ENGINES:
        raise ValueError(f"engine {name!r}: expected one of {', '.join(ENGINES)}")
    if runtime.device.type == "cuda" or name == "torch":
        if name not in ("auto", "torch"):
            raise ValueError(f"engine {name!r} runs on the CPU; on CUDA use torch (or auto)")
        return "torch", runtime.precision
    if name == "auto":
        name = "torch" if runtime.precision == "bf16" else "onnxruntime"
        if name == "torch":
            return name, runtime.precision
    if name == "openvino-int8":
        from yawil.policy.quantize import require_nncf

        require_nncf()
        return "openvino", "int8"
    if name == "openvino":
        import importlib.util

        if importlib.util.find_spec("openvino") is None:
            raise ValueError("engine 'openvino' needs the openvino package: pip install openvino")
    return name, "bf16" if name == "openvino" and runtime.precision == "bf16" else "fp32"


def image_size(model: Any) -> tuple[int, int]:
    """The camera size a model takes (its config's image_size; 88 x 200, CIL's crop, by default)."""
    size = getattr(model, "config", {}).get("image_size")
    return (int(size[0]), int(size[1])) if size else (88, 200)


def make_engine(model: torch.nn.Module, runtime: Runtime, name: str = "auto",
                calibration: Calibration | None = None) -> Engine:
    """The engine `name` for a model in eval mode (see the module's docstring); `calibration` only for
    openvino-int8."""
    kind, precision = resolve_engine(name, runtime)
    if kind == "torch":
        return TorchEngine(model, runtime)
    return GraphEngine(model, kind, precision, torch.get_num_threads(), image_size(model), calibration,
                       float_hint=runtime.precision)
