"""One CARLA server per worker (`--carla-servers HOST:PORT,...`): the list checked, and each worker's world
factory, on its own server and with its own Traffic Manager port (two clients on one machine cannot both
serve a Traffic Manager on one port).

No `carla` import: the CLIs build their flag from here before anything heavy loads.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

TM_PORT = 8000  # CarlaWorld's Traffic Manager port; worker r serves its own on TM_PORT + r
FLAG = "--carla-servers"


def add_servers_argument(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    p.add_argument(FLAG, default=None, metavar="HOST:PORT,...",
                   help="--backend carla: one server per worker, as many as --workers (e.g. "
                        "localhost:2000,localhost:2002); each worker drives its own; replaces --host and --port")


def parse_servers(text: str) -> tuple[tuple[str, int], ...]:
    """'a:2000,b:2000' -> (('a', 2000), ('b', 2000)); ValueError naming the flag and the bad item."""
    servers: list[tuple[str, int]] = []
    for item in (part.strip() for part in text.split(",")):
        host, _, port = item.rpartition(":")
        host = host.strip("[]")  # an IPv6 address in brackets
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"{FLAG} {text!r}: {item!r} is not HOST:PORT (expected HOST:PORT,HOST:PORT,... "
                             "with ports 1-65535)")
        if (host, int(port)) in servers:
            raise ValueError(f"{FLAG} {text!r}: {item} is given twice; each worker needs its own server")
        servers.append((host, int(port)))
    return tuple(servers)


def servers_for(text: str | None, workers: int, backend: str) -> tuple[tuple[str, int], ...] | None:
    """The servers of the flag, one per worker (None without it); ValueError naming the flag otherwise."""
    if text is None:
        return None
    if backend != "carla":
        raise ValueError(f"{FLAG} applies to --backend carla, not --backend {backend}")
    servers = parse_servers(text)
    if len(servers) != workers:
        raise ValueError(f"{FLAG} lists {len(servers)} server(s) for --workers {workers}: give one server per worker")
    return servers


def server_worlds(servers: tuple[tuple[str, int], ...], timeout: float) -> tuple[Callable[[], Any], ...]:
    """One picklable world factory per worker: worker r on the r-th server, its Traffic Manager on TM_PORT + r."""
    from yawil.sim import world_factory

    return tuple(world_factory("carla", host=host, port=port, timeout=timeout, tm_port=TM_PORT + rank)
                 for rank, (host, port) in enumerate(servers))
