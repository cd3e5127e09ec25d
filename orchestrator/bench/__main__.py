"""Command line of the benchmarks."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orchestrator.bench", description=__doc__)
    sub = parser.add_subparsers(dest="what", required=True)
    sim = sub.add_parser("sim", help="raw MuJoCo stepping against the batched simulator")
    sim.add_argument("--envs", type=int, default=32, help="environments in the batched simulator")
    sim.add_argument("--seconds", type=float, default=5.0, help="wall time of each measurement")
    sim.add_argument("--sim-hz", type=float, default=480.0)
    sim.add_argument("--control-hz", type=float, default=30.0)
    sim.add_argument("--seed", type=int, default=0)
    for p in (sim,):
        p.add_argument("--json", action="store_true", help="print JSON instead of the table")
        p.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = parser.parse_args(argv)

    if args.what == "sim":
        from orchestrator.bench import sim as bench_sim

        if args.envs < 1 or args.seconds <= 0:
            parser.error("--envs must be at least 1 and --seconds positive")
        result = bench_sim.run(args.envs, args.seconds, args.sim_hz, args.control_hz, args.seed)
        text = bench_sim.format_table(result)
    else:  # pragma: no cover - argparse refuses unknown commands
        parser.error(f"unknown benchmark {args.what}")

    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
