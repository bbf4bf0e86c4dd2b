"""The lazy reader interface shared by the FITS and HDF5 layouts: :class:`CoaddFile`."""

from __future__ import annotations

import abc
from typing import Any

from astropy.table import Table

from cellcoadd.errors import CellCoaddKeyError
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.patch_coadd import PatchMetadata


class CoaddFile(abc.ABC):
    """An open cellcoadd patch file, read lazily (one cell at a time).

    Use as a context manager or call :meth:`close`. ``metadata`` and ``cell_indices`` come
    from the small header part of the file; :meth:`read_cell` reads one cell's bytes.
    """

    #: ``"fits"`` or ``"hdf5"``.
    format_name: str = ""

    def __init__(self, path: str, metadata: PatchMetadata, cell_indices: list[tuple[int, int]]):
        self.path = path
        self.metadata = metadata
        self.cell_indices = cell_indices

    @abc.abstractmethod
    def read_cell(self, index: tuple[int, int]) -> CellCoadd:
        """The cell ``index`` (KeyError if the file does not hold it)."""

    @abc.abstractmethod
    def read_cell_inputs(self, index: tuple[int, int]) -> list[InputRecord]:
        """Only the inputs of cell ``index``."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the file."""

    def _check_index(self, index: tuple[int, int]) -> tuple[int, int]:
        key = (int(index[0]), int(index[1]))
        if key not in self.cell_indices:
            raise CellCoaddKeyError(
                f"{self.path}: no cell {key} in this file", path=self.path, cell=key, value=key
            )
        return key

    def read_inputs(self) -> Table:
        """All inputs of all cells as an astropy Table with ``cell_x`` / ``cell_y`` columns."""
        rows: list[dict[str, Any]] = []
        for cx, cy in self.cell_indices:
            for record in self.read_cell_inputs((cx, cy)):
                rows.append({"cell_x": cx, "cell_y": cy, **record.model_dump()})
        names = ["cell_x", "cell_y", *InputRecord.model_fields]
        if not rows:
            dtypes = [int, int, int, int, str, float, str, *([float] * 6)]
            return Table(names=names, dtype=dtypes)
        return Table(rows=[[row[name] for name in names] for row in rows], names=names)

    def __enter__(self) -> CoaddFile:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        meta = self.metadata
        return (
            f"<{type(self).__name__} {self.path!r}: tract {meta.tract} patch {meta.patch} "
            f"band {meta.band!r}, {len(self.cell_indices)} cells>"
        )
