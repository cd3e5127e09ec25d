"""Benchmarks: `python -m orchestrator.bench sim|rollout|learners|pipeline|peer|learning|chaos [--json]`."""
