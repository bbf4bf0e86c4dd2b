"""Empty cells cost no pixel bytes (format 1.6): the size of a patch file follows what it
holds, in both layouts, and reading gives back every bit; a plane marked empty in a cell
with data is refused; files that store an empty cell's pixels (before 1.6) still read."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from coadd_factory import MEDIUM, make_patch

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.io.coadd import fits_format, hdf5_format
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.planes import plane

FORMATS = ["patch.fits", "patch.h5", "patch.fits.fz"]


def _pixel_bytes(cell: CellCoadd) -> int:
    """What a cell's planes hold, in bytes."""
    return sum(getattr(cell, name).nbytes for name in cell.plane_names)


@pytest.mark.parametrize("name", FORMATS)
def test_empty_cells_cost_no_pixel_bytes_and_read_back_bit_for_bit(tmp_path, name):
    full = make_patch(MEDIUM, seed=3, n_noise=3, psf_size=15)
    indices = list(full.cells)
    empty = tuple(indices[: len(indices) // 2])
    half = make_patch(MEDIUM, seed=3, n_noise=3, psf_size=15, empty=empty)
    sizes = {}
    for label, patch in (("full", full), ("half", half)):
        path = tmp_path / f"{label}-{name}"
        api.write(patch, path, compression="lossless" if name.endswith(".fz") else None)
        back = api.read(path)
        assert back.equals(patch)  # NaN planes and NO_DATA masks bit for bit
        for index in empty if label == "half" else ():
            cell = back.cells[index]
            assert cell.is_empty and np.isnan(cell.variance).all()
            assert (cell.mask == patch.metadata.mask_bits.value("NO_DATA")).all()
        sizes[label] = path.stat().st_size
    saved = sizes["full"] - sizes["half"]
    pixels = sum(_pixel_bytes(half.cells[i]) for i in empty)
    if name.endswith(".fz"):  # compressed: random planes shrink a little, NaN planes a lot
        assert saved > 0.5 * pixels
    else:  # what the empty cells' pixels took (and their WCS cards, now left out)
        assert 0.95 * pixels < saved < 1.1 * pixels, (saved, pixels)


#: A cell of the MEDIUM patches.
CELL = next(iter(make_patch(MEDIUM).cells))


def test_an_empty_cell_with_other_fill_values_is_stored_as_it_is(tmp_path):
    """A foreign empty cell whose planes are not NaN/NO_DATA keeps its pixels."""
    patch = make_patch(MEDIUM, seed=5, empty=(CELL,))
    cell = patch.cells[CELL]
    cell.variance[...] = 0.0  # not the fill of an empty cell
    for name in ("p.fits", "p.h5"):
        api.write(patch, tmp_path / name)
        back = api.read(tmp_path / name).cells[CELL]
        assert (back.variance == 0.0).all() and np.isnan(back.image).all()


def test_a_plane_marked_empty_in_a_cell_with_data_is_refused(tmp_path):
    patch = make_patch(MEDIUM, seed=6, empty=(CELL,))
    path = tmp_path / "p.h5"
    api.write(patch, path)
    used = next(i for i, c in patch.cells.items() if not c.is_empty)
    with h5py.File(path, "r+") as h5:
        marked = h5[f"cells/{hdf5_format.group_name(CELL)}/image"]
        group = h5[f"cells/{hdf5_format.group_name(used)}"]
        del group["image"]
        h5.copy(marked, group, "image")  # the empty cell's marker in a cell with data
    with pytest.raises(CellCoaddFormatError, match="marked empty in a cell with data"):
        api.read(path)


@pytest.mark.parametrize("name", ["p.fits", "p.h5"])
def test_files_storing_empty_cells_pixels_still_read(tmp_path, name, monkeypatch):
    """As written before format 1.6: every plane of every cell with its pixels."""
    cells = list(make_patch(MEDIUM).cells)
    patch = make_patch(MEDIUM, seed=7, empty=(cells[0], cells[5]), psf_phase=True)

    def per_input_only(cell: CellCoadd, no_data: int) -> frozenset[str]:
        return frozenset(n for n in real(cell, no_data) if plane(n).per_input)

    real = fits_format.planes_without_pixels
    monkeypatch.setattr(fits_format, "planes_without_pixels", per_input_only)
    monkeypatch.setattr(hdf5_format, "planes_without_pixels", per_input_only)
    api.write(patch, tmp_path / name)
    monkeypatch.undo()
    bigger = (tmp_path / name).stat().st_size
    api.write(patch, tmp_path / f"new-{name}")
    assert (tmp_path / f"new-{name}").stat().st_size < bigger
    assert api.read(tmp_path / name).equals(patch)
