"""Catalog trimming: every object kept by exactly one cell, in every container type."""

import numpy as np
import pytest
from astropy.table import Table

from cellcoadd.geometry import SkyMap, SkyMapConfig, flag_unique, trim_to_cell, trim_to_patch

CONFIG = SkyMapConfig(cell_inner=50, cell_border=10, cells_per_patch=4, patches_per_tract=3)


@pytest.fixture(scope="module")
def skymap():
    return SkyMap.from_centers([(150.0, 2.0)], CONFIG)


def _catalog_over_patch(skymap, n=4000, seed=1):
    tract = skymap[0]
    patch = tract.patch(1, 1)
    box = patch.outer_bbox
    rng = np.random.default_rng(seed)
    x = rng.uniform(box.x_start - 0.5, box.x_stop - 0.5, n)
    y = rng.uniform(box.y_start - 0.5, box.y_stop - 0.5, n)
    # exact cell boundaries too: they must be kept once
    edges = np.arange(box.x_start, box.x_stop, CONFIG.cell_inner) - 0.5
    x = np.concatenate([x, edges, edges])
    y = np.concatenate([y, edges, edges[::-1]])
    ra, dec = tract.pixel_to_sky(x, y)
    return patch, {"id": np.arange(ra.size), "ra": ra, "dec": dec}


@pytest.mark.parametrize("kind", ["dict", "table", "structured"])
def test_trimming_cell_by_cell_keeps_every_object_once(skymap, kind):
    patch, cat = _catalog_over_patch(skymap)
    if kind == "table":
        cat = Table(cat)
    elif kind == "structured":
        cat = Table(cat).as_array()
    in_patch = trim_to_patch(cat, skymap, 0, patch.index)
    kept = []
    for cell in patch.cells:  # border cells too: they keep nothing of this patch's objects
        rows = trim_to_cell(in_patch, skymap, cell)
        kept.extend(np.asarray(rows["id"]).tolist())
    assert sorted(kept) == sorted(np.asarray(in_patch["id"]).tolist())
    assert len(kept) == len(set(kept)) > 0


def test_flags_are_nested_and_cover_the_patch(skymap):
    patch, cat = _catalog_over_patch(skymap)
    tract = skymap[0]
    counts = np.zeros(cat["ra"].size, dtype=int)
    for cell in patch.cells:
        flags = flag_unique(cat, skymap, tract=0, patch=patch.index, cell=cell.index)
        assert not (flags["is_cell_inner"] & ~flags["is_tract_inner"]).any()
        counts += flags["is_primary"]
    x, y = tract.sky_to_pixel(cat["ra"], cat["dec"])
    # the patch's cells (border cells included) own the patch inner box grown by the border
    owned_area = patch.inner_bbox.grow(CONFIG.patch_border_cells * CONFIG.cell_inner)
    np.testing.assert_array_equal(counts, owned_area.contains(x, y).astype(int))


def test_missing_column_is_a_clear_error(skymap):
    with pytest.raises(KeyError, match="no column 'ra'"):
        flag_unique({"dec": np.zeros(2)}, skymap, tract=0)
