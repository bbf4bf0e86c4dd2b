"""Rubin's ring sky map (``SkyMap.lsst``) against an independent re-derivation.

The reference values here are recomputed step by step from the published description of
LSST's ``RingsSkyMap`` (version 1) and its ``cells`` tract builder (docs/geometry.md):
scalar loops, textbook TAN formulas, astropy WCS objects built from scratch and the
spherical "offset" of a point along a bearing done with explicit vector rotations. None
of it calls cellcoadd's geometry code.
"""

import math
import pickle

import numpy as np
import pytest
from astropy.wcs import WCS
from click.testing import CliRunner

from cellcoadd.errors import CellCoaddIndexError, ConfigError
from cellcoadd.geometry import SkyMap, SkyMapConfig, sky_ids

N_RINGS = 120
RING = math.pi / (N_RINGS + 1)
OVERLAP = math.radians(1.0 / 60.0)
SCALE = math.radians(0.2 / 3600.0)  # rad/pixel
PATCH = 20 * 150
CELL = 150


# -- the published algorithm, re-derived plainly -------------------------------------------
def ref_ring_counts() -> list[int]:
    counts = []
    for i in range(N_RINGS):
        lo = -math.pi / 2 + RING * (i + 0.5)
        hi = lo + RING
        counts.append(int(2 * math.pi * math.cos(min(abs(lo), abs(hi))) / RING) + 1)
    return counts


COUNTS = ref_ring_counts()
N_TRACTS = sum(COUNTS) + 2


def ref_tract(ra_deg: float, dec_deg: float) -> int:
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    first = RING * 0.5 - math.pi / 2
    if dec < first:
        return 0
    if dec > -first:
        return N_TRACTS - 1
    ring = int((dec - first) / RING)
    if ring >= N_RINGS:
        return N_TRACTS - 1
    index = int((ra % (2 * math.pi)) / (2 * math.pi / COUNTS[ring]) + 0.5)
    if index == COUNTS[ring]:
        index = 0
    return 1 + sum(COUNTS[:ring]) + index


def ref_ring_index(tract: int) -> tuple[int, int]:
    if tract == 0:
        return -1, 0
    if tract == N_TRACTS - 1:
        return N_RINGS, 0
    ring, index = 0, tract - 1
    while index >= COUNTS[ring]:
        index -= COUNTS[ring]
        ring += 1
    return ring, index


def ref_center(tract: int) -> tuple[float, float]:
    ring, index = ref_ring_index(tract)
    if ring == -1:
        return 0.0, -90.0
    if ring == N_RINGS:
        return 0.0, 90.0
    ra = (2 * math.pi * index / COUNTS[ring]) % (2 * math.pi)
    return math.degrees(ra), math.degrees(RING * (ring + 1) - math.pi / 2)


def _vec(ra: float, dec: float) -> np.ndarray:
    return np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])


def ref_offset(ra_deg: float, dec_deg: float, bearing: float, amount: float) -> tuple:
    """Move ``amount`` rad along the great circle leaving at ``bearing`` (rad, 0 = East,
    pi/2 = North); at a pole "East" is the direction of RA + 90 deg."""
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    r = _vec(ra, dec)
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.cross(r, east)
    direction = math.cos(bearing) * east + math.sin(bearing) * north
    p = math.cos(amount) * r + math.sin(amount) * direction
    return math.degrees(math.atan2(p[1], p[0])) % 360.0, math.degrees(math.asin(p[2]))


def ref_wcs(center: tuple[float, float], crpix0: float) -> WCS:
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(center)
    wcs.wcs.crpix = [crpix0 + 1.0, crpix0 + 1.0]
    deg = math.degrees(SCALE)
    wcs.wcs.cd = [[-deg, 0.0], [0.0, deg]]
    wcs.wcs.set()
    return wcs


def ref_tract_wcs(tract: int) -> tuple[WCS, int]:
    """Final tract WCS and side: box of the four offset points, every pixel it touches,
    grown to whole patches about its centre, shifted to start at 0."""
    center = ref_center(tract)
    start = ref_wcs(center, 0.0)
    pts = [ref_offset(*center, k * math.pi / 2, RING / 2 + OVERLAP) for k in range(4)]
    x, y = start.all_world2pix([p[0] for p in pts], [p[1] for p in pts], 0)
    lows, sides = [], []
    for values in (x, y):
        low = math.ceil(min(values) - 0.5)
        side = math.floor(max(values) + 0.5) - low + 1
        n = -(-side // PATCH)
        lows.append(low - (n * PATCH - side) // 2)
        sides.append(n * PATCH)
    assert lows[0] == lows[1] and sides[0] == sides[1]
    return ref_wcs(center, -lows[0]), sides[0]


def ref_tan_pixel(ra, dec, center, crpix0):
    """Textbook gnomonic projection, 0-based pixels."""
    a, d = np.radians(ra), np.radians(dec)
    a0, d0 = np.radians(center[0]), np.radians(center[1])
    cos_c = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(a - a0)
    xi = np.cos(d) * np.sin(a - a0) / cos_c
    eta = (np.cos(d0) * np.sin(d) - np.sin(d0) * np.cos(d) * np.cos(a - a0)) / cos_c
    if center[1] == 90.0:  # FITS default LONPOLE = 0 when the tangent point is the pole
        xi, eta = -xi, -eta
    return crpix0 - xi / SCALE, crpix0 + eta / SCALE


@pytest.fixture(scope="module")
def lsst():
    return SkyMap.named("lsst_cells_v1")


# -- tests ---------------------------------------------------------------------------------
def test_counts_ids_and_centres_match_the_published_layout(lsst):
    assert len(lsst) == N_TRACTS == 18_938
    assert COUNTS[59] == COUNTS[60] == 243  # the two rings touching the equator
    for tract in [0, 1, 2, 9, 10, 11, 9_467, 9_468, 9_469, 18_936, N_TRACTS - 1]:
        assert lsst[tract].center == pytest.approx(ref_center(tract), abs=1e-12)
    assert lsst[0].center == (0.0, -90.0) and lsst[N_TRACTS - 1].center == (0.0, 90.0)
    assert lsst.config.name == "lsst_cells_v1"
    assert (lsst.config.patches_per_tract, lsst.config.tract_pixels) == (10, 30_000)


@pytest.mark.parametrize("tract", [0, 1, 500, 4_016, 5_063, 9_468, 9_469, 15_000, 18_937])
def test_tract_box_and_wcs_match_the_published_algorithm(lsst, tract):
    wcs, side = ref_tract_wcs(tract)
    ours = lsst[tract]
    assert ours.bbox.nx == ours.bbox.ny == side == 30_000
    np.testing.assert_array_equal(ours.wcs.wcs.crpix, wcs.wcs.crpix)  # 15000: pixel 14999
    cd = ours.wcs.wcs.get_pc() * ours.wcs.wcs.cdelt
    np.testing.assert_allclose(cd, wcs.wcs.cd, rtol=1e-13, atol=0)
    assert ours.wcs.wcs.lonpole == wcs.wcs.lonpole and ours.wcs.wcs.ctype[0] == "RA---TAN"
    # the tangent point itself is exact
    assert ours.center == ref_center(tract)
    rng = np.random.default_rng(tract)
    x, y = rng.uniform(-0.5, side - 0.5, (2, 2_000))
    ra, dec = wcs.all_pix2world(x, y, 0)
    fx, fy = ours.sky_to_pixel(ra, dec)  # the exact tangent point: ~1e-9 px
    assert max(np.max(np.abs(fx - x)), np.max(np.abs(fy - y))) < 3e-9
    # The astropy WCS object, as a worker process receives it: its parameters are exact
    # (the tangent point bit for bit; the CD matrix to 1 ulp, 0.2 / 3600 against
    # degrees(radians(0.2 / 3600))), so it puts every position where the independent
    # WCS does to ~1e-11 px. (Round trips through RA in degrees alone differ from the
    # start by up to ~2e-9 px, for either WCS.)
    received = pickle.loads(pickle.dumps(ours.wcs))
    np.testing.assert_array_equal(received.wcs.crval, wcs.wcs.crval)
    np.testing.assert_allclose(received.wcs.get_pc() * received.wcs.cdelt, wcs.wcs.cd, rtol=3e-16)
    wx, wy = received.all_world2pix(ra, dec, 0)
    rx, ry = wcs.all_world2pix(ra, dec, 0)
    assert max(np.max(np.abs(wx - rx)), np.max(np.abs(wy - ry))) <= 1e-9
    # and the same sky position for each pixel, to the rounding of RA and Dec in degrees
    # (measured <= 1.04e-9 px; one unit in the last place of RA ~ 360 deg is 1.02e-9 px)
    wra, wdec = received.all_pix2world(x, y, 0)
    offset = np.hypot((wra - ra) * np.cos(np.radians(dec)), wdec - dec) * 3600.0 / 0.2
    assert np.max(offset) <= 1.5e-9


def test_ten_thousand_positions_poles_and_ra_wrap(lsst):
    rng = np.random.default_rng(27)
    n = 10_000
    ra = rng.uniform(0.0, 360.0, n)
    dec = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    # poles, cap edges, the RA wrap and tract RA boundaries of a few rings
    first = math.degrees(RING * 0.5 - math.pi / 2)
    extra_ra = [0.0, 123.0, 359.0, 0.0, 250.0, 0.0, 0.0, 359.999999, 1e-9, 359.99999999]
    extra_dec = [90.0, 90.0, 90.0, -90.0, -90.0, first, -first, 10.0, -45.0, 0.0]
    for ring in (0, 30, 59, 60, 119):
        half = 180.0 / COUNTS[ring]
        d = math.degrees(RING * (ring + 1) - math.pi / 2)
        for k in (1, COUNTS[ring] - 1):
            extra_ra += [(2 * k - 1) * half - 1e-7, (2 * k - 1) * half + 1e-7]
            extra_dec += [d, d]
    ra, dec = np.concatenate([ra, extra_ra]), np.concatenate([dec, extra_dec])

    loc = lsst.locate(ra, dec)
    expected_tract = np.array([ref_tract(r, d) for r, d in zip(ra, dec, strict=True)])
    np.testing.assert_array_equal(loc["tract"] >= 0, True)
    np.testing.assert_array_equal(loc["tract"], expected_tract)
    assert loc["tract"][n] == loc["tract"][n + 1] == N_TRACTS - 1  # north pole, any RA
    assert loc["tract"][n + 3] == 0
    assert loc["tract"][n + 7] == ref_tract(0.0, 10.0)  # RA 359.999999 wraps to the RA-0 tract

    # pixel, patch and cell of every position, with the textbook projection
    x, y = np.empty_like(ra), np.empty_like(ra)
    for tract in np.unique(expected_tract):
        sel = expected_tract == tract
        x[sel], y[sel] = ref_tan_pixel(ra[sel], dec[sel], ref_center(int(tract)), 14_999.0)
    px, py = np.floor(x + 0.5).astype(int), np.floor(y + 0.5).astype(int)
    assert np.all((px >= 0) & (px < 30_000) & (py >= 0) & (py < 30_000))
    np.testing.assert_allclose(loc["x"], x, atol=1e-6)
    np.testing.assert_allclose(loc["y"], y, atol=1e-6)
    np.testing.assert_array_equal(loc["patch_x"], px // PATCH)
    np.testing.assert_array_equal(loc["patch_y"], py // PATCH)
    np.testing.assert_array_equal(loc["cell_x"], px // CELL)
    np.testing.assert_array_equal(loc["cell_y"], py // CELL)
    # Rubin's ids: the butler's sequential patch, and the cell counted from the first cell
    # of the patch's cell grid, whose box starts one cell below the patch's inner box
    np.testing.assert_array_equal(loc["patch_id"], (py // PATCH) * 10 + px // PATCH)
    np.testing.assert_array_equal(loc["rubin_cell_x"], (px - (px // PATCH * PATCH - CELL)) // CELL)
    np.testing.assert_array_equal(loc["rubin_cell_y"], (py - (py // PATCH * PATCH - CELL)) // CELL)


def test_known_dp1_tracts(lsst):
    # Data Preview 1 fields and the lsst_cells_v1 tracts Rubin processed them in
    fields = {(53.16, -28.10): 5063, (37.86, 6.98): 10463, (6.02, -72.08): 453}
    loc = lsst.locate([k[0] for k in fields], [k[1] for k in fields])
    assert list(loc["tract"]) == list(fields.values())


def test_json_round_trip_and_names(lsst):
    again = SkyMap.from_json(lsst.to_json())
    assert again.spec == lsst.spec and len(again) == len(lsst)
    assert SkyMap.named("lsst").config == lsst.config
    assert SkyMap.named("lsst_cells_v2").config.cell_border == 0
    with pytest.raises(ConfigError, match="unknown sky map name 'hsc'.*lsst_cells_v1"):
        SkyMap.named("hsc")


def test_dc2_cells_v1_is_lsst_cells_v1_under_its_own_name(lsst):
    dc2 = SkyMap.named("DC2_cells_v1")
    assert dc2.config.name == "DC2_cells_v1"
    assert dc2.config.model_copy(update={"name": "lsst_cells_v1"}) == lsst.config
    assert dc2[5063].center == lsst[5063].center


def test_rubin_patch_and_cell_ids(lsst):
    tract = lsst[5063]
    for patch in tract.patches:
        assert lsst.patch_from_rubin_id(5063, patch.rubin_id) == patch
    assert tract.patch(4, 3).rubin_id == 34 and tract.patch(9, 9).rubin_id == 99
    for bad in (-1, 100):
        with pytest.raises(CellCoaddIndexError, match=f"patch id {bad} is outside tract 5063"):
            tract.patch_from_rubin_id(bad)
    patch = tract.patch(4, 3)
    first, last = patch.cell_indices[0], patch.cell_indices[-1]
    assert patch.rubin_cell_index(first) == (0, 0) and patch.rubin_cell_index(last) == (21, 21)
    for index in patch.cell_indices:
        assert patch.cell_from_rubin_index(patch.rubin_cell_index(index)) == index
    for index in patch.inner_cell_indices:  # a cell's own patch: 1 to 20
        cell = tract.cell(*index)
        assert cell.owner_patch == (4, 3)
        assert cell.rubin_index == patch.rubin_cell_index(index)
        assert all(1 <= i <= 20 for i in cell.rubin_index)
    # a border cell has another index in the neighbour that lists it
    border = tract.cell(*first)
    assert border.owner_patch == (3, 2) and border.rubin_index == (20, 20)
    with pytest.raises(CellCoaddIndexError, match=r"Rubin cell index \(22, 0\) is not a cell"):
        patch.cell_from_rubin_index((22, 0))
    with pytest.raises(CellCoaddIndexError, match=r"cell \(0, 0\) is not a cell of patch"):
        patch.rubin_cell_index((0, 0))


def test_catalogue_columns_carry_both_ids(lsst):
    ra, dec = lsst[5063].pixel_to_sky([12345.0, 15100.0], [10000.0, 17999.0])
    ids = sky_ids({"ra": ra, "dec": dec}, lsst)
    assert list(ids["tract"]) == [5063, 5063]
    assert list(ids["patch"]) == [3 * 10 + 4, 5 * 10 + 5]
    assert (ids["cell_x"][0], ids["cell_y"][0]) == (12345 // 150, 10000 // 150)
    # cell 82 of the tract is cell 82 - (4 * 20 - 1) = 3 of patch 4
    assert (ids["rubin_cell_x"][0], ids["rubin_cell_y"][0]) == (3, 66 - 59)
    assert (ids["rubin_cell_x"][1], ids["rubin_cell_y"][1]) == (1, 20)


def test_inconsistent_explicit_tract_size_is_refused():
    with pytest.raises(ConfigError, match="patches_per_tract=8 disagrees.*=10"):
        SkyMap.lsst(SkyMapConfig(patches_per_tract=8))


def test_rings_is_a_different_tessellation(lsst):
    ours = SkyMap.rings()
    assert len(ours) == 18_936 != len(lsst)
    assert ours[0].wcs.wcs.crpix[0] == 15_000.5 and lsst[0].wcs.wcs.crpix[0] == 15_000.0


def test_cli_locate_accepts_the_name(lsst):
    from cellcoadd.cli.main import cli as main

    result = CliRunner().invoke(main, ["locate", "53.16", "-28.1", "--skymap", "lsst", "--json"])
    assert result.exit_code == 0, result.output
    assert '"tract": 5063' in result.output
    where = lsst.locate([53.16], [-28.1])[0]
    assert f'"patch_id": {where["patch_id"]}' in result.output
    text = CliRunner().invoke(main, ["locate", "53.16", "-28.1", "--skymap", "DC2_cells_v1"])
    assert text.exit_code == 0, text.output
    rubin = (where["patch_id"], where["rubin_cell_x"], where["rubin_cell_y"])
    assert "Rubin: patch {}, cell ({}, {})".format(*rubin) in text.output
    summary = CliRunner().invoke(main, ["skymap", "--lsst"])
    assert summary.exit_code == 0, summary.output
    assert "18938 tract(s)" in summary.output and "lsst_cells_v1" in summary.output
