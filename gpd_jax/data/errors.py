"""Errors raised for bad input data: always name the file (or sample) and the reason."""

from __future__ import annotations

import os


class DataError(ValueError):
    """Bad or unreadable input data. `path` names the file, `reason` says what is wrong with it."""

    def __init__(self, path: str | os.PathLike | None, reason: str):
        self.path = None if path is None else os.fspath(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}" if self.path else reason)
