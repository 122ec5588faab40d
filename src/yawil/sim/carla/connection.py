"""Where the CARLA server is: one set of defaults for every command that connects (collect, bench, the
route-file maker) and for `CarlaWorld` itself, so the port or the time-out is changed in one place.

No `carla` import: the CLIs build their flags from here before anything heavy loads.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from typing import Any

__all__ = ["CarlaConnection", "add_connection_arguments", "check_connection_arguments", "connection_from_args"]


@dataclass(frozen=True)
class CarlaConnection:
    host: str = "localhost"
    port: int = 2000  # CARLA's default RPC port (`-carla-rpc-port`)
    timeout: float = 10.0  # seconds a client call may take before it counts as a simulator error

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments of `make_world("carla", ...)` / `CarlaWorld`."""
        return asdict(self)


def add_connection_arguments(p: argparse.ArgumentParser, timeout: float | None = None,
                             timeout_help: str = "seconds a client call may take before it counts as a simulator error",
                             prefix: str = "--backend carla: ", note: str = "") -> None:
    """--host, --port, --timeout with the defaults above (`timeout` overrides the default time-out; `note` is
    added to its help after the default)."""
    d = CarlaConnection()
    t = d.timeout if timeout is None else timeout
    p.add_argument("--host", default=d.host, help=f"{prefix}server host (default {d.host})")
    p.add_argument("--port", type=int, default=d.port, help=f"{prefix}server port (default {d.port})")
    p.add_argument("--timeout", type=float, default=t, help=f"{prefix}{timeout_help} (default {t:g}{'; ' + note if note else ''})")


def check_connection_arguments(args: argparse.Namespace, timeout: float | None = None) -> None:
    """--host, --port or --timeout changed without --backend carla is refused in one line: they would be ignored."""
    if getattr(args, "backend", "embedded") == "carla":
        return
    d = CarlaConnection()
    changed = [f"--{k}" for k, default in (("host", d.host), ("port", d.port),
                                           ("timeout", d.timeout if timeout is None else timeout))
               if getattr(args, k, default) != default]
    if changed:
        raise ValueError(f"{', '.join(changed)} applies to --backend carla; this run uses the embedded simulator")


def connection_from_args(args: argparse.Namespace) -> CarlaConnection:
    return CarlaConnection(host=args.host, port=args.port, timeout=args.timeout)
