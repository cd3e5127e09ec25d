"""Errors raised on bad motion data: they name the file and, where known, the frame."""

from __future__ import annotations


class ClipError(ValueError):
    """A clip that cannot be used, with the file and frame it was found in."""

    def __init__(self, path: object, message: str, frame: int | None = None):
        self.path = str(path)
        self.frame = frame
        self.message = message
        where = f"{self.path}: frame {frame}" if frame is not None else self.path
        super().__init__(f"{where}: {message}")
