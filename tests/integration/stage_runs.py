"""What the stage tests share: smoke configs composed outside a test's fixtures, and the runs of a store by method.

Module-scoped fixtures (one pipeline trained per test module) cannot use the function-scoped `smoke`
fixture of conftest.py, so they compose here, the same way.
"""

from __future__ import annotations

from pathlib import Path

from mlflow.tracking import MlflowClient

from orchestrator.compose import compose, validate
from orchestrator.schema import Config


def smoke_config(run_dir: Path, *overrides: str) -> Config:
    """The smoke scale on the walk clip, as `python -m orchestrator` composes it, with `overrides`; what the
    `smoke` fixture (conftest.py) and the module-scoped fixtures use."""
    base = ["scale=smoke", "motion=walk", f"run_dir={run_dir}", "progress=false"]
    # Tests run single-process (runtime=local) unless they ask for Ray; `python -m orchestrator` defaults to Ray.
    base += [] if any(o.startswith("runtime=") for o in overrides) else ["runtime=local"]
    # Videos cost seconds per evaluation in software GL: only the tests that ask for them render them.
    base += [] if any(o.startswith("eval.video=") for o in overrides) else ["eval.video=false"]
    return validate(compose([*base, *overrides]))


def runs_of(uri: str, algo: str) -> list:
    """Every run of method `algo` in the store at `uri`, in any experiment."""
    client = MlflowClient(uri)
    ids = [e.experiment_id for e in client.search_experiments()]
    return client.search_runs(ids, filter_string=f"tags.algo = '{algo}'")
