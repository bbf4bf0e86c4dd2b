"""Geometry: exact tiling, unique ownership, WCS consistency, invalid configurations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from cellcoadd.geometry import Box, SkyMap, SkyMapConfig

SMALL = SkyMapConfig(
    pixel_scale=0.2,
    cell_inner=150,
    cell_border=50,
    cells_per_patch=4,
    patches_per_tract=3,
    n_rings=200,  # tracts of 0.1 deg need narrow rings
)


@pytest.fixture(scope="module")
def rings_default():
    return SkyMap.rings()


@pytest.fixture(scope="module")
def field_map():
    centers = [(10.0, -30.0), (10.1, -30.0), (10.05, -29.9)]
    return SkyMap.from_centers(centers, SMALL)


# -- Box ---------------------------------------------------------------------------------
def test_box_conventions():
    box = Box(x_start=2, x_stop=5, y_start=-1, y_stop=3)
    assert box.shape == (4, 3)
    assert box.slices == (slice(-1, 3), slice(2, 5))
    assert box.contains(1.5, -1.5) and not box.contains(1.49, 0)
    assert box.contains(4.49, 2.49) and not box.contains(4.5, 0) and not box.contains(3, 2.5)
    assert box.grow(2) == Box(x_start=0, x_stop=7, y_start=-3, y_stop=5)
    assert box.shifted(1, -1) == Box(x_start=3, x_stop=6, y_start=-2, y_stop=2)
    assert box.intersection(Box(x_start=4, x_stop=9, y_start=0, y_stop=1)) == Box(
        x_start=4, x_stop=5, y_start=0, y_stop=1
    )
    assert box.intersection(Box(x_start=10, x_stop=12, y_start=0, y_stop=1)).is_empty
    with pytest.raises(ValidationError):
        box.x_start = 0  # frozen
    with pytest.raises(ValidationError, match="must not precede"):
        Box(x_start=3, x_stop=2, y_start=0, y_stop=1)


@given(st.integers(-50, 50), st.integers(1, 30), st.floats(-100, 100, allow_nan=False))
def test_box_contains_matches_pixel_membership(start, size, x):
    box = Box(x_start=start, x_stop=start + size, y_start=0, y_stop=1)
    pixel = int(np.floor(x + 0.5))  # the pixel whose span [i - 0.5, i + 0.5) holds x
    assert box.contains(x, 0.0) == (start <= pixel < start + size)


# -- configuration -----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cell_inner": 0}, "greater than 0"),
        ({"pixel_scale": -0.2}, "greater than 0"),
        ({"cell_border": 200}, "must not exceed cell_inner"),
        ({"cells_per_patch": 2, "patch_border_cells": 3}, "must not exceed cells_per_patch"),
        ({"cell_border": -1}, "greater than or equal to 0"),
        ({"unknown": 1}, "Extra inputs"),
    ],
)
def test_invalid_configurations_are_refused(kwargs, message):
    with pytest.raises(ValidationError, match=message):
        SkyMapConfig(**kwargs)


def test_rings_refuse_tracts_smaller_than_rings():
    with pytest.raises(ValueError, match="increase n_rings"):
        SkyMap.rings(SkyMapConfig(patches_per_tract=2, n_rings=120))


# -- hierarchy ---------------------------------------------------------------------------
def test_integer_multiples_and_cell_boxes(rings_default):
    tract = rings_default[100]
    cfg = tract.config
    assert tract.bbox.nx == cfg.patches_per_tract * cfg.cells_per_patch * cfg.cell_inner
    patch = tract.patch(3, 7)
    assert patch.inner_bbox.nx == cfg.cells_per_patch * cfg.cell_inner
    inner_cells = patch.inner_cells
    assert len(inner_cells) == cfg.cells_per_patch**2
    assert len(patch.cells) == (cfg.cells_per_patch + 2 * cfg.patch_border_cells) ** 2
    # inner boxes of inner cells tile the patch inner box: areas add up and none overlap
    assert sum(c.inner_bbox.nx * c.inner_bbox.ny for c in inner_cells) == (
        patch.inner_bbox.nx * patch.inner_bbox.ny
    )
    assert all(patch.inner_bbox.contains_box(c.inner_bbox) for c in inner_cells)
    for cell in patch.cells:
        assert cell.outer_bbox == cell.inner_bbox.grow(cfg.cell_border)
        assert patch.outer_bbox.contains_box(cell.outer_bbox)
        assert cell.outer_bbox.shape == (cfg.cell_outer, cfg.cell_outer)


def test_neighbouring_cells_overlap_by_twice_the_border(rings_default):
    tract = rings_default[0]
    cfg = tract.config
    a, right, up = tract.cell(5, 5), tract.cell(6, 5), tract.cell(5, 6)
    assert a.outer_bbox.intersection(right.outer_bbox).nx == 2 * cfg.cell_border
    assert a.outer_bbox.intersection(up.outer_bbox).ny == 2 * cfg.cell_border
    assert a.inner_bbox.intersection(right.inner_bbox).is_empty


def test_patch_border_cells_are_neighbour_inner_cells(rings_default):
    tract = rings_default[5000]
    patch, right = tract.patch(4, 4), tract.patch(5, 4)
    border = [c for c in patch.cells if not patch.is_inner_cell(c.index)]
    right_inner = {c.index: c for c in right.inner_cells}
    shared = [c for c in border if c.index in right_inner]
    assert len(shared) == tract.config.cells_per_patch
    for cell in shared:
        twin = right_inner[cell.index]
        assert cell == twin and cell.outer_bbox == twin.outer_bbox


def test_cell_wcs_is_tract_wcs_shifted(rings_default):
    tract = rings_default[777]
    cell = tract.cell(37, 121)
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 260, 50)
    y = rng.uniform(-10, 260, 50)
    ra_c, dec_c = cell.wcs.wcs_pix2world(x, y, 0)
    x_t, y_t = tract.sky_to_pixel(ra_c, dec_c)
    np.testing.assert_allclose(x_t - cell.outer_bbox.x_start, x, atol=1e-9)
    np.testing.assert_allclose(y_t - cell.outer_bbox.y_start, y, atol=1e-9)
    # the centre pixel of the outer array is the cell centre
    ra, dec = cell.wcs.wcs_pix2world([125], [125], 0)
    assert np.allclose((ra[0], dec[0]), cell.center_sky, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0, 360, exclude_max=True, allow_nan=False),
    st.floats(-90, 90, allow_nan=False),
)
def test_sky_pixel_sky_round_trip(rings_default, ra, dec):
    tract = rings_default[int(rings_default.find_tract(ra, dec)[0])]
    x, y = tract.sky_to_pixel(ra, dec)
    ra2, dec2 = tract.pixel_to_sky(x, y)
    assert abs(dec2[0] - dec) < 1e-9
    if abs(dec) < 89.9999:
        dra = (ra2[0] - ra + 180.0) % 360.0 - 180.0
        assert abs(dra * np.cos(np.radians(dec))) < 1e-9


# -- unique ownership --------------------------------------------------------------------
def _owners(skymap, ra, dec):
    return [t.id for t in skymap if t.contains_inner(ra, dec)[0]]


positions = st.one_of(
    st.tuples(st.floats(0, 360, exclude_max=True), st.floats(-90, 90)),
    st.tuples(st.sampled_from([0.0, 359.9999999, 1e-12, 180.0]), st.floats(-90, 90)),
    st.tuples(st.floats(0, 360, exclude_max=True), st.sampled_from([90.0, -90.0, 89.99, -89.9])),
)


@settings(max_examples=40, deadline=None)
@given(positions)
def test_every_position_has_exactly_one_tract_patch_and_cell(rings_default, pos):
    ra, dec = pos
    skymap = rings_default
    loc = skymap.locate([ra], [dec])[0]
    tract_id = int(skymap.find_tract(ra, dec)[0])
    # only tracts near the position can own it; check them all, plus the found one
    near = [t for t in _nearby_tracts(skymap, ra, dec)]
    owners = [t.id for t in near if t.contains_inner(ra, dec)[0]]
    assert owners == [tract_id] == [loc["tract"]]
    tract = skymap[tract_id]
    x, y = tract.sky_to_pixel(ra, dec)
    patches = [p for p in tract.patches if p.contains_inner(x, y)[0]]
    assert [p.index for p in patches] == [(loc["patch_x"], loc["patch_y"])]
    patch = patches[0]
    cells = [c for c in patch.cells if c.contains_inner(x, y)[0]]
    assert [c.index for c in cells] == [(loc["cell_x"], loc["cell_y"])]
    assert patch.is_inner_cell(cells[0].index)


def _nearby_tracts(skymap, ra, dec):
    """Tracts whose centres are within 4 deg (a superset of possible owners)."""
    from cellcoadd.geometry.regions import unit_vectors

    target = unit_vectors(np.array([ra]), np.array([dec]))[0]
    centers = np.array([t.center for t in skymap])
    cosd = unit_vectors(centers[:, 0], centers[:, 1]) @ target
    return [skymap[int(i)] for i in np.nonzero(cosd > np.cos(np.radians(4.0)))[0]]


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_exact_cell_and_patch_boundaries_belong_to_one_cell(field_map, data):
    tract = field_map[0]
    cfg = tract.config
    n_cells = cfg.cells_per_tract
    cx = data.draw(st.integers(1, n_cells - 1))
    cy = data.draw(st.integers(1, n_cells - 1))
    # the exact boundary between cells: x = cx * inner - 0.5
    x = np.array([cx * cfg.cell_inner - 0.5])
    y = np.array([cy * cfg.cell_inner - 0.5])
    owners = [
        c.index
        for c in (tract.cell(i, j) for i in range(cx - 1, cx + 1) for j in range(cy - 1, cy + 1))
        if c.contains_inner(x, y)[0]
    ]
    assert owners == [(cx, cy)]
    assert tuple(int(v[0]) for v in tract.cell_of_pixel(x, y)) == (cx, cy)


def test_explicit_centres_share_the_sky_without_overlap(field_map):
    rng = np.random.default_rng(3)
    ra = rng.uniform(9.9, 10.2, 20000)
    dec = rng.uniform(-30.1, -29.8, 20000)
    owned = np.array([t.contains_inner(ra, dec) for t in field_map])
    assert owned.sum(axis=0).max() == 1
    loc = field_map.locate(ra, dec)
    has_owner = owned.any(axis=0)
    assert np.array_equal(loc["tract"] >= 0, has_owner)
    np.testing.assert_array_equal(np.argmax(owned, axis=0)[has_owner], loc["tract"][has_owner])


def test_rings_cover_the_sky_and_wrap_in_ra(rings_default):
    rng = np.random.default_rng(11)
    ra = np.concatenate([rng.uniform(0, 360, 20000), [0.0, 360.0 - 1e-9, 360.0, 720.5, -0.5]])
    dec = np.concatenate([np.degrees(np.arcsin(rng.uniform(-1, 1, 20000))), [0, 0, 0, 10, 10]])
    loc = rings_default.locate(ra, dec)
    assert (loc["tract"] >= 0).all()
    # 360 is the same place as 0, 720.5 as 0.5, -0.5 as 359.5
    assert loc["tract"][-3] == loc["tract"][-5]
    assert loc["tract"][-2] == rings_default.locate([0.5], [10.0])["tract"][0]
    assert loc["tract"][-1] == rings_default.locate([359.5], [10.0])["tract"][0]
    poles = rings_default.locate([0.0, 123.0, 0.0, 250.0], [90.0, 90.0, -90.0, -90.0])
    assert poles["tract"][0] == poles["tract"][1] == len(rings_default) - 1
    assert poles["tract"][2] == poles["tract"][3] == 0


def test_skymap_json_round_trip(field_map, rings_default):
    again = SkyMap.from_json(field_map.to_json())
    assert again.spec == field_map.spec
    assert [t.center for t in again] == [t.center for t in field_map]
    assert len(SkyMap.from_json(rings_default.to_json())) == len(rings_default)


@pytest.mark.parametrize("center", [(60.0, -30.0), (10.123456789, 45.987654321), (359.9, -89.0)])
@pytest.mark.parametrize("cell_inner", [150, 151])
def test_cell_wcs_is_canonical_without_a_round_trip(center, cell_inner):
    """A cell's WCS is the tract's shifted by whole pixels, without the (slow) pickle round
    trip; it must be what a worker process receives, bit for bit."""
    import pickle

    config = SkyMapConfig(
        pixel_scale=0.2,
        cell_inner=cell_inner,
        cell_border=50,
        cells_per_patch=3,
        patches_per_tract=3,
    )
    tract = SkyMap.from_centers([center], config)[0]
    points = np.array([[0.0, 0.0], [1.3, 7.7], [200.2, 150.1]])
    for index in [(-1, -1), (0, 0), (4, 7), (8, 2)]:
        wcs = tract.cell(*index).wcs
        received = pickle.loads(pickle.dumps(wcs))
        for name in ("crpix", "crval", "cdelt"):
            assert np.array_equal(getattr(wcs.wcs, name), getattr(received.wcs, name)), name
        assert np.array_equal(wcs.wcs.get_pc(), received.wcs.get_pc())
        assert np.array_equal(wcs.all_pix2world(points, 0), received.all_pix2world(points, 0))
