"""Errors raised by the storage layer."""

from __future__ import annotations

import os


class CellCoaddFormatError(Exception):
    """A file is not a readable cellcoadd (or exposure) file: names the file and the problem."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
