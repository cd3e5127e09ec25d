"""The control plane: composes a config, builds a run's components on a runtime, trains them through the
shared trainer, tracks everything in MLflow, and runs sweeps and their reports (docs/architecture.md)."""
