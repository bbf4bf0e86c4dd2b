"""Aperture corrections of a coadd's cells, as Rubin's ``lsst.cell_coadds`` keeps them.

Rubin stores one aperture-correction map per cell: for each measurement algorithm (a
column of its ``APCORR`` table, e.g. ``base_PsfFlux_instFlux``) the dimensionless factor
that brings that algorithm's flux to the aperture flux at the cell's centre. cellcoadd
does not compute them; it keeps what a Rubin file holds so that writing the coadd back
loses nothing (``docs/format.md``, "LSST cell_coadds layout").
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from cellcoadd.errors import CellCoaddValueError

#: Longest algorithm name kept (FITS ``TTYPEn`` values hold 68 characters).
MAX_ALGORITHM_NAME = 68


class CellApertureCorrection(BaseModel):
    """The aperture corrections of one cell.

    Parameters
    ----------
    index : (int, int)
        Tract-global cell index ``(cx, cy)``.
    values : tuple of float or None
        One factor per algorithm of :attr:`ApertureCorrections.algorithms`, in that order
        (dimensionless); None where the file holds NaN (no value for that algorithm).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    index: tuple[int, int]
    values: tuple[float | None, ...]

    @field_validator("values")
    @classmethod
    def _finite(cls, values: tuple[float | None, ...]) -> tuple[float | None, ...]:
        for value in values:
            if value is not None and not math.isfinite(value):
                raise CellCoaddValueError(
                    f"aperture correction {value} is not finite (use None for none)", value=value
                )
        return values


class ApertureCorrections(BaseModel):
    """Per-cell aperture corrections: the algorithms (columns) and one row per cell.

    Parameters
    ----------
    algorithms : tuple of str
        Algorithm names, in the order of the file's columns.
    cells : tuple of CellApertureCorrection
        One entry per cell that has a map, in the order of the file's rows; no cell twice.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    algorithms: tuple[str, ...] = Field(min_length=1)
    cells: tuple[CellApertureCorrection, ...] = ()

    @field_validator("algorithms")
    @classmethod
    def _names(cls, algorithms: tuple[str, ...]) -> tuple[str, ...]:
        for name in algorithms:
            if not (0 < len(name) <= MAX_ALGORITHM_NAME and name.isascii() and name.isprintable()):
                raise CellCoaddValueError(
                    f"aperture-correction algorithm name {name!r} is not 1 to "
                    f"{MAX_ALGORITHM_NAME} printable ASCII characters",
                    value=name,
                )
            if name.lower() in ("x", "y"):
                raise CellCoaddValueError(
                    f"aperture-correction algorithm name {name!r} is a cell-index column",
                    value=name,
                )
        if len({name.lower() for name in algorithms}) != len(algorithms):
            raise CellCoaddValueError("an aperture-correction algorithm is listed twice")
        return algorithms

    @model_validator(mode="after")
    def _rows(self) -> ApertureCorrections:
        seen: set[tuple[int, int]] = set()
        for cell in self.cells:
            if len(cell.values) != len(self.algorithms):
                raise CellCoaddValueError(
                    f"cell {cell.index} has {len(cell.values)} aperture corrections for "
                    f"{len(self.algorithms)} algorithms",
                    value=cell.index,
                )
            if cell.index in seen:
                raise CellCoaddValueError(
                    f"cell {cell.index} has two aperture-correction maps", value=cell.index
                )
            seen.add(cell.index)
        return self

    def of(self, index: tuple[int, int]) -> dict[str, float]:
        """The map of cell ``index``: algorithm -> factor, without the missing values
        (empty when the cell has none)."""
        for cell in self.cells:
            if cell.index == tuple(index):
                return {
                    name: value
                    for name, value in zip(self.algorithms, cell.values, strict=True)
                    if value is not None
                }
        return {}
