"""Self-describing cells: a cell read alone, or taken from a patch, carries its patch's
common components (unit, zero point, band, mask-bit names, tract, patch, sky map) and
converts to astropy without being told its unit."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from coadd_factory import make_cell, make_metadata, make_patch

from cellcoadd.errors import InvalidCoaddError
from cellcoadd.geometry import SkyMapConfig
from cellcoadd.io import api
from cellcoadd.model.cell_common import CellCommon
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata


def _counts_patch() -> PatchCoadd:
    patch = make_patch(seed=9, band="i", patch=(0, 1))
    meta = patch.metadata.model_dump()
    meta["units"], meta["zero_point"] = "count", 30.0
    meta["build_config"].update(units="count", zero_point=30.0)
    meta["skymap_config"]["name"] = "my_rings"
    return PatchCoadd(PatchMetadata.model_validate(meta), patch.cells)


@pytest.mark.parametrize("suffix", [".fits", ".fits.fz", ".h5", "cell_coadds"])
def test_a_cell_read_alone_describes_itself(tmp_path, suffix):
    patch = _counts_patch()
    index = next(i for i, c in patch.items() if not c.is_empty)
    if suffix == "cell_coadds":
        path = api.write(patch, tmp_path / "lsst.fits", layout="cell_coadds")
    else:
        path = api.write(patch, tmp_path / f"patch{suffix}")
    cell = api.read_cell(path, index)
    common = cell.common
    assert common == patch.metadata.cell_common
    assert (common.units, common.zero_point, common.band) == ("count", 30.0, "i")
    assert (common.tract, common.patch, common.skymap) == (7, (0, 1), "my_rings")
    assert common.mask_bits == patch.metadata.mask_bits
    nd = cell.to_nddata()  # no argument needed
    assert nd.unit == u.ct and nd.uncertainty.unit == u.ct**2
    assert nd.meta["MAGZERO"] == 30.0 and nd.meta["FILTER"] == "i"
    assert (nd.meta["PATCH_X"], nd.meta["PATCH_Y"], nd.meta["SKYMAP"]) == (0, 1, "my_rings")
    assert (nd.meta["CELL_X"], nd.meta["CELL_Y"], nd.meta["TRACT"]) == (*index, 7)
    assert nd.meta["MP_SAT"] == patch.metadata.mask_bits.value("SAT").bit_length() - 1
    assert np.array_equal(nd.data, cell.image, equal_nan=True)


def test_a_cell_taken_from_a_patch_describes_itself_and_the_original_is_untouched():
    meta = make_metadata(SkyMapConfig(cell_inner=10, cell_border=4, cells_per_patch=2))
    rng = np.random.default_rng(3)
    loose = {index: make_cell(meta, index, rng) for index in meta.all_cell_indices}
    patch = PatchCoadd(meta, loose)
    index = next(iter(loose))
    assert patch[index].common == meta.cell_common and patch[index].equals(loose[index])
    assert loose[index].common is None  # the cell given is not changed
    assert patch[index].image is loose[index].image  # a shallow copy: arrays shared
    nd = patch[index].to_nddata(inner=True)
    assert nd.unit == u.nJy and "MAGZERO" not in nd.meta
    assert nd.data.shape == patch[index].inner_bbox.shape
    # the same cells in a patch of another unit describe that patch there
    other = PatchMetadata.model_validate(
        {**meta.model_dump(), "units": "count", "zero_point": 27.0}
        | {"build_config": {**meta.build_config.model_dump(), "units": "count", "zero_point": 27.0}}
    )
    again = PatchCoadd(other, patch.cells)
    assert again[index].common.units == "count" and patch[index].common.units == "nJy"


def test_a_loose_cell_needs_its_unit():
    meta = make_metadata()
    cell = make_cell(meta, meta.inner_cell_indices[0], np.random.default_rng(1))
    with pytest.raises(InvalidCoaddError, match=r"no unit of its own.*pass unit="):
        cell.to_nddata()
    assert cell.to_nddata("nJy").unit == u.nJy


def test_common_components_must_match_the_tract():
    meta = make_metadata()
    cell = make_cell(meta, meta.inner_cell_indices[0], np.random.default_rng(1))
    wrong = CellCommon(units="nJy", zero_point=31.4, band="r", tract=8, patch=(1, 1))
    with pytest.raises(InvalidCoaddError, match="tract 7, its common components say 8"):
        cell.attach(wrong)
