"""Behaviour-identity check of the expert's benchmark records (issue 15, "Done when"): the expert on the 250
single-seed benchmark episodes, camera off, gives records identical to the stored reference in every field
but `wall_s`.

The episodes: `yawil.bench.suites.episodes("all", seeds=1, weather_rule="cycle")`, both conditions of suite
"all" (training, new-town-weather), 125 each: route i in weather i mod 4 (with `weather_rule="all"` it would
be 750). The reference, `tests/fixtures/identity/expert_records.json`, holds one SHA-256 per episode key
(task/condition/weather/route/seed) of the record without `wall_s` (`record_digest`), so it stays small;
`tests/test_identity.py` re-runs six of these episodes in every `make test`.

    nice -n 19 .venv/bin/python benchmarks/identity_expert.py --workers 2            # compare
    nice -n 19 .venv/bin/python benchmarks/identity_expert.py --workers 2 --write    # new reference

Prints how many records match, the keys of those that differ (or are missing), and exits 1 on any difference.
`--keep DIR` keeps the run's records (`DIR/episodes.jsonl`) to look at a difference field by field with
`benchmarks/judge_identity.py records`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

REFERENCE = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "identity" / "expert_records.json"
IGNORED = ("wall_s",)
SUITE, SEEDS, WEATHER_RULE = "all", 1, "cycle"


def record_digest(rec: Mapping[str, Any]) -> str:
    """SHA-256 of a record's fields but wall time, keys sorted (JSON as the record log writes floats)."""
    kept = {k: v for k, v in rec.items() if k not in IGNORED}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


def reference_episodes() -> list[Any]:
    from yawil.bench.suites import episodes

    return episodes(SUITE, seeds=SEEDS, weather_rule=WEATHER_RULE)


def load_reference(path: Path = REFERENCE) -> dict[str, str]:
    return dict(json.loads(path.read_text())["records"])


def run(workers: int, out: Path) -> dict[str, str]:
    from yawil.bench.records import episode_key
    from yawil.bench.runner import AgentSpec, run_benchmark

    eps = reference_episodes()
    summary = run_benchmark(eps, AgentSpec("expert"), out, workers=workers, camera=False, progress=False,
                            label="identity")
    return {episode_key(r): record_digest(r) for r in summary.records}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--write", action="store_true", help="write the reference instead of comparing with it")
    ap.add_argument("--keep", type=Path, default=None, help="results folder to keep (default: a temporary one)")
    ap.add_argument("--reference", type=Path, default=REFERENCE)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="identity_expert_") as tmp:
        got = run(args.workers, args.keep or Path(tmp) / "run")
    wall = time.perf_counter() - t0
    if args.write:
        from yawil.fileio import write_json_atomic

        write_json_atomic(args.reference, {
            "episodes": f"yawil.bench.suites.episodes({SUITE!r}, seeds={SEEDS}, weather_rule={WEATHER_RULE!r})",
            "agent": "expert", "camera": False, "ignored": list(IGNORED),
            "records": dict(sorted(got.items())),
        })
        print(f"wrote {len(got)} record digests to {args.reference} ({wall:.1f} s)")
        return 0
    want = load_reference(args.reference)
    match = sorted(k for k in want if got.get(k) == want[k])
    differ = sorted(k for k in want if k in got and got[k] != want[k])
    missing = sorted(set(want) - set(got))
    extra = sorted(set(got) - set(want))
    for k in differ:
        print(f"differs: {k}")
    for k in missing:
        print(f"missing: {k}")
    for k in extra:
        print(f"not in the reference: {k}")
    print(f"expert records: {len(match)} of {len(want)} match, {len(differ)} differ, {len(missing)} missing, "
          f"{len(extra)} extra ({wall:.1f} s, {args.workers} workers)")
    return 0 if len(match) == len(want) and not extra else 1


if __name__ == "__main__":
    sys.exit(main())
