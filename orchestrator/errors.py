"""The errors that end a command in one line: a config value that cannot work (re-exported by `orchestrator.schema`),
a service that does not come up."""

from __future__ import annotations


class ConfigError(ValueError):
    """A config value that cannot work; the message starts with its dotted key."""


class ServiceError(RuntimeError):
    """A service (a server, its database, its users) did not come up, could not be set up or stopped; the message is
    one line naming it and its log."""
