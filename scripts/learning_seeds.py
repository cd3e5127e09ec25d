"""The learning test's protocol over seeds, for two settings: is one of them worse per sample?

    python scripts/learning_seeds.py [--seeds 0-7] [--modes eager,default] [--starts 16] [--iterations N]
        [--json FILE] [--rows FILE ...] [--margin M]

For each seed and each `runtime.learner_compile` mode (eager, default, reduce-overhead), in a fresh
process: the default loop as `tests/integration/test_learning_loop.py` runs it (its overrides, read from
it: walk, its iterations unless `--iterations` says otherwise; Ray, tracking off), then two tracking
errors of the trained controller against the untrained one the test builds, each as after / before:

  test      the test's own: `tracking_error` with 1-second segments (the walk clip gives 2).
  starts    the same quantity from `--starts` start frames spread evenly over the clip (1 second each,
            the posterior's mean action, no tracking termination): the mean over start phases, where
            the test's two segments are two draws of it.

It prints one row per run and, for the first two modes, each metric's paired difference (second minus
first) over the seeds with its 95% t interval and the Wilcoxon signed-rank p (scipy.stats). A fixed
seed of this loop is one draw: float rounding alone (a compiled loss, another CPU) moves it, so
only a difference whose interval excludes zero says one mode learns differently per sample.

`--rows` reads the rows of earlier runs (their `--json`) and summarises them with this run's (`--seeds ""`
runs nothing). `--margin M`, fixed before the runs, judges "second - first < M" on each metric with the
sweeps' verdicts (`orchestrator.sweep.verdict.judge`: the paired differences' t interval, Bonferroni over
the metrics): "no worse" when the interval ends below M, "worse" when it starts above, else "not resolved".
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy import stats

from orchestrator.sweep.verdict import CONTRADICTED, REPRODUCED, judge

ROOT = Path(__file__).resolve().parents[1]

ONE = """
import json, sys
import numpy as np, torch
from tempfile import TemporaryDirectory
from orchestrator.build import untracked_trainer
from orchestrator.compose import compose, validate
from orchestrator.world import evaluation_sim_config, load_character_and_library
from workers.body.features import relative_position_error
from workers.evaluation.controller import posterior_mean_action, tracking_error, without_tracking_termination
from workers.models.nets import evaluation_mode
from workers.learners.vae import build_controller
from workers.sim.env import make_sim
from workers.sim.episodes import run_episodes

from tests.integration.test_learning_loop import OVERRIDES as TEST

seed, mode, starts, iterations = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
mine = ("tracking=", *(("algo.loop.iterations=",) if iterations else ()))
OVERRIDES = [o for o in TEST if not o.startswith(mine)] + ["tracking=off"]
OVERRIDES += [f"algo.loop.iterations={iterations}"] if iterations else []

def from_starts(controller, character, library, sim_config):
    config = without_tracking_termination(sim_config)
    frames = np.linspace(0, int(library.num_frames[0]) - 1, starts, endpoint=False).astype(int)
    steps = int(round(config.control_hz))  # one second
    sim = make_sim(character, library, starts, config, seed=0)
    sim.reset(np.arange(starts), np.zeros(starts, dtype=int), frames)
    total = np.zeros(starts)

    def after(t, result):
        total[:] += relative_position_error(result.kin.xpos, sim.reference_state().xpos)

    with evaluation_mode(controller):
        run_episodes(sim, lambda sim, _: posterior_mean_action(controller, sim), steps, after, states=False)
    return float(total.mean() / steps)

with TemporaryDirectory() as tmp:
    cfg = validate(compose([f"run_dir={tmp}", *OVERRIDES, f"seed={seed}", f"runtime.learner_compile={mode}"]))
    character, library = load_character_and_library(cfg)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        untrained = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    sc = evaluation_sim_config(cfg)
    before = (tracking_error(untrained, character, library, 1.0, sc, seed=cfg.seed)["mean"],
              from_starts(untrained, character, library, sc))
    runtime, trainer = untracked_trainer(cfg)
    try:
        trainer.method.start(trainer)
        for _ in range(cfg.algo.loop.iterations):
            trainer.step()
        weights = runtime.get(runtime.call(trainer.handles["vae"], "get_weights"))
        trainer.method.finish(trainer)
    finally:
        runtime.shutdown()
    trained = build_controller(character.num_bodies, character.num_actions, cfg.algo.vae)
    trained.load_state_dict(weights.state)
    after = (tracking_error(trained, character, library, 1.0, sc, seed=cfg.seed)["mean"],
             from_starts(trained, character, library, sc))
    row = {"seed": seed, "mode": mode, "test": after[0] / before[0], "starts": after[1] / before[1],
           "test_m": [before[0], after[0]], "starts_m": [before[1], after[1]]}
    print("RESULT " + json.dumps(row))
"""

METRICS = ("test", "starts")


def seeds(text: str) -> list[int]:
    """Seeds written as a range, 0-7, or a list, 0,2,5."""
    if not text:
        return []
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def one(seed: int, mode: str, starts: int, iterations: int | None) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", ONE, str(seed), mode, str(starts), str(iterations or "")],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
    )
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise SystemExit(f"learning_seeds: seed {seed}, {mode} failed (exit {out.returncode}):\n{out.stderr[-2000:]}")


def differences(rows: list[dict], first: str, second: str, metric: str) -> tuple[np.ndarray, np.ndarray]:
    """Each seed's (first, second) values [n, 2] and their differences second - first [n]."""
    by = {(r["seed"], r["mode"]): r[metric] for r in rows}
    pairs = np.array([(by[s, first], by[s, second]) for s, m in sorted(by) if m == first and (s, second) in by])
    return pairs, (pairs[:, 1] - pairs[:, 0] if len(pairs) else np.array([]))


VERDICTS = {REPRODUCED: "no worse", CONTRADICTED: "worse by more than the margin"}


def summary(rows: list[dict], first: str, second: str, margin: float | None) -> list[str]:
    """One line per metric: the means, the paired difference with its 95% t interval and the Wilcoxon p; with
    a margin, the verdict on "second - first < margin" (Bonferroni over the metrics)."""
    lines = []
    for metric in METRICS:
        pairs, d = differences(rows, first, second, metric)
        if len(d) < 2:
            return [f"{metric}: fewer than two paired seeds"]
        lo, hi = stats.t.interval(0.95, len(d) - 1, loc=d.mean(), scale=stats.sem(d))
        wilcoxon = stats.wilcoxon(d).pvalue if np.any(d) else 1.0
        means = pairs.mean(axis=0)
        line = (
            f"{metric}: {first} {means[0]:.3f}, {second} {means[1]:.3f} (mean after/before over {len(d)} seeds); "
            f"{second} - {first} {d.mean():+.3f}, 95% t interval [{lo:+.3f}, {hi:+.3f}], Wilcoxon p {wilcoxon:.2f}"
        )
        if margin is not None:
            j = judge(d, None, (-np.inf, margin), claims=len(METRICS))
            verdict = VERDICTS.get(j.verdict, j.verdict)
            line += f"; below {margin:+.3f}? {100 * j.confidence:.1f}% [{j.low:+.3f}, {j.high:+.3f}]: {verdict}"
        lines.append(line)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0-7", type=seeds)
    parser.add_argument("--modes", default="eager,default")
    parser.add_argument("--starts", type=int, default=16)
    parser.add_argument("--iterations", type=int, help="the test's own unless given")
    parser.add_argument("--json", help="also write the rows here")
    parser.add_argument("--rows", nargs="*", default=[], help="earlier runs' --json files to summarise with these")
    parser.add_argument("--margin", type=float, help="the non-inferiority margin, fixed before the runs")
    args = parser.parse_args()
    modes = args.modes.split(",")
    rows = [row for path in args.rows for row in json.loads(Path(path).read_text())]
    for seed in args.seeds:
        for mode in modes:
            rows.append(one(seed, mode, args.starts, args.iterations))
            r = rows[-1]
            print(f"seed {seed} {mode}: test {r['test']:.3f}, starts {r['starts']:.3f} (after / before)", flush=True)
            if args.json:  # after every run: a later run that fails or is stopped loses none of these
                Path(args.json).write_text(json.dumps(rows, indent=1))
    if len(modes) >= 2:
        print("\n".join(summary(rows, modes[0], modes[1], args.margin)))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
