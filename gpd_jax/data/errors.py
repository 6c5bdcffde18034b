"""Errors raised for bad input data: always name the file (or sample) and the reason."""

from __future__ import annotations

import os


class DataError(ValueError):
    """Bad or unreadable input data. `path` names the file, `reason` says what is wrong with it."""

    def __init__(self, path: str | os.PathLike | None, reason: str):
        self.path = None if path is None else os.fspath(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}" if self.path else reason)

    def __reduce__(self):
        # as its arguments, not its message: a build's worker process sends the error back to the command, which
        # names the file (the default reduction calls DataError(message) and the pool breaks instead)
        return type(self), (self.path, self.reason)
