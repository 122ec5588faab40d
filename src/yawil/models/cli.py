"""`yawil models`: every registered network with its parameter count and the inputs it needs."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "models",
        help="list the registered driving networks and their parameter counts",
        description="List every registered model: parameters, inputs, default config.",
    )
    p.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    p.add_argument("--zoo", action="store_true", help="list the trained models shipped with yawil (yawil zoo list)")
    return p


def describe() -> list[dict[str, object]]:
    """One record per registered model, built with its default config."""
    from yawil.models import create, list_models, parameter_count

    rows: list[dict[str, object]] = []
    for name in list_models():
        model = create(name, seed=0)
        doc = (type(model).__doc__ or "").strip().splitlines()
        rows.append(
            {
                "name": name,
                "parameters": parameter_count(model),
                "input": "command" if model.uses_command else f"guidance {model.guidance}[{model.guidance_dim}]",
                "config": model.config,
                "summary": doc[0] if doc else "",
            }
        )
    return rows


def run(args: argparse.Namespace) -> int:
    import json

    if args.zoo:
        from yawil.zoo import table

        print(table())
        return 0
    rows = describe()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'name':<15}{'parameters':>13}  {'input':<22}config")
    for r in rows:
        print(f"{r['name']!s:<15}{r['parameters']:>13,}  {r['input']!s:<22}{json.dumps(r['config'])}")
    return 0
