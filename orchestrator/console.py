"""What a run prints when it starts and when it ends.

At the start (once the components are up): where to watch it, the MLflow UI (or server: its URI's password
masked) and the Ray dashboard with how to get its token. At the end: the final evaluation beside the untrained
policy's (`eval.at_start`), where the figures, videos and model are, and the `mlflow ui` line.
"""

from __future__ import annotations

import math

from orchestrator.runtime.base import Runtime
from orchestrator.schema import Config
from orchestrator.tracking.base import RunLogger
from orchestrator.tracking.uri import redact, scrub, store_uri

# Spread and per-clip breakdowns stay in MLflow; the table keeps one line per measure.
HIDDEN_SUFFIXES = ("_std", "_median")


def mlflow_line(cfg: Config, run_id: str | None) -> str:
    """Where to look at the run in MLflow: the server, or the `mlflow ui` line for a store (its password masked)."""
    uri = redact(store_uri(cfg.tracking.uri, cfg.run_dir))
    run = f"run {run_id}" if run_id else "run not created yet: the server is away, records are spooled"
    if uri.startswith("http"):
        return f"MLflow: {uri}  ({run})"
    return f"MLflow UI: mlflow ui --backend-store-uri {uri} --host 127.0.0.1  ({run})"


def where_to_watch(cfg: Config, logger: RunLogger, runtime: Runtime) -> str:
    lines = [mlflow_line(cfg, logger.run_id)] if cfg.tracking.enabled else []
    dashboard = runtime.dashboard_url()
    if dashboard:
        lines.append(f"Ray dashboard: {dashboard}  (its token: ray get-auth-token)")
    else:
        lines.append("Ray dashboard: none (runtime=local: one process)")
    lines.append(f"Run directory: {cfg.run_dir}")
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.4g}"


def table(baseline: dict[str, float], final: dict[str, float]) -> str:
    """One line per top-level `eval/` measure: untrained, trained, change."""
    keys = [k for k in final if k.startswith("eval/") and k.count("/") == 1 and not k.endswith(HIDDEN_SUFFIXES)]
    if not keys:
        return ""
    names = [k.removeprefix("eval/") for k in keys]
    width = max(len(n) for n in names)
    rows = [f"  {'measure':<{width}}  {'untrained':>10}  {'trained':>10}  {'change':>10}"]
    for key, name in zip(keys, names, strict=True):
        before, after = baseline.get(key), final[key]
        change = after - before if before is not None else None
        change_s = "-" if change is None else f"{change:+.4g}"
        rows.append(f"  {name:<{width}}  {_fmt(before):>10}  {_fmt(after):>10}  {change_s:>10}")
    return "\n".join(rows)


def artifact_location(cfg: Config, logger: RunLogger) -> str | None:
    """The run's artifact root (a local directory for the embedded store), or None if unknown."""
    if not cfg.tracking.enabled or logger.run_id is None:
        return None
    try:
        from orchestrator.tracking.query import artifact_root  # loads mlflow: only when tracked

        return artifact_root(store_uri(cfg.tracking.uri, cfg.run_dir), logger.run_id)
    except Exception:  # noqa: BLE001 - the server is away: the summary says less
        return None


def closing(
    cfg: Config, logger: RunLogger, baseline: dict[str, float], final: dict[str, float], model_uri: str | None
) -> str:
    lines = [f"\n{cfg.algo.name} finished: {scrub(cfg.tracking.run_name or '')}".rstrip()]
    rows = table(baseline, final)
    if rows:
        lines += ["", rows]
        if not baseline:
            lines.append("  (no untrained baseline: eval.at_start=false or a resumed run)")
    where = artifact_location(cfg, logger)
    if where:
        lines += ["", f"Figures:  {where}/eval/"] + ([f"Videos:   {where}/videos/"] if cfg.eval.video else [])
    if model_uri:
        lines.append(f"Model:    {model_uri}  (mlflow.pytorch.load_model)")
    if cfg.tracking.enabled:
        lines.append(mlflow_line(cfg, logger.run_id))
    lines.append(f"Run directory: {cfg.run_dir}")
    return "\n".join(lines)
