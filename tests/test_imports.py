"""The import rule of docs/architecture.md, checked on the import graph of `src/yawil`.

Every module belongs to a layer, and the layers follow the data flow, lowest first:

     0 base       yawil (the package: version, Gymnasium registration), executor, fileio, locking, stages, video,
                  zoo (the catalogue of shipped models: names, cards, paths; torch-free)
     1 sim        yawil.sim (both worlds, types, the episode judge and criteria, the CARLA backend)
     2 guidance   yawil.guidance (a route -> a guidance vector)
     3 expert     yawil.expert
     4 gym_env    yawil.gym_env (the Gymnasium wrapper: a world, guidance and the expert's action)
     5 data       yawil.data (schema, files, dataset, collection)
     6 models     yawil.models
     7 policy     yawil.policy (checkpoint format and model rebuild, the model-input contract, runtime)
     8 learn      yawil.learn (config, sampling, loss, validation, loop, augmentation, DDP, ONNX export)
     9 agent      yawil.agent, yawil.zoo.pack and yawil.zoo.cli (packing and checking zoo models drive the agent)
    10 bench      yawil.bench (suites, route files, runner, metrics, report, experiments, select)
    11 explain    yawil.explain (attention maps, figures, videos)
    12 pipelines  yawil.pipelines (demo, reproduce, dagger)
    13 command    yawil.cli

The rules (every `import` and `from ... import` counts, at module level or inside a function, since a lazy
import is still a dependency):
1. A module imports only modules of its own layer or of lower layers.
2. CLI modules are the command layer of their package: `cli.py`, `*_cli.py` and `__main__.py` (and `yawil.cli`,
   the top). A CLI module has its package's layer, so it may import its own package and anything below it;
   the other modules of that layer never import it (within a layer, the command line sits on top: the
   library does not go through argparse). A module of a higher layer may (as `yawil.pipelines.dagger`'s
   command line uses `yawil.learn.cli`'s KEY=VALUE parser).
3. Nothing under `yawil.sim` or in `yawil.guidance` imports torch (the simulator and guidance are numpy).
4. `yawil.models` imports nothing of `yawil.sim` (the models take tensors only).

A new top-level module or package must be given a layer in `LAYERS` below: the test fails until it is.
Imports through strings (the Gymnasium entry point, `yawil.cli.COMMANDS`) are not imports to this test,
except `importlib.import_module` with a constant name.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"

# (layer name, module prefixes), lowest first. A module belongs to the layer of its longest matching prefix.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("yawil", "yawil.cliargs", "yawil.executor", "yawil.fileio", "yawil.locking", "yawil.provenance", "yawil.signals", "yawil.stages", "yawil.video",
              "yawil.zoo")),
    ("sim", ("yawil.sim",)),
    ("guidance", ("yawil.guidance",)),
    ("expert", ("yawil.expert",)),
    ("gym_env", ("yawil.gym_env",)),
    ("data", ("yawil.data",)),
    ("models", ("yawil.models",)),
    ("policy", ("yawil.policy",)),
    ("learn", ("yawil.learn",)),
    ("agent", ("yawil.agent", "yawil.zoo.pack", "yawil.zoo.cli")),
    ("bench", ("yawil.bench",)),
    ("explain", ("yawil.explain",)),
    ("pipelines", ("yawil.pipelines",)),
    ("command", ("yawil.cli",)),
)
NO_TORCH = ("yawil.sim", "yawil.guidance")  # rule 3
FORBIDDEN: tuple[tuple[str, str], ...] = (("yawil.models", "yawil.sim"),)  # rule 4: (importer, imported) prefixes


@dataclass(frozen=True)
class Import:
    importer: str  # module name
    imported: str  # the module it names (a submodule when `from pkg import submodule`)
    line: int


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def module_name(path: Path, src: Path) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules(src: Path) -> dict[str, Path]:
    return {module_name(p, src): p for p in sorted((src / "yawil").rglob("*.py"))}


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    """Every import in the file, at any depth, as the module it names (relative imports resolved)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[Import] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [Import(name, a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.append(Import(name, sub if sub in modules else target, node.lineno))
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append(Import(name, node.args[0].value, node.lineno))
    return found


def layer_of(name: str) -> int | None:
    best: tuple[int, int] | None = None  # (prefix length, layer)
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            matches = name == prefix if prefix == "yawil" else _under(name, prefix)
            if matches and (best is None or len(prefix) > best[0]):
                best = (len(prefix), i)
    return None if best is None else best[1]


def is_cli(name: str) -> bool:
    last = name.rpartition(".")[2]
    return last in ("cli", "__main__") or last.endswith("_cli")


def _label(name: str) -> str:
    layer = layer_of(name)
    return f"{name} [{LAYERS[layer][0] if layer is not None else '?'}]"


def violations(src: Path) -> list[str]:
    """Every break of rules 1-4 in the tree under `src`, one readable line each."""
    modules = all_modules(src)
    out: list[str] = []
    for name in modules:
        if layer_of(name) is None:
            out.append(f"{name}: in no layer (give its top-level module a place in tests/test_imports.py LAYERS)")
    for name, path in modules.items():
        where = f"{path.relative_to(src)}"
        for imp in imports_of(name, path, modules):
            tgt = imp.imported
            if any(_under(name, p) for p in NO_TORCH) and _under(tgt, "torch"):
                out.append(f"{where}:{imp.line}: {name} -> torch (nothing under {', '.join(NO_TORCH)} imports torch)")
            if not _under(tgt, "yawil") or tgt == name:
                continue
            for low, high in FORBIDDEN:
                if _under(name, low) and _under(tgt, high):
                    out.append(f"{where}:{imp.line}: {name} -> {tgt} ({low} imports nothing of {high})")
            mine, theirs = layer_of(name), layer_of(tgt)
            if mine is None or theirs is None:
                continue
            if theirs > mine:
                out.append(f"{where}:{imp.line}: {_label(name)} -> {_label(tgt)} (a lower layer imports a higher one)")
            elif theirs == mine and is_cli(tgt) and not is_cli(name):
                out.append(f"{where}:{imp.line}: {_label(name)} -> {_label(tgt)} (a library module imports its "
                           "layer's command line)")
    return list(dict.fromkeys(out))  # one line per import, however many names it takes


def test_every_module_follows_the_import_rule() -> None:
    found = violations(SRC)
    assert not found, "imports against the rule (docs/architecture.md, tests/test_imports.py):\n" + "\n".join(found)


def test_every_layer_names_existing_modules() -> None:
    """A prefix left behind by a move would silently match nothing."""
    modules = all_modules(SRC)
    stale = [p for _, prefixes in LAYERS for p in prefixes if not any(_under(m, p) for m in modules)]
    assert not stale, f"LAYERS names modules that do not exist: {stale}"


def _tree(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / "yawil" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        # an upward import inside a function counts as much as one at the top
        ({"sim/__init__.py": "def f():\n    from yawil.bench import suites\n", "bench/__init__.py": "",
          "bench/suites.py": ""}, ["yawil.sim [sim] -> yawil.bench.suites [bench]"]),
        # a relative import is resolved
        ({"sim/__init__.py": "", "sim/x.py": "from ..agent import Agent\n", "agent.py": ""},
         ["yawil.sim.x [sim] -> yawil.agent [agent]"]),
        # torch under sim; models reaching into sim (a lower layer, but a rule of its own)
        ({"sim/__init__.py": "import torch.nn\n"}, ["yawil.sim -> torch"]),
        ({"models/__init__.py": "from yawil.sim.types import Pose\n", "sim/__init__.py": "", "sim/types.py": ""},
         ["yawil.models -> yawil.sim.types"]),
        # a library module of bench importing bench's command line; the CLI importing the library is fine
        ({"bench/__init__.py": "", "bench/cli.py": "from yawil.bench import runner\n",
          "bench/runner.py": "def f():\n    import yawil.bench.cli\n"},
         ["yawil.bench.runner [bench] -> yawil.bench.cli [bench]"]),
        # downward imports, a higher layer using a lower layer's CLI helper, and importlib with a constant
        ({"agent.py": "import yawil.sim\n", "sim/__init__.py": "", "learn/__init__.py": "", "learn/cli.py": "",
          "pipelines/__init__.py": "", "pipelines/dagger.py": "from yawil.learn.cli import x\nimport importlib\nimportlib.import_module('yawil.agent')\n"}, []),
        ({"sim/__init__.py": "import importlib\nimportlib.import_module('yawil.agent')\n", "agent.py": ""},
         ["yawil.sim [sim] -> yawil.agent [agent]"]),
        ({"newthing.py": ""}, ["yawil.newthing: in no layer"]),
    ],
)
def test_the_checker_finds_what_it_should(tmp_path: Path, files: dict[str, str], expected: list[str]) -> None:
    found = violations(_tree(tmp_path, {"__init__.py": "", **files}))
    assert len(found) == len(expected), found
    for line, want in zip(sorted(found), sorted(expected), strict=True):
        assert want in line, (want, line)
