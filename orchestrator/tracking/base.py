"""The tracker interface the training code writes through, its no-op twin, and config flattening.

Learners and the loop return plain dicts; only a `RunLogger` writes them anywhere (STYLE.md item 6).
This module imports no tracking backend, so code that only needs the interface stays light.
"""

from __future__ import annotations

import abc
import json
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

# MLflow's limit on a param value, in characters (mlflow.utils.validation.MAX_PARAM_VAL_LENGTH).
MAX_PARAM_VALUE_LENGTH = 6000
TRUNCATION_MARK = "...[truncated]"


class RunLogger(abc.ABC):
    """Where params, metrics, tags and artifacts of one run go.

    Metric keys are namespaced by the caller (`rollout/…`, `vae/…`); `step` is the number of
    environment samples collected so far (DESIGN.md, tracking conventions). A tracker never lets
    a tracking failure escape into training. Usable as a context manager: the run closes
    FINISHED, or FAILED when the block raises.
    """

    @property
    @abc.abstractmethod
    def run_id(self) -> str | None:
        """The backend's id of the run, or None (no-op tracker, or a run not created yet)."""

    @abc.abstractmethod
    def log_params(self, params: Mapping[str, Any]) -> None:
        """Record run parameters (string values; see `flatten` for nested configs)."""

    @abc.abstractmethod
    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        """Record scalar metrics at `step`; may be buffered until `flush`."""

    @abc.abstractmethod
    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Set run tags (values are stringified)."""

    @abc.abstractmethod
    def log_artifact(self, local_path: str | Path, artifact_path: str | None = None) -> None:
        """Upload a file (or a directory's contents) under `artifact_path` in the run's artifacts."""

    @abc.abstractmethod
    def log_dict(self, obj: Any, artifact_file: str) -> None:
        """Store `obj` as a text artifact: YAML when `artifact_file` ends in .yaml/.yml, else JSON."""

    def log_text(self, text: str, artifact_file: str) -> None:
        """Store `text` as the artifact `artifact_file` (e.g. `hydra/config.yaml`)."""
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / Path(artifact_file).name
            path.write_text(text)
            self.log_artifact(path, _parent(artifact_file))

    def log_figure(self, fig: Any, artifact_file: str) -> None:
        """Store a matplotlib-like figure (anything with `savefig(path)`) as an image artifact."""
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / Path(artifact_file).name
            fig.savefig(path)
            self.log_artifact(path, _parent(artifact_file))

    def delete_artifact(self, artifact_path: str) -> None:  # noqa: B027 - optional hook
        """Delete a file logged earlier (a checkpoint older than those kept); a tracker may keep it."""

    def flush(self) -> None:  # noqa: B027 - optional hook, a no-op unless the tracker buffers
        """Send whatever is buffered now."""

    @abc.abstractmethod
    def close(self, status: str = "FINISHED") -> None:
        """Flush and end the run with a terminal status (FINISHED, FAILED or KILLED)."""

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close("FAILED" if exc_type is not None else "FINISHED")


class NoOpLogger(RunLogger):
    """A tracker that accepts every call and records nothing (`tracking=off`, tests)."""

    @property
    def run_id(self) -> str | None:
        return None

    def log_params(self, params: Mapping[str, Any]) -> None:
        pass

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        pass

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        pass

    def log_artifact(self, local_path: str | Path, artifact_path: str | None = None) -> None:
        pass

    def log_dict(self, obj: Any, artifact_file: str) -> None:
        pass

    def log_text(self, text: str, artifact_file: str) -> None:
        pass

    def log_figure(self, fig: Any, artifact_file: str) -> None:
        pass

    def close(self, status: str = "FINISHED") -> None:
        pass


def flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Flatten a nested config into dotted keys with string values, for run params.

    Mappings nest by key (`algo.alpha`); sequences that hold mappings or sequences nest by index
    (`stages.0.name`); a sequence of scalars stays one value (`motion.clips` -> "['walk', 'run']"),
    which reads better in the MLflow UI than one param per clip. Empty mappings and sequences
    become "{}" and "[]". Values longer than MLflow's limit are cut to exactly
    `MAX_PARAM_VALUE_LENGTH` characters, ending in a visible truncation mark.

    >>> flatten({"algo": {"alpha": 3e-4, "prior": "learned"}, "clips": ["a", "b"], "seed": 0})
    {'algo.alpha': '0.0003', 'algo.prior': 'learned', 'clips': "['a', 'b']", 'seed': '0'}
    """
    out: dict[str, str] = {}
    _flatten_into(out, config, prefix)
    return out


def _flatten_into(out: dict[str, str], value: Any, key: str) -> None:
    if isinstance(value, Mapping):
        if not value and key:
            out[key] = "{}"
        for k, v in value.items():
            _flatten_into(out, v, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list | tuple) and any(isinstance(v, Mapping | list | tuple) for v in value):
        for i, v in enumerate(value):
            _flatten_into(out, v, f"{key}.{i}" if key else str(i))
    else:
        out[key] = truncate(str(list(value)) if isinstance(value, tuple) else str(value))


def truncate(text: str, limit: int = MAX_PARAM_VALUE_LENGTH) -> str:
    """`text` if it fits in `limit` characters, else a prefix plus a mark, `limit` characters in all."""
    if len(text) <= limit:
        return text
    return text[: limit - len(TRUNCATION_MARK)] + TRUNCATION_MARK


def dump_text(obj: Any, artifact_file: str) -> str:
    """The text `log_dict` stores: YAML for .yaml/.yml names, JSON (indented, keys in order) otherwise."""
    if artifact_file.endswith((".yaml", ".yml")):
        import yaml  # a dependency of mlflow and hydra; imported only when YAML is asked for

        return yaml.safe_dump(obj, sort_keys=False)
    return json.dumps(obj, indent=2, default=str)


def _parent(artifact_file: str) -> str | None:
    parent = Path(artifact_file).parent.as_posix()
    return None if parent in ("", ".") else parent


# Marks an experiment as model training, so that the MLflow UI opens it on its training view (runs,
# metrics, charts) rather than the GenAI one.
EXPERIMENT_TAGS = {"mlflow.experimentKind": "custom_model_development"}


def store_artifacts(uri: str) -> str | None:
    """Where a new experiment in a SQLite store keeps its artifacts: beside the database file (MLflow's own
    default, ./mlruns under the working directory, would scatter them); None (the server decides) otherwise."""
    if not uri.startswith("sqlite:///"):
        return None
    return (Path(uri.removeprefix("sqlite:///")).parent / "mlartifacts").resolve().as_uri()
