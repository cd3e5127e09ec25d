"""Tracking URIs, told without importing mlflow: the store a run writes to, and which URIs MLflow can use.

`store_uri` is the one place that says where a run (or a sweep) without `tracking.uri` keeps its records:
the embedded SQLite store `mlflow.db` in its directory. `tracking_uri_error` is asked at composition.

A URI may carry a credential (`postgresql://user:pw@host/db`, `http://user:pw@host`, `?token=`): `redact` is
the URI fit to print, `scrub` any text with the credentials of the URIs in it (and of those passed to `hide`)
masked, and `hide(uri)` also masks them in every log record of the process (tracebacks included).
`credentials_to_env` moves an HTTP server's user and password into MLFLOW_TRACKING_USERNAME /
MLFLOW_TRACKING_PASSWORD, where MLflow reads them, so that the URLs MLflow builds itself (in its errors, and in
the "View run at" lines it writes to stdout) carry none.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import traceback
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, quote, unquote, urlparse, urlsplit

# The schemes of MLflow's own tracking stores (a bare path is a file store); plug-ins add theirs under
# the `mlflow.tracking_store` entry point. A database scheme may name its driver: postgresql+psycopg2.
TRACKING_SCHEMES = (
    "file", "sqlite", "postgresql", "mysql", "mssql", "http", "https", "databricks", "databricks-uc", "uc",
)  # fmt: skip


def tracking_uri_error(uri: str) -> str | None:
    """Why MLflow cannot use `uri` as a tracking store (an unknown scheme, a file store without the opt-in), or None."""
    if uri in ("databricks", "databricks-uc", "uc"):
        return None
    scheme = urlparse(uri).scheme  # as MLflow reads it
    if scheme in ("", "file") and os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").lower() not in ("true", "1"):
        # MLflow 3's file store is in maintenance mode: it refuses to open without the opt-in.
        return (
            f"{redact(uri)!r} is an MLflow file store, which MLflow 3 opens only with MLFLOW_ALLOW_FILE_STORE=true; "
            "use sqlite:///PATH/mlflow.db (or leave tracking.uri unset: a SQLite store in the run directory)"
        )
    if scheme in ("http", "https") and not urlparse(uri).hostname:
        # http:/host parses as a path with no host: every request would fail and the run would spool for ever
        return f"{redact(uri)!r} names no host (a server is {scheme}://HOST:PORT)"
    if not scheme or scheme.split("+")[0] in TRACKING_SCHEMES:
        return None
    plugins = {e.name for e in entry_points(group="mlflow.tracking_store")}
    if scheme in plugins:
        return None
    known = ", ".join(f"{s}:" for s in (*TRACKING_SCHEMES, *sorted(plugins)))
    return f"MLflow has no tracking store for the scheme {scheme!r} of {redact(uri)!r} (a path, or one of {known})"


def embedded_uri(directory: str | Path) -> str:
    """The tracking URI of the embedded store of a run (or sweep) directory: `<directory>/mlflow.db`."""
    return f"sqlite:///{Path(directory).resolve() / 'mlflow.db'}"


def store_uri(uri: str | None, directory: str | Path) -> str:
    """The store a run or sweep writes to: `tracking.uri` as given, else the embedded one in `directory`."""
    return uri or embedded_uri(directory)


# ---------------------------------------------------------------- credentials

MASK = "***"
# Query parameters whose value is a credential (`?password=`, `?token=`, `?client_secret=`).
SECRET_QUERY_KEYS = ("password", "passwd", "pwd", "token", "secret")
# Shorter secrets are masked only where they stand in a URI: masking every "pw" in free text would mangle it.
MIN_SECRET_LENGTH = 4
# The password of a URI's user information inside free text: `scheme://user:` then the password up to `@`
# (also as Hydra logs an override, its colons escaped: `http\://user\:pw@host`).
_USERINFO = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.-]*\\?://[^\s/:@\\]*\\?:)[^\s/@]+@")
_HIDDEN: set[str] = set()  # the secrets that `scrub` masks wherever they stand
_HIDE_LOCK = threading.Lock()


def uri_secrets(uri: str | None) -> set[str]:
    """The credentials in `uri`: its password and secret query values, as written and percent-decoded."""
    if not uri:
        return set()
    parts = urlsplit(uri)
    found = set()
    if parts.password:
        found |= {parts.password, unquote(parts.password)}
    for key, value in parse_qsl(parts.query):
        if value and any(k in key.lower() for k in SECRET_QUERY_KEYS):
            found |= {value, quote(value, safe="")}
    return {s for s in found if s}


def redact(uri: str | None) -> str | None:
    """`uri` with its credentials masked: `postgresql://user:***@host/db`; unchanged without any."""
    if not uri:
        return uri
    parts = urlsplit(uri)
    out = uri
    if parts.password:
        userinfo, _, host = parts.netloc.rpartition("@")
        user = userinfo.split(":", 1)[0]
        out = out.replace(parts.netloc, f"{user}:{MASK}@{host}", 1)
    if parts.query:
        pieces = []
        for piece in parts.query.split("&"):
            key, _, value = piece.partition("=")
            secret = value and any(k in unquote(key).lower() for k in SECRET_QUERY_KEYS)
            pieces.append(f"{key}={MASK}" if secret else piece)
        out = out.replace(parts.query, "&".join(pieces), 1)
    return out


def scrub(text: str) -> str:
    """`text` with the password of every URI in it masked, and every secret given to `hide`."""
    text = _USERINFO.sub(lambda m: f"{m['head']}{MASK}@", text)
    for secret in sorted(_HIDDEN, key=len, reverse=True):
        text = text.replace(secret, MASK)
    return text


def scrub_file(path: Path) -> None:
    """`path` rewritten with `scrub` applied, if that changes it (a record on disk of a command as typed)."""
    text = path.read_text()
    if (clean := scrub(text)) != text:
        path.write_text(clean)


def scrub_tree(obj: Any) -> Any:
    """`obj` (nested dicts, lists and tuples) with `scrub` applied to every string in it."""
    if isinstance(obj, str):
        return scrub(obj)
    if isinstance(obj, dict):
        return {k: scrub_tree(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(scrub_tree(v) for v in obj)
    return obj


def hide(uri: str | None) -> None:
    """Mask `uri`'s credentials wherever `scrub` is applied, and in every log record of this process from now on
    (and keep MLflow from printing its server's URL)."""
    secrets = {s for s in uri_secrets(uri) if len(s) >= MIN_SECRET_LENGTH}
    if not secrets:
        return
    with _HIDE_LOCK:
        if not _HIDDEN:
            _install_record_factory()
            # MLflow writes "View run ... at: <server URL>" to stdout itself, past logging; our own lines say where.
            os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        _HIDDEN.update(secrets)


def credentials_to_env(uri: str) -> str:
    """`uri` without its user and password, which go to MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD, for an
    HTTP(S) tracking server; any other URI, or one whose credentials differ from those already set there, as is."""
    parts = urlsplit(uri)
    if parts.scheme not in ("http", "https") or parts.password is None:
        return uri
    user, password = unquote(parts.username or ""), unquote(parts.password)
    wanted = {"MLFLOW_TRACKING_USERNAME": user, "MLFLOW_TRACKING_PASSWORD": password}
    if any(os.environ.get(key, value) != value for key, value in wanted.items()):
        return uri
    os.environ.update(wanted)
    return uri.replace(parts.netloc, parts.netloc.rpartition("@")[2], 1)


def _install_record_factory() -> None:
    """Scrub each log record as it is made: its message, and its traceback, formatted now for the handlers."""
    make = logging.getLogRecordFactory()

    def scrubbed(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = make(*args, **kwargs)
        try:
            message = record.getMessage()
        except Exception:  # noqa: BLE001 - a malformed record is the logging module's to report
            return record
        clean = scrub(message)
        if clean != message:
            record.msg, record.args = clean, None
        if record.exc_info and record.exc_info[0] is not None:
            record.exc_text = scrub("".join(traceback.format_exception(*record.exc_info)).rstrip("\n"))
        return record

    logging.setLogRecordFactory(scrubbed)


class ScrubbedStream:
    """A text stream that masks URI passwords in what is written through it (`scrub`): stderr, for the lines
    other code writes there itself (Hydra's "Error executing job with overrides: [...]", its tracebacks)."""

    def __init__(self, stream: Any):
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(scrub(text))
        return len(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)
