"""A patch written while it is built (stream_patch + write_cells): the same bytes as a
whole build written at once, a bounded number of cells held, and nothing left behind when
a cell fails or comes out of order."""

from __future__ import annotations

import gc
import hashlib
import os
import weakref
from pathlib import Path

import numpy as np
import pytest
from coadd_factory import TINY_BUILD, tiny_exposures, tiny_patch

import cellcoadd.builder.patch as patch_module
from cellcoadd import CellBuildError, build_patch
from cellcoadd.builder import stream_patch
from cellcoadd.errors import InvalidCoaddError
from cellcoadd.io import api
from cellcoadd.io.coadd import fits_format, hdf5_format
from cellcoadd.model.build_config import BuildConfig

NAMES = ("patch.fits", "patch.fits.fz", "patch.h5")


@pytest.fixture(scope="module")
def tiny():
    patch = tiny_patch()
    good = tiny_exposures(patch, 2)
    return patch, good, build_patch(patch, good, TINY_BUILD, seed=1, progress=False)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("workers", [1, 2])
def test_streamed_files_are_byte_identical_to_whole_writes(tmp_path, tiny, workers):
    patch, good, serial = tiny
    for name in NAMES:
        api.write(serial, tmp_path / f"whole-{name}")
        with stream_patch(patch, good, TINY_BUILD, 1, progress=False, workers=workers) as stream:
            api.write_cells(stream.metadata, stream, tmp_path / f"streamed-{name}")
        assert _sha256(tmp_path / f"whole-{name}") == _sha256(tmp_path / f"streamed-{name}"), name
        assert api.read(tmp_path / f"streamed-{name}").metadata == serial.metadata


def test_blocks_list_the_cells_in_file_order(tiny, monkeypatch):
    patch, _, _ = tiny
    for limit in (1, 3, 64):
        monkeypatch.setattr(patch_module, "MAX_BLOCK_CELLS", limit)
        for tasks in (1, 2, 5):
            blocks = patch_module.blocks_of(patch.cells, tasks)
            assert all(0 < len(block) <= limit for block in blocks)
            flat = [cell.index for block in blocks for cell in block]
            assert flat == sorted(cell.index for cell in patch.cells)


@pytest.mark.parametrize("workers", [1, 2, "dask"])
def test_a_streamed_write_holds_a_few_blocks_not_the_patch(
    tmp_path, tiny, monkeypatch, request, workers
):
    """Cells of one column per block: with the window of blocks (a pool's, or a dask
    cluster's of 2 workers), the cells alive here while the file is written, handed on or
    still to come, stay below that window's, far below the patch's count; so do their
    pixels (the arrays received from a worker, which anything holding a worker's result,
    e.g. its future, would keep after the cell itself is gone)."""
    patch, good, _ = tiny
    monkeypatch.setattr(patch_module, "MAX_BLOCK_CELLS", 1)  # one cell per block
    monkeypatch.setattr(fits_format, "_BATCH", 2)  # cells the writers take together
    monkeypatch.setattr(hdf5_format, "_BATCH", 2)
    where = (
        {"scheduler": request.getfixturevalue("dask_client")}
        if workers == "dask"
        else {"workers": workers}
    )
    # every cell made here (from a worker's result, or built here), from its making on
    alive: dict[str, list[weakref.ref]] = {"cells": [], "images": []}
    most = dict.fromkeys(alive, 0)
    unparcel = patch_module._unparcel

    def recorded(cell, built):
        coadd = unparcel(cell, built)
        alive["cells"].append(weakref.ref(coadd))
        alive["images"].append(weakref.ref(_first_array(coadd.image)))
        return coadd

    monkeypatch.setattr(patch_module, "_unparcel", recorded)

    def watched(stream):
        for cell in stream:
            gc.collect()
            for what, refs in alive.items():
                most[what] = max(most[what], sum(ref() is not None for ref in refs))
            yield cell
            del cell

    n_cells = len(patch.cells)
    for name in ("patch.fits", "patch.h5"):
        for refs in alive.values():
            refs.clear()
        most.update(dict.fromkeys(most, 0))
        with stream_patch(patch, good, TINY_BUILD, 1, progress=False, **where) as stream:
            api.write_cells(stream.metadata, watched(stream), tmp_path / name)
        # the window of blocks, the writers' own batches (HDF5: 3 of them), the cell being
        # handed on and the block being built
        n_workers = 2 if workers == "dask" else workers
        bound = patch_module.WINDOW_PER_WORKER * n_workers + 3 * 2 + 2
        assert max(most.values()) <= bound < n_cells, (name, most, n_cells)
        assert len(api.read(tmp_path / name)) == n_cells


def _first_array(array: np.ndarray) -> np.ndarray:
    """The array whose memory ``array`` views (itself if it owns it): a cell's plane may be
    a view of the array received from a worker (unpickled arrays have their own dtype
    instance, which ``np.asarray(..., dtype)`` answers with a view)."""
    while isinstance(array.base, np.ndarray):
        array = array.base
    return array


def test_cells_out_of_order_or_missing_leave_no_file(tmp_path, tiny):
    _, _, serial = tiny
    cells = list(serial.cells.values())
    for name in NAMES:
        with pytest.raises(InvalidCoaddError, match="came where"):
            api.write_cells(serial.metadata, [cells[1], cells[0], *cells[2:]], tmp_path / name)
        with pytest.raises(InvalidCoaddError, match="is missing"):
            api.write_cells(serial.metadata, cells[:-1], tmp_path / name)
    assert os.listdir(tmp_path) == []


def test_a_failing_cell_in_a_streamed_build_names_it_and_leaves_no_file(tmp_path, tiny):
    patch, good, _ = tiny
    config = BuildConfig(n_noise=1, psf_size=35)  # larger than the 32-pixel cells
    with (
        pytest.raises(CellBuildError, match=r"cell \(-?\d+, -?\d+\) of tract 0 failed"),
        stream_patch(patch, good, config, 1, progress=False, workers=2) as stream,
    ):
        api.write_cells(stream.metadata, stream, tmp_path / "patch.h5")
    assert os.listdir(tmp_path) == []


def test_streamed_corner_psfs_are_byte_identical_and_every_cell_must_hold_them(tmp_path, tiny):
    """With corner PSFs the streamed file is the whole write's; a cell without them in a
    patch built with them (or the reverse) is refused, and nothing is left."""
    import copy

    patch, good, plain = tiny
    config = TINY_BUILD.model_copy(update={"psf_corners": True})
    whole = build_patch(patch, good, config, seed=1, progress=False)
    assert whole.metadata.cell_plane_names[-1] == "psf_corners"
    for name in NAMES:
        api.write(whole, tmp_path / f"whole-{name}")
        with stream_patch(patch, good, config, 1, progress=False, workers=1) as stream:
            api.write_cells(stream.metadata, stream, tmp_path / f"streamed-{name}")
        assert _sha256(tmp_path / f"whole-{name}") == _sha256(tmp_path / f"streamed-{name}"), name
        cells = list(whole.cells.values())
        bare = copy.copy(cells[1])
        bare.psf_corners = None
        with pytest.raises(InvalidCoaddError, match="same planes"):
            api.write_cells(whole.metadata, [cells[0], bare, *cells[2:]], tmp_path / name)
        with pytest.raises(InvalidCoaddError, match="same planes"):
            # a cell with corners among a patch built without them
            mixed = [cells[0], *list(plain.cells.values())[1:]]
            api.write_cells(plain.metadata, mixed, tmp_path / name)
        assert not (tmp_path / name).exists()
