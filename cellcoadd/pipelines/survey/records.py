"""The typed records of a survey run: a patch's key, what a worker reports about the
patch it built, and the ledger's record of each patch.

One shape for the run, the ledger and the report: the worker returns a
:class:`PatchSummary`, the run stores a :class:`PatchRecord` (with the summary inside) in
the ledger, and the report reads the records back; paths are relative to the run's
output directory, so a moved or copied directory stays valid.
"""

from __future__ import annotations

from enum import Enum
from typing import NamedTuple

from pydantic import BaseModel, ConfigDict, Field


class PatchKey(NamedTuple):
    """A patch of a survey run: band, tract id and patch index ``(px, py)``."""

    band: str
    tract: int
    px: int
    py: int

    @property
    def patch(self) -> tuple[int, int]:
        return (self.px, self.py)

    def __str__(self) -> str:
        return f"{self.band} tract {self.tract} patch {self.px},{self.py}"


class PatchState(str, Enum):
    """Where a patch stands in the ledger."""

    PENDING = "pending"
    DONE = "done"
    FAILED = "failed"
    NO_INPUTS = "no_inputs"


class InputStamp(BaseModel):
    """One input of a patch as planned: its index row and checksum, and its exposure
    file's path, size and mtime (ns) when indexed."""

    model_config = ConfigDict(frozen=True)

    row: int
    checksum: str
    path: str
    size: int
    mtime_ns: int


class PatchSummary(BaseModel):
    """What a worker did for one patch (a few kB): its file, cells, inputs, cost."""

    model_config = ConfigDict(frozen=True)

    output: str = Field(description="the patch file, relative to the output directory")
    checksum: str = Field(description="SHA-256 of the file")
    size: int = Field(description="bytes")
    cells: int
    inner_cells: int
    empty_cells: int
    empty_inner_cells: int
    inputs: int = Field(description="inputs given to the build")
    inputs_used: int = Field(description="inputs used by at least one cell")
    rejected_records: dict[str, int] = Field(description="cell input records by reason")
    depth: list[tuple[int, int, int]] = Field(description="(cx, cy, inputs used) per cell")
    parts: int = 1
    parts_cpu_s: list[float] = Field(default_factory=list)
    wall_s: float = Field(description="worker seconds, summed over parts and the write")
    cpu_s: float = Field(description="worker CPU seconds, summed over parts and the write")
    peak_rss_mb: float
    worker: str = Field(description="host:pid that wrote the file")
    warnings: list[str] = Field(
        default_factory=list,
        description="the build's warnings, one line each (``Category: message``), in order",
    )


class PatchRecord(BaseModel):
    """One patch in the ledger: what it is built from and what became of it."""

    model_config = ConfigDict(frozen=True)

    band: str
    tract: int
    px: int
    py: int
    state: PatchState
    signature: str = Field(description="SHA-256 of everything the patch's bytes depend on")
    config_hash: str
    seed: int
    version: str
    inputs: list[InputStamp]
    output: str = Field(description="relative to the output directory")
    checksum: str | None = None
    size: int | None = None
    attempts: int = 0
    error: str | None = None
    retried: list[str] = Field(default_factory=list, description="why earlier attempts failed")
    lost_workers: int = Field(0, description="times the task was moved after its worker died")
    summary: PatchSummary | None = None

    @property
    def key(self) -> PatchKey:
        return PatchKey(self.band, self.tract, self.px, self.py)
