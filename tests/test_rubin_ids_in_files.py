"""Rubin's ids stored in our own files (format 1.6, informative): the patch id in the FITS
primary header and the HDF5 root, each cell's patch-local index in the FITS cell index
and its HDF5 group; equal to the geometry's."""

from __future__ import annotations

import fitsio
import h5py
from coadd_factory import MEDIUM, make_patch

from cellcoadd.io import api
from cellcoadd.io.coadd.hdf5_format import group_name


def test_rubin_ids_are_stored_in_both_layouts(tmp_path):
    patch = make_patch(MEDIUM, seed=2, patch=(2, 1))
    geometry = patch.metadata.geometry
    assert geometry.rubin_id == 1 * MEDIUM.patches_per_tract + 2
    expected = {index: geometry.rubin_cell_index(index) for index in patch.cells}
    api.write(patch, tmp_path / "p.fits")
    with fitsio.FITS(str(tmp_path / "p.fits")) as fits:
        assert fits[0].read_header()["PATCHID"] == geometry.rubin_id
        rows = fits["CELLINDEX"].read()
    stored = {(int(r["CELL_X"]), int(r["CELL_Y"])): (r["RUBIN_X"], r["RUBIN_Y"]) for r in rows}
    assert stored == expected and min(expected.values()) == (0, 0)
    api.write(patch, tmp_path / "p.h5")
    with h5py.File(tmp_path / "p.h5", "r") as h5:
        assert h5.attrs["patch_id"] == geometry.rubin_id
        for index, rubin in expected.items():
            assert tuple(h5["cells"][group_name(index)].attrs["rubin_cell_index"]) == rubin
    assert api.read(tmp_path / "p.h5").equals(api.read(tmp_path / "p.fits"))
