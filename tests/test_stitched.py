"""The stitched patch's PSF at any position and the CELL_EDGE plane (as Rubin's
``StitchedPsf`` and ``set_cell_edges`` serve them)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from coadd_factory import make_patch

from cellcoadd.errors import CellCoaddIndexError, CellCoaddValueError, InvalidCoaddError
from cellcoadd.model.stitched import cell_edge_mask, cell_of_position, psf_at


@pytest.fixture(scope="module")
def patch():
    return make_patch(seed=9, empty=((2, 3),), missing=((3, 2),))


def test_the_psf_of_the_cell_holding_the_position(patch):
    meta = patch.metadata
    side = meta.cell_inner
    for index, cell in patch.items():
        if cell.is_empty:
            continue
        box = cell.inner_bbox
        # every corner of the inner box (pixel edges included) and its centre
        for x, y in [
            (box.x_start - 0.5, box.y_start - 0.5),
            (box.x_stop - 0.5 - 1e-9, box.y_stop - 0.5 - 1e-9),
            (box.x_start + side / 2, box.y_start + side / 2),
        ]:
            assert cell_of_position(patch, x, y) == index
            stamp = psf_at(patch, x, y)
            assert np.array_equal(stamp, cell.psf) and stamp is not cell.psf


def test_the_outer_border_is_served_by_the_outermost_cells(patch):
    outer = patch.metadata.geometry.outer_bbox
    corner = (outer.x_start, outer.y_start)  # in the border of the first border cell
    first = min(patch.metadata.all_cell_indices, key=lambda i: (i[1], i[0]))
    assert cell_of_position(patch, *corner) == first
    assert np.array_equal(psf_at(patch, *corner), patch[first].psf)
    with pytest.raises(CellCoaddIndexError, match="outside patch"):
        psf_at(patch, outer.x_start - 1, outer.y_start)


def test_no_psf_where_the_cell_is_missing_or_empty(patch):
    for index, what in (((2, 3), "empty"), ((3, 2), "missing")):
        box = patch.metadata.cell_boxes(index)[0]
        with pytest.raises(InvalidCoaddError, match=re.escape(f"its cell {index} is {what}")):
            psf_at(patch, box.x_start + 1, box.y_start + 1)


def test_cells_with_corner_psfs_interpolate(patch):
    corners = make_patch(seed=9, psf_corners=True)
    index = corners.metadata.inner_cell_indices[0]
    cell = corners[index]
    x = cell.outer_bbox.x_start + 4.25
    y = cell.outer_bbox.y_start + 5.5
    assert np.array_equal(psf_at(corners, x, y), cell.psf_at(4.25, 5.5))


def test_cell_edge_mask_flags_the_inner_box_edges(patch):
    edges = cell_edge_mask(patch)
    side = patch.metadata.cell_inner
    box = patch.patch_inner_bbox
    assert edges.shape == box.shape
    # each cell's inner box: its outermost ring of pixels, nothing inside
    cell = edges[:side, :side]
    assert cell[0].all() and cell[-1].all() and cell[:, 0].all() and cell[:, -1].all()
    assert not cell[1:-1, 1:-1].any()
    assert edges.sum() == (box.nx // side) * (box.ny // side) * (side * side - (side - 2) ** 2)
    for bad in (0, side, True):
        with pytest.raises(CellCoaddValueError):
            cell_edge_mask(patch, width=bad)
