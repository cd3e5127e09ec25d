"""What a refactor must leave unchanged, written down so that two checkouts can be compared.

    python -m tests.config_snapshot configs --out A.json          # every conf/algo x conf/scale, resolved, and hashes
    python -m tests.config_snapshot history --out B.json [KEY=V..] # a short default run, runtime=local, its metrics
    python -m tests.config_snapshot compare A.json A2.json         # what differs (exit 1 if anything does)

`configs` composes `algo=<name> scale=<scale>` for every file of conf/algo and conf/scale and records the
validated config (as a dict) and its stage hash, upstream stages' hashes included (composed as a run would,
without MLflow); with `--former`, also the hash by the rule before the layout change (the class's module
path in it), which must equal the stage hash a checkout from before that change records. `history` runs
the default experiment (with any overrides) in a child process with tracking into a fresh SQLite store and
records every metric's history except those that measure time or the machine (throughput/, system/, *_s).
Used for the layout change (the configs and histories before and after are compared).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def _api():
    """compose, validate, config_hash, upstream_config wherever this checkout keeps them."""
    try:  # the rebuilt layout
        from orchestrator.compose import compose, validate
        from orchestrator.stages import config_hash, upstream_config
    except ImportError:  # before it
        from orchestrator.schema import validate
        from orchestrator.stages import compose, config_hash, upstream_config
    return compose, validate, config_hash, upstream_config


def chain_hash(cfg, config_hash, upstream_config) -> str:
    """The stage hash a run of `cfg` gets, its needs composed and hashed first (as stages.resolve does)."""
    above = {
        role: chain_hash(upstream_config(cfg, spec, role), config_hash, upstream_config)
        for role, spec in cfg.algo.needs.items()
        if not spec.startswith("run:")
    }
    return config_hash(cfg, above)


# Where method classes lived before the layout change (the hash then included this path).
FORMER_TARGETS = {
    "orchestrator.algos.physicsvae.SimulationLayer": "orchestrator.algos.offline.OfflineWorldModel",
    "orchestrator.algos.physicsvae.PhysicsVAE": "orchestrator.algos.offline.PhysicsVAE",
}


def former_hash(cfg, upstream: dict[str, str] | None = None) -> str:
    """The stage hash as it was computed before the layout change: `algo._target_` (its former module path) in it."""
    from orchestrator.stages import NOT_RESULT, RUNTIME_RESULT

    d = asdict(cfg)
    for key in NOT_RESULT:
        d.pop(key, None)
    d["runtime"] = {k: d["runtime"][k] for k in RUNTIME_RESULT}
    d["algo"] = {k: v for k, v in d["algo"].items() if v is not None}
    d["algo"]["_target_"] = FORMER_TARGETS.get(d["algo"]["_target_"], d["algo"]["_target_"])
    d["algo"]["needs"] = dict(sorted((upstream or {}).items()))
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:20]


def configs(former: bool = False) -> dict:
    compose, validate, config_hash, upstream_config = _api()
    out = {}
    for algo in sorted(p.stem for p in (CONF / "algo").glob("*.yaml")):
        for scale in sorted(p.stem for p in (CONF / "scale").glob("*.yaml")):
            cfg = validate(compose([f"algo={algo}", f"scale={scale}", "run_dir=outputs/snapshot"]))
            # The stage hash covers the source files' digest (tracking.stage_code=source): any edit of them changes
            # it. The same hash with the package's version instead says whether anything else did.
            same_code = validate(compose([f"algo={algo}", f"scale={scale}", "run_dir=outputs/snapshot",
                                          "tracking.stage_code=version"]))  # fmt: skip
            out[f"{algo}/{scale}"] = {
                "config": asdict(cfg),
                "stage_hash": chain_hash(cfg, config_hash, upstream_config),
                "stage_hash_but_code": chain_hash(same_code, config_hash, upstream_config),
            }
            if former:
                out[f"{algo}/{scale}"]["former_stage_hash"] = chain_hash(cfg, former_hash, upstream_config)
    return out


TIMING = ("throughput/", "system/")


def history(overrides: list[str]) -> dict:
    from mlflow import MlflowClient

    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "runtime=local",
            "seed=0",
            "eval.video=false",
            "progress=false",
            f"run_dir={tmp}/run",
            f"hydra.run.dir={tmp}/run",
            *overrides,
        ]
        subprocess.run([sys.executable, "-m", "orchestrator", *args], check=True, cwd=ROOT)
        client = MlflowClient(f"sqlite:///{tmp}/run/mlflow.db")
        exp = [e.experiment_id for e in client.search_experiments()]
        (run,) = client.search_runs(exp)
        out = {}
        for key in sorted(run.data.metrics):
            if key.startswith(TIMING) or key.endswith("_s"):
                continue
            out[key] = [
                (m.step, m.value)
                for m in sorted(client.get_metric_history(run.info.run_id, key), key=lambda m: (m.step, m.timestamp))
            ]
        return out


def _strip_targets(x):
    """Module paths of classes (`_target_`) moved on purpose; compare the class names only."""
    if isinstance(x, dict):
        return {
            k: (v.rpartition(".")[2] if k == "_target_" and isinstance(v, str) else _strip_targets(v))
            for k, v in x.items()
        }
    if isinstance(x, list):
        return [_strip_targets(v) for v in x]
    return x


def compare(a: dict, b: dict, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}{k}: only in {'second' if k in b else 'first'}")
            else:
                out += compare(a[k], b[k], f"{path}{k}.")
        return out
    return [] if a == b else [f"{path[:-1]}: {a!r} != {b!r}"[:300]]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=("configs", "history", "compare"))
    p.add_argument("files", nargs="*", help="compare: two snapshots; history: Hydra overrides")
    p.add_argument("--out")
    p.add_argument("--keep-targets", action="store_true", help="compare: _target_ module paths too")
    p.add_argument("--former", action="store_true", help="configs: also each stage hash as the former rule made it")
    args = p.parse_intermixed_args()
    if args.what == "compare":
        a, b = (json.loads(Path(f).read_text()) for f in args.files)
        if not args.keep_targets:
            a, b = _strip_targets(a), _strip_targets(b)
        diff = compare(a, b)
        print("\n".join(diff) if diff else "identical")
        print(f"{len(diff)} differences")
        sys.exit(1 if diff else 0)
    data = configs(args.former) if args.what == "configs" else history(args.files)
    text = json.dumps(data, indent=1, sort_keys=True, default=str)
    Path(args.out).write_text(text) if args.out else print(text)


if __name__ == "__main__":
    main()
