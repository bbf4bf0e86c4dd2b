"""How many inputs each cell of a coadd kept, in one vocabulary, and a warning when few.

Vocabulary (the same in ``cellcoadd demo``, ``cellcoadd info`` and ``cellcoadd build``):

* an **exposure** is one CCD (detector) of one visit, one input file;
* an **input record** is one (cell, exposure) pair: every exposure whose footprint
  touches a cell's neighbourhood gets a record in that cell, with its status (``used``
  or the rejection reason). A visit whose focal plane straddles a cell gives the cell one
  record per CCD it touches, so records outnumber (cell, visit) pairs;
* a **visit is used in a cell** when one of its CCDs is used there; it is **lost to an
  edge** when none is used and at least one was rejected as ``edge`` (the cell crosses
  a CCD edge or gap).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchCoadd

#: warn when more than this fraction of the cells is empty ...
EMPTY_FRACTION_LIMIT = 0.5
#: ... or when more than this fraction of the (cell, visit) pairs is lost to CCD edges
EDGE_FRACTION_LIMIT = 0.5


@dataclass(frozen=True)
class InputCounts:
    """What the cells of a patch kept.

    Attributes
    ----------
    n_cells, n_empty : int
        Cells (inner and border) and cells without any used input.
    records : Counter
        Input records (one per cell and exposure) by status.
    visits : Counter
        (cell, visit) pairs by outcome: ``used``, else the most informative rejection
        reason of the visit's CCDs (``edge`` before ``no_overlap``).
    visits_used_per_cell : ndarray
        Per cell, the visits used.
    n_visits : int
        Distinct visits among the records.
    """

    n_cells: int
    n_empty: int
    records: Counter
    visits: Counter
    visits_used_per_cell: np.ndarray
    n_visits: int

    @property
    def edge_fraction(self) -> float:
        """Fraction of the (cell, visit) pairs that overlap the cell and are lost to edges."""
        touching = sum(n for outcome, n in self.visits.items() if outcome != "no_overlap")
        return self.visits["edge"] / touching if touching else 0.0

    def summary_lines(self) -> list[str]:
        """Two report lines: the records, then the visits per cell."""
        total = sum(self.records.values())
        rejected = ", ".join(
            f"{reason} {count}"
            for reason, count in sorted(self.records.items())
            if reason != "used"
        )
        per = self.visits_used_per_cell
        return [
            f"input records (one per cell and overlapping exposure, i.e. CCD of a visit): "
            f"{total}: used {self.records['used']}, rejected: {rejected or 'none'}",
            f"visits used per cell (of {self.n_visits}): min {per.min() if per.size else 0}, "
            f"median {np.median(per) if per.size else 0:g}, max {per.max() if per.size else 0}; "
            f"{100 * self.edge_fraction:.0f}% of the (cell, visit) pairs lost to CCD edges",
        ]


class CellInputs(Protocol):
    """What counting needs of a cell (a CellCoadd has it)."""

    @property
    def inputs(self) -> list[InputRecord]: ...

    @property
    def is_empty(self) -> bool: ...


def count_inputs(coadd: PatchCoadd) -> InputCounts:
    """Count the input records and the visits of every cell of ``coadd``."""
    return count_cell_inputs(coadd.cells.values())


def count_cell_inputs(cells: Iterable[CellInputs]) -> InputCounts:
    """Count the input records and the visits of ``cells`` (see :func:`count_inputs`)."""
    records: Counter = Counter()
    visits: Counter = Counter()
    per_cell = []
    all_visits: set[int] = set()
    n_empty = 0
    n_cells = 0
    for cell in cells:
        n_cells += 1
        by_visit: dict[int, set[str]] = {}
        for record in cell.inputs:
            records[record.status] += 1
            by_visit.setdefault(record.visit, set()).add(record.status)
        all_visits.update(by_visit)
        used = 0
        for statuses in by_visit.values():
            if "used" in statuses:
                outcome = "used"
                used += 1
            elif "edge" in statuses:
                outcome = "edge"
            else:
                reasons = statuses - {"no_overlap"}
                outcome = min(reasons) if reasons else "no_overlap"
            visits[outcome] += 1
        per_cell.append(used)
        n_empty += cell.is_empty
    return InputCounts(
        n_cells=n_cells,
        n_empty=n_empty,
        records=records,
        visits=visits,
        visits_used_per_cell=np.array(per_cell, dtype=int),
        n_visits=len(all_visits),
    )


def coverage_warning(coadd: PatchCoadd) -> str | None:
    """A one-paragraph warning when most cells are empty or most visits are lost to
    CCD edges, with the likely cause; None when the coadd looks useful.
    """
    return counts_warning(count_inputs(coadd), coadd.metadata.skymap_config)


def counts_warning(counts: InputCounts, config: SkyMapConfig) -> str | None:
    """:func:`coverage_warning` from the counts of a patch's cells (``config``: its sky
    map's)."""
    empty = counts.n_empty / counts.n_cells if counts.n_cells else 0.0
    if empty <= EMPTY_FRACTION_LIMIT and counts.edge_fraction <= EDGE_FRACTION_LIMIT:
        return None
    outer = (config.cell_inner + 2 * config.cell_border) * config.pixel_scale
    per = counts.visits_used_per_cell
    return (
        f"warning: {counts.n_empty} of {counts.n_cells} cells are empty and "
        f"{100 * counts.edge_fraction:.0f}% of the (cell, visit) pairs were rejected because "
        f"a CCD edge or gap crosses the cell (median {np.median(per):g} of {counts.n_visits} "
        f"visits used per cell). Edge-free cells need CCDs much larger than a cell's outer "
        f'box ({outer:.0f}" plus the warp kernel): likely cause, CCDs small compared with '
        "cells. Use larger CCDs (e.g. `cellcoadd simulate --ccd-pixels`), more visits or "
        "smaller cells (SkyMapConfig cell_inner, cell_border)."
    )


__all__ = [
    "EDGE_FRACTION_LIMIT",
    "EMPTY_FRACTION_LIMIT",
    "InputCounts",
    "coverage_warning",
    "count_cell_inputs",
    "count_inputs",
    "counts_warning",
]
