"""The error a config value that cannot work raises (re-exported by `orchestrator.schema`)."""

from __future__ import annotations


class ConfigError(ValueError):
    """A config value that cannot work; the message starts with its dotted key."""
