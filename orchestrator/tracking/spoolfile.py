"""The spool file: an append-only JSON-lines file of the tracker's records that could not be sent yet.

Only `orchestrator.tracking.spool` writes it; it imports no tracking backend.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

log = logging.getLogger(__name__)

_SPOOL_LOCKS: dict[Path, threading.RLock] = {}


class Spool:
    """An append-only JSON-lines file of records that could not be sent, oldest first.

    `count` is the number of records in the file, those being replayed included; use under `lock`.
    """

    def __init__(self, path: Path):
        self.path = path
        self.lock = _SPOOL_LOCKS.setdefault(path.resolve(), threading.RLock())
        self.count = sum(1 for line in path.open() if line.strip()) if path.exists() else 0

    def append(self, records: Iterable[dict]) -> None:
        lines = [json.dumps(r) + "\n" for r in records]
        if lines:
            with self.lock, self.path.open("a") as f:
                f.writelines(lines)
                f.flush()
                os.fsync(f.fileno())
                self.count += len(lines)

    def read(self) -> tuple[list[dict], int]:
        """The spooled records and the file's length in bytes when read (for `replace`)."""
        with self.lock:
            if not self.path.exists():
                return [], 0
            data = self.path.read_bytes()
        return self._parse(data, 1), len(data)

    def replace(
        self, records: list[dict], read_up_to: int | None = None, resolve: Callable[[dict], dict] | None = None
    ) -> None:
        """Make `records` the spool (atomically), followed by whatever was appended after the first
        `read_up_to` bytes were read (None: nothing is kept), each passed through `resolve`; no records
        at all deletes the file."""
        with self.lock:
            later: list[dict] = []
            if read_up_to is not None and self.path.exists():
                with self.path.open("rb") as f:
                    f.seek(read_up_to)
                    later = self._parse(f.read(), None)
            everything = records + later
            if resolve is not None:
                everything = [resolve(r) for r in everything]
            if not everything:
                self.path.unlink(missing_ok=True)
            else:
                tmp = self.path.with_suffix(".tmp")
                tmp.write_text("".join(json.dumps(r) + "\n" for r in everything))
                os.replace(tmp, self.path)
            self.count = len(everything)

    def _parse(self, data: bytes, first_line: int | None) -> list[dict]:
        """Records from JSON lines; a line that does not parse (a write cut short by a crash) is skipped."""
        records = []
        for number, line in enumerate(data.decode(errors="replace").splitlines(), first_line or 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                record = None
            if isinstance(record, dict) and "op" in record and "run" in record:
                records.append(record)
            elif line.strip():
                where = f"line {number}" if first_line else "a line appended during a replay"
                log.warning("tracking: %s %s is not a record; skipped", self.path, where)
        return records
