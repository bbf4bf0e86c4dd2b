"""Trim catalogs measured on cells or patches to their unique areas.

A catalog measured on a cell's outer region contains objects that other cells also
measure. Keeping only objects whose position falls in the cell's inner region (half-open,
pixel centres at integers) keeps every object exactly once over the sky.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcoadd.errors import CellCoaddKeyError
from cellcoadd.geometry.skymap import SkyMap
from cellcoadd.geometry.tract import Cell


def _column(catalog: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(catalog[name], dtype=float)
    except (KeyError, ValueError, IndexError) as err:
        raise CellCoaddKeyError(f"catalog has no column {name!r}", value=name) from err


def flag_unique(
    catalog: Any,
    skymap: SkyMap,
    *,
    tract: int,
    patch: tuple[int, int] | None = None,
    cell: tuple[int, int] | None = None,
    ra: str = "ra",
    dec: str = "dec",
) -> dict[str, np.ndarray]:
    """Flags saying which catalog rows lie in the unique areas of a tract, patch and cell.

    Parameters
    ----------
    catalog : structured array, astropy Table or dict of arrays
        Must hold the sky position columns named by ``ra`` and ``dec`` (deg).
    skymap : SkyMap
        The sky map the catalog was measured on.
    tract : int
        Tract the catalog was measured on.
    patch : (px, py), optional
        Patch the catalog was measured on.
    cell : (cx, cy), optional
        Tract-global cell index the catalog was measured on.
    ra, dec : str
        Column names of the positions.

    Returns
    -------
    dict of boolean arrays
        ``is_tract_inner`` (the tract owns the position), ``is_patch_inner`` (and ``patch``
        owns it; False everywhere when ``patch`` is None), ``is_cell_inner`` (and ``cell``
        owns it; False when ``cell`` is None), and ``is_primary``: the row is kept by the
        finest level given (cell, else patch, else tract), so over all cells (or patches,
        or tracts) each object is primary exactly once.
    """
    where = skymap.locate(_column(catalog, ra), _column(catalog, dec))
    is_tract_inner = where["tract"] == tract
    if patch is not None:
        is_patch_inner = (
            is_tract_inner & (where["patch_x"] == patch[0]) & (where["patch_y"] == patch[1])
        )
    else:
        is_patch_inner = np.zeros_like(is_tract_inner)
    if cell is not None:
        is_cell_inner = is_tract_inner & (where["cell_x"] == cell[0]) & (where["cell_y"] == cell[1])
    else:
        is_cell_inner = np.zeros_like(is_tract_inner)
    if cell is not None:
        is_primary = is_cell_inner
    elif patch is not None:
        is_primary = is_patch_inner
    else:
        is_primary = is_tract_inner
    return {
        "is_cell_inner": is_cell_inner,
        "is_patch_inner": is_patch_inner,
        "is_tract_inner": is_tract_inner,
        "is_primary": is_primary.copy(),
    }


def sky_ids(
    catalog: Any, skymap: SkyMap, *, ra: str = "ra", dec: str = "dec"
) -> dict[str, np.ndarray]:
    """Where each catalog row lies, in our ids and Rubin's: catalogue columns.

    Parameters
    ----------
    catalog : structured array, astropy Table or dict of arrays
        Must hold the sky position columns named by ``ra`` and ``dec`` (deg).
    skymap : SkyMap
        The sky map to place the rows on.
    ra, dec : str
        Column names of the positions.

    Returns
    -------
    dict of int64 arrays
        ``tract``; ``patch_x, patch_y`` and Rubin's ``patch`` (the butler's sequential
        patch id, ``patch_y * nx + patch_x``); ``cell_x, cell_y`` (tract-global cell
        index) and Rubin's ``rubin_cell_x, rubin_cell_y`` (the cell's index in its patch,
        counted from the patch's first border cell). -1 where no tract owns the position.
    """
    where = skymap.locate(_column(catalog, ra), _column(catalog, dec))
    names = {
        "tract": "tract",
        "patch": "patch_id",
        "patch_x": "patch_x",
        "patch_y": "patch_y",
        "cell_x": "cell_x",
        "cell_y": "cell_y",
        "rubin_cell_x": "rubin_cell_x",
        "rubin_cell_y": "rubin_cell_y",
    }
    return {column: np.asarray(where[field]).copy() for column, field in names.items()}


def _select_rows(catalog: Any, keep: np.ndarray) -> Any:
    if isinstance(catalog, dict):
        return {name: np.asarray(values)[keep] for name, values in catalog.items()}
    return catalog[keep]


def trim_to_cell(
    catalog: Any, skymap: SkyMap, cell: Cell, *, ra: str = "ra", dec: str = "dec"
) -> Any:
    """The rows of ``catalog`` in the unique (inner) area of ``cell``, same container type."""
    flags = flag_unique(catalog, skymap, tract=cell.tract, cell=cell.index, ra=ra, dec=dec)
    return _select_rows(catalog, flags["is_primary"])


def trim_to_patch(
    catalog: Any,
    skymap: SkyMap,
    tract: int,
    patch: tuple[int, int],
    *,
    ra: str = "ra",
    dec: str = "dec",
) -> Any:
    """The rows of ``catalog`` in the unique (inner) area of a patch, same container type."""
    flags = flag_unique(catalog, skymap, tract=tract, patch=patch, ra=ra, dec=dec)
    return _select_rows(catalog, flags["is_primary"])
