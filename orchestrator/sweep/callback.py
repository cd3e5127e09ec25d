"""Sweeps: one MLflow parent run per Hydra multirun, a child run per point, and the comparison at the end.

`SweepCallback` (registered in conf/config.yaml) opens the parent run when the
multirun starts and writes `sweep.json` into the sweep directory; each job reads
it (`parent_of`) to log into the same store as a child. Without `tracking.uri` the
store is one SQLite file in the sweep directory. The basic launcher's sequential
jobs write it directly; when a launcher runs jobs in parallel (e.g.
`hydra/launcher=joblib`), SQLite would lock under the concurrent writers, so the
callback starts an MLflow server on 127.0.0.1 in front of that file (or of the
`sqlite:///` file given as `tracking.uri`) for the sweep's duration and the jobs
log through it, as its one user (MLflow's basic-auth app, a fresh password in the
environment the jobs inherit: another user of the machine cannot write to it).
A sweep that does not reach its end (a point raised, and Hydra skips
`on_multirun_end`; Ctrl-C) closes its parent run FAILED and stops that server
when the process exits.
When the multirun ends, the children's final metrics are gathered into a table
(JSON and Markdown) and a figure, with the learning curves of the preset's
`curves` and the paper's result beside ours (`orchestrator.sweep.report`), logged to
the parent run. A preset's `facet_by` (a second swept key, e.g. the terrain) groups
them by (compared value, facet); its `figures` and `claims` name a paper's own
figures and table of statements (`orchestrator.sweep.tasks`, `orchestrator.sweep.physicsvae`).
"""

from __future__ import annotations

import atexit
import json
import os
import socket
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from orchestrator.sweep import amp, physicsvae, report, tasks
from orchestrator.tracking.secret_files import write_secret
from orchestrator.tracking.uri import hide, redact, scrub, scrub_file, store_uri

SWEEP_FILE = "sweep.json"
SEQUENTIAL_LAUNCHER = "hydra._internal.core_plugins.basic_launcher.BasicLauncher"
# ControlVAE's and PhysicsVAE's measures; a preset names its own (callbacks.sweep.metrics).
DEFAULT_METRICS = {"eval/time_until_fall_mean": "time until fall (s)", "eval/tracking_error_mean": "tracking error (m)"}


def runs_in_parallel(config: DictConfig) -> bool:
    """Whether the multirun's launcher may run jobs at once (anything but Hydra's basic launcher)."""
    launcher = config.hydra.get("launcher") or {}
    return launcher.get("_target_", SEQUENTIAL_LAUNCHER) != SEQUENTIAL_LAUNCHER


def sweep_points(config: DictConfig) -> int:
    """How many runs the multirun's sweeper makes: the product of its swept values' counts."""
    n = 1
    for value in (config.hydra.sweeper.get("params") or {}).values():
        n *= len(str(value).split(","))
    return n


def parent_of(sweep_dir: str | Path) -> dict[str, str] | None:
    """The parent run's id and store for jobs of a multirun (None outside one)."""
    path = Path(sweep_dir) / SWEEP_FILE
    return json.loads(path.read_text()) if path.exists() else None


class SweepCallback(Callback):
    """The parent run of a multirun, and its comparison at the end.

    compare_by: the swept key whose points are compared (seeds are pooled).
    metrics:    final metrics to tabulate and plot, key -> label.
    curves:     metrics whose learning curves (against samples) are plotted, key -> label; the first
                is also summarised (final level, roughness, speed) in the table.
    paper:      the paper's result, lines set beside ours in comparison.md.
    reference:  the paper's value of final metrics, drawn as a dashed line in comparison.png.
    spread:     a figure of one per-rollout quantity's mean and spread per point ({"mean", "std", "label",
                "title"}; PhysicsVAE's Fig. 9), as spread.png.
    claims:     the name of a table of the paper's statements beside our numbers
                (`CLAIMS` of `orchestrator.sweep.physicsvae`, `.tasks` or `.amp`).
    facet_by:   a second swept key (e.g. `terrain.kind`): rows carry it, and the tables and figures group by
                (compare_by, facet_by); None compares `compare_by` alone (seeds pooled).
    figures:    names of a paper's own figures (`orchestrator.sweep.tasks.FIGURES`), each written as <name>.png.
    """

    def __init__(
        self,
        compare_by: str = "algo.vae.prior",
        metrics: dict[str, str] | None = None,
        curves: dict[str, str] | None = None,
        paper: list[str] | None = None,
        reference: dict[str, float] | None = None,
        spread: dict[str, str] | None = None,
        claims: str | None = None,
        facet_by: str | None = None,
        figures: list[str] | None = None,
    ) -> None:
        # Checked here, when the multirun starts, not after its runs.
        known = {**physicsvae.CLAIMS, **tasks.CLAIMS, **amp.CLAIMS}
        if claims is not None and claims not in known:
            raise ValueError(f"callbacks.sweep.claims: unknown table {claims!r}; expected one of {sorted(known)}")
        unknown = [f for f in figures or [] if f not in tasks.FIGURES]
        if unknown:
            raise ValueError(f"callbacks.sweep.figures: unknown {unknown}; expected some of {sorted(tasks.FIGURES)}")
        self.compare_by = compare_by
        self.metrics = dict(metrics or DEFAULT_METRICS)
        self.curves = dict(curves or {})
        self.paper = list(paper or [])
        self.reference = dict(reference or {})
        self.spread = dict(spread or {})
        self.claims = claims
        self.facet_by = facet_by
        self.figures = list(figures or [])
        self.stages_table = ""
        self.expert_level: float | None = None  # the expert's own time until fall on its demos
        self.logger = None
        self.sweep_dir: Path | None = None
        self.server = None

    def __getstate__(self) -> dict[str, Any]:
        # Parallel launchers pickle the callbacks into each job; the parent run and the server stay here.
        return {**self.__dict__, "logger": None, "server": None}

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from orchestrator.tracking.mlflow import MlflowLogger

        if not config.tracking.enabled:
            return
        atexit.register(self.abandon)  # unregistered at the sweep's end
        self.sweep_dir = Path(config.hydra.sweep.dir)
        self.sweep_dir.mkdir(parents=True, exist_ok=True)
        store = store_uri(config.tracking.uri, self.sweep_dir)
        hide(store)  # Hydra's launcher logs each point's overrides
        uri = store
        experiment = config.tracking.experiment or config.preset
        if store.startswith("sqlite:///") and runs_in_parallel(config):
            from orchestrator.tracking.query import ensure_experiment
            from orchestrator.tracking.server import start_local_server

            # The experiment is made in the store itself, its artifacts in files beside it (the jobs write them
            # there directly), so that the store stays whole without the server: later commands (a preset
            # reusing these stages, `mlflow ui`) read it as a file.
            ensure_experiment(store, experiment)

            self.server = start_local_server(
                store, sqlite_artifacts(store), log_path=self.sweep_dir / "mlflow-server.log", auth=True
            )
            # This process and the jobs it launches (they inherit the environment) log as the server's one user.
            os.environ.update(self.server.credentials)
            uri = self.server.uri
            print(f"sweep: parallel jobs log through the tracking server at {uri}")
        refuse_unwritable(uri, experiment)
        self.logger = MlflowLogger(
            uri=uri,
            experiment=experiment,
            run_name=f"{config.preset} sweep",
            tags={"preset": config.preset, "role": "sweep", "host": socket.gethostname()},
            run_dir=self.sweep_dir,
        )
        self.logger.set_tags({"sweep_id": self.logger.run_id})
        params = dict(config.hydra.sweeper.get("params") or {})
        self.logger.log_params({f"sweep.{k}": str(v) for k, v in params.items()})
        # `uri` is what the jobs log to; `store` is where the runs stay once the sweep is over.
        info = {"parent_run_id": self.logger.run_id, "uri": uri, "store": store, "experiment": experiment}
        # The jobs read the store from it, a password in its URI included: readable by this user alone.
        write_secret(self.sweep_dir / SWEEP_FILE, json.dumps(info))
        self.run_stages(config, uri, experiment)

    def run_stages(self, config: DictConfig, uri: str, experiment: str) -> None:
        """The points' upstream stages, once, before the points (which then find them finished in the store);
        the parent run links them (tags `upstream.*`, and stages.md)."""
        from omegaconf import OmegaConf

        from orchestrator import stages
        from orchestrator.build import train_stage
        from orchestrator.compose import validate

        plain = OmegaConf.to_container(config, resolve=False)
        plain.pop("hydra", None)
        plain["run_dir"] = str(self.sweep_dir)
        try:
            cfg = validate(plain)
            jobs = int(config.hydra.launcher.get("n_jobs") or 1) if runs_in_parallel(config) else 1
            print("sweep: " + stages.expected_time(cfg, uri, experiment, sweep_points(config), jobs), flush=True)
            upstream = stages.resolve(cfg, uri, self.sweep_dir, experiment, train_stage) if cfg.algo.needs else {}
        except Exception:
            self.logger.close("FAILED")
            self.logger = None
            raise
        if not upstream:
            return
        self.logger.set_tags(stages.lineage_tags(upstream))
        rows = ["| role | stage | run | stage hash | reused |", "| --- | --- | --- | --- | --- |"]
        rows += [f"| {r} | {u.name} | {u.run_id} | {u.stage_hash} | {u.reused} |" for r, u in upstream.items()]
        rows += [f"| {r}.{k} | | {v} | | |" for r, u in upstream.items() for k, v in u.lineage.items()]
        expert = {k: v for u in upstream.values() if u.name == "demos" for k, v in u.metrics().items()}
        quality = [f"- {k}: {v:.3g}" for k, v in sorted(expert.items()) if k.startswith("expert/")]
        self.expert_level = expert.get("expert/time_until_fall_mean")
        if quality:
            rows += ["", "The expert, on the demos it made (noisy rollouts; `own/` is its own evaluation):", *quality]
        self.stages_table = "\n".join(rows) + "\n"
        self.logger.log_dict(
            {
                r: {
                    "name": u.name,
                    "run_id": u.run_id,
                    "stage_hash": u.stage_hash,
                    "reused": u.reused,
                    "lineage": u.lineage,
                }
                for r, u in upstream.items()
            },
            "stages.json",
        )

    def scrub_record(self) -> None:
        """Hydra's record of the multirun (`multirun.yaml`, written after the sweep started) with the passwords of
        the URIs in it masked."""
        path = self.sweep_dir / "multirun.yaml" if self.sweep_dir is not None else None
        if path is not None and path.exists():
            scrub_file(path)

    def abandon(self) -> None:
        """The sweep ends without `on_multirun_end` (at exit): its parent run FAILED, its server stopped."""
        self.scrub_record()
        if self.logger is not None:
            self.logger.close("FAILED")  # no-op if closed already
            self.logger = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        self.scrub_record()
        if self.logger is None:
            atexit.unregister(self.abandon)
            self.abandon()
            return
        from orchestrator.tracking.query import child_runs, metric_histories

        self.logger.flush()
        children = child_runs(self.logger.uri, self.logger.run_id)
        wanted = list(self.metrics) + [self.spread[k] for k in ("mean", "std") if k in self.spread]
        rows = child_results(children, self.compare_by, list(dict.fromkeys(wanted)), self.facet_by)
        if rows:
            by, facet = self.compare_by, self.facet_by
            self.logger.log_dict({"rows": rows}, "comparison.json")
            text = f"# {config.preset}\n\n" + report.final_table(rows, by, self.metrics, facet)
            png = self.sweep_dir / "comparison.png"
            report.plot_final(rows, by, self.metrics, png, self.reference, facet)
            self.logger.log_artifact(str(png))
            if self.curves:
                histories = metric_histories(self.logger.uri, [r["run_id"] for r in rows], list(self.curves))
                # A curve no run logged (e.g. the model-based task loss under the PPO trainer) gets no panel.
                curves = {k: v for k, v in self.curves.items() if any(h.get(k) for h in histories.values())}
                if curves:
                    curves_png = self.sweep_dir / "curves.png"
                    report.plot_curves(rows, histories, by, curves, curves_png, facet)
                    self.logger.log_artifact(str(curves_png))
                    key, label = next(iter(curves.items()))
                    text += "\n" + report.curve_table(rows, histories, by, key, label, facet)
                    for row in rows:  # the first curve's summary, for claims about how a point learns
                        summary = report.curve_summary(histories.get(row["run_id"], {}).get(key, []))
                        row.update({f"curve/{k}": v for k, v in summary.items()})
            if self.spread:
                spread_png = self.sweep_dir / "spread.png"
                sp = self.spread
                level = None
                if self.expert_level is not None and sp["mean"] == "eval/time_until_fall_mean":
                    level = (self.expert_level, f"the expert on its demos ({self.expert_level:.2f} s)")
                label = sp.get("label", sp["mean"])
                physicsvae.plot_spread(rows, by, sp["mean"], sp["std"], label, spread_png, sp.get("title", ""), level)
                self.logger.log_artifact(str(spread_png))
            for name in self.figures:
                figure_png = self.sweep_dir / f"{name}.png"
                tasks.FIGURES[name](rows, by, facet, figure_png)
                self.logger.log_artifact(str(figure_png))
            if self.claims:
                text += "\n## The paper's statements and ours\n\n" + claims_table(self.claims, rows, by, facet)
            if self.stages_table:
                text += "\n## Stages shared by every point\n\n" + self.stages_table
            if self.paper:
                text += "\n## The paper\n\n" + "\n".join(f"- {line}" for line in self.paper) + "\n"
            table = self.sweep_dir / "comparison.md"
            table.write_text(text)
            self.logger.log_artifact(str(table))
            print(f"sweep {self.logger.run_id}: {len(rows)} runs\n" + text)
        self.logger.close("FINISHED")
        atexit.unregister(self.abandon)
        store = store_uri(config.tracking.uri, self.sweep_dir)
        look = f"mlflow ui --backend-store-uri {redact(store)} --host 127.0.0.1"
        if self.server is not None:
            self.server.stop()
            self.server = None
            look += f" --artifacts-destination {sqlite_artifacts(store)}"
        where = f"MLflow: {redact(store)}" if store.startswith("http") else f"MLflow UI: {look}"
        print(f"{where}  (sweep {self.logger.run_id})")


def refuse_unwritable(uri: str, experiment: str) -> None:
    """One line and exit 2 when the server would refuse the sweep's parent run in `experiment`
    (`orchestrator.preflight.own_experiment`), before any point or stage starts."""
    from orchestrator.preflight import InputError, own_experiment

    try:
        own_experiment(uri, experiment)
    except InputError as e:
        print(f"error: {scrub(str(e))}", file=sys.stderr)
        sys.exit(2)


def sqlite_artifacts(store: str) -> Path:
    """The artifacts beside a `sqlite:///` store, as `orchestrator.tracking.base.store_artifacts` places them."""
    return (Path(store.removeprefix("sqlite:///")).parent / "mlartifacts").resolve()


def claims_table(name: str, rows: list[dict[str, Any]], compare_by: str, facet_by: str | None) -> str:
    """The paper's statements beside ours, from whichever registry holds `name` (the task tables read the facet)."""
    if name in tasks.CLAIMS:
        return tasks.CLAIMS[name](rows, compare_by, facet_by)
    if name in amp.CLAIMS:
        return amp.CLAIMS[name](rows, compare_by)
    return physicsvae.CLAIMS[name](rows, compare_by)


def child_results(
    children: list[dict[str, Any]], compare_by: str, metrics: list[str], facet_by: str | None = None
) -> list[dict[str, Any]]:
    """One row per child run: the compared parameter, the facet (with facet_by), the seed and the final metrics."""
    keys = [compare_by, facet_by, "seed"] if facet_by else [compare_by, "seed"]
    rows = []
    for child in children:
        row = {k: child["params"].get(k) for k in keys}
        row.update({k: child["metrics"].get(k) for k in metrics})
        row["run_id"] = child["run_id"]
        rows.append(row)
    return sorted(rows, key=lambda r: tuple(str(r[k]) for k in keys))
