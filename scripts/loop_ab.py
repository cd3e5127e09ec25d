"""The default loop's samples per second at two commits, in alternating blocks on this machine.

    python scripts/loop_ab.py BEFORE AFTER [--rounds 3] [--iterations 20] [--warmup 4]
        [--after-set KEY=VALUE ...] [OVERRIDES...]

Each commit is checked out in a temporary worktree; every round runs the default run
(`python -m orchestrator` as shipped, tracking off, seed 0, any Hydra OVERRIDES) once at
each commit, in turn, in a fresh process: `--warmup` untimed iterations, then
`--iterations` timed ones. It prints each block's samples/s and seconds per iteration,
and the median over rounds of each pair's ratio AFTER / BEFORE: the two sides share
whatever else the machine is doing. The measuring code lives here, not in either tree,
so any commit with `orchestrator.build.untracked_trainer` can be measured. `--after-set`
(repeatable) gives a Hydra override to the AFTER side only: a setting measured against the
shipped default at the same commit, e.g. `loop_ab.py HEAD HEAD --after-set algo.vae.batch_size=256`.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MEASURE = """
import json, sys, time
from tempfile import TemporaryDirectory
from orchestrator.build import untracked_trainer
from orchestrator.compose import compose, validate
iterations, warmup, overrides = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
with TemporaryDirectory() as tmp:
    cfg = validate(compose([f"run_dir={tmp}", "tracking=off", "progress=false", "seed=0", *overrides]))
    runtime, trainer = untracked_trainer(cfg)
    try:
        trainer.method.start(trainer)
        for _ in range(warmup):
            trainer.step()
        samples, t0 = trainer.state.samples, time.perf_counter()
        for _ in range(iterations):
            trainer.step()
        seconds = time.perf_counter() - t0
        print("RESULT " + json.dumps({"samples_per_s": (trainer.state.samples - samples) / seconds,
                                      "s_per_iteration": seconds / iterations}))
        trainer.method.finish(trainer)
    finally:
        runtime.shutdown()
"""


def block(tree: Path, iterations: int, warmup: int, overrides: list[str]) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", MEASURE, str(iterations), str(warmup), *overrides],
        cwd=tree,
        env={**os.environ, "PYTHONPATH": str(tree)},
        capture_output=True,
        text=True,
    )
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise SystemExit(f"loop_ab: the run at {tree.name} failed (exit {out.returncode}):\n{out.stderr[-2000:]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=4)
    parser.add_argument("--after-set", action="append", default=[], metavar="KEY=VALUE")
    args, overrides = parser.parse_known_args()
    with tempfile.TemporaryDirectory(prefix="loop-ab-") as tmp:
        trees = {}
        for side, rev in (("before", args.before), ("after", args.after)):
            trees[side] = Path(tmp) / side
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(trees[side]), rev], check=True)
        try:
            ratios = []
            for r in range(args.rounds):
                extra = {"before": [], "after": args.after_set}
                got = {
                    side: block(tree, args.iterations, args.warmup, [*overrides, *extra[side]])
                    for side, tree in trees.items()
                }
                ratios.append(got["after"]["samples_per_s"] / got["before"]["samples_per_s"])
                print(
                    f"round {r + 1}: before {got['before']['samples_per_s']:.0f} samples/s "
                    f"({got['before']['s_per_iteration']:.3f} s/it), after {got['after']['samples_per_s']:.0f} "
                    f"({got['after']['s_per_iteration']:.3f} s/it): {ratios[-1]:.2f}x",
                    flush=True,
                )
            print(f"after / before, median of {len(ratios)} pairs: {statistics.median(ratios):.2f}x")
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)


if __name__ == "__main__":
    main()
