"""Benchmarks: `python -m orchestrator.bench {sim} [--json]`."""
