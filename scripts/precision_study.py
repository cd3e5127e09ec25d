"""The bfloat16 study of docs/physicsvae.md, from a store's finished physicsvae runs: does
`algo.offline.precision=bfloat16` change what the VAE learns?

The runs are made by a sweep (the rule fixes the seeds and the point before any of them):

    python -m orchestrator -m algo=physicsvae scale=cpu algo.offline.precision=float32,bfloat16 seed=0,1,2,3,4,5 \\
        tracking.uri=<the store ablation_kl trained its stages in>

and judged here, per seed paired: the log ratio bfloat16 / float32 of each measure, its paired t interval
(`orchestrator.sweep.verdict.judge` on the differences, Bonferroni over the measures), "no change" when the
interval lies within the measure's margin, "changed" when it lies outside, else "not resolved":

    python scripts/precision_study.py --uri <store> [--experiment default] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from orchestrator.sweep.verdict import CONTRADICTED, REPRODUCED, judge  # noqa: E402

# Each measure and its margin on the ratio bfloat16 / float32 (docs/physicsvae.md, fixed before the runs).
MEASURES = {
    "eval/heldout_action_error": 0.10,
    "eval/heldout_sim_error": 0.10,
    "eval/time_until_fall_mean": 0.20,
}
SAID = {REPRODUCED: "no change", CONTRADICTED: "changed"}


def rows_of(uri: str, experiment: str) -> list[dict]:
    """{seed, precision, metrics} of every FINISHED physicsvae run of `experiment`."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"no experiment {experiment!r} in {uri}")
    runs = client.search_runs(
        [exp.experiment_id], filter_string="tags.algo = 'physicsvae' and attributes.status = 'FINISHED'"
    )
    return [
        {
            "seed": int(r.data.params["seed"]),
            "precision": r.data.params.get("algo.offline.precision", "float32"),
            "alpha": float(r.data.params["algo.vae.alpha"]),
            "beta": float(r.data.params["algo.vae.beta.start"]),
            **{k: r.data.metrics.get(k) for k in MEASURES},
        }
        for r in runs
    ]


def judge_rows(rows: list[dict]) -> dict:
    """The paired verdicts of bfloat16 against float32 on each measure (newest run per seed and precision)."""
    by = {(r["seed"], r["precision"]): r for r in rows}
    seeds = sorted({s for s, p in by if p == "bfloat16"} & {s for s, p in by if p == "float32"})
    out = {"seeds": seeds, "measures": {}}
    for key, margin in MEASURES.items():
        d = np.array([math.log(by[s, "bfloat16"][key] / by[s, "float32"][key]) for s in seeds])
        j = judge(d, None, (math.log(1 - margin), math.log(1 + margin)), claims=len(MEASURES))
        out["measures"][key] = {
            "log_ratios": d.tolist(),
            "ratio": math.exp(j.effect) if math.isfinite(j.effect) else math.nan,
            "low": math.exp(j.low) if math.isfinite(j.low) else math.nan,
            "high": math.exp(j.high) if math.isfinite(j.high) else math.nan,
            "confidence": j.confidence,
            "margin": margin,
            "verdict": SAID.get(j.verdict, j.verdict),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--uri", required=True, help="the MLflow store of the study's runs")
    parser.add_argument("--experiment", default="default")
    parser.add_argument("--json", type=Path, help="also write the rows and verdicts here")
    args = parser.parse_args(argv)
    rows = rows_of(args.uri, args.experiment)
    result = judge_rows(rows)
    print(f"seeds paired: {result['seeds']}")
    for key, m in result["measures"].items():
        print(
            f"{key}: bfloat16 / float32 = {m['ratio']:.3f}, {100 * m['confidence']:.1f}% CI "
            f"[{m['low']:.3f}, {m['high']:.3f}] against ±{100 * m['margin']:.0f}%: {m['verdict']}"
        )
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, **result}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
