"""The LSST ``lsst.cell_coadds`` FITS layout: exact round trips through our writer, files
written by hand exactly as the LSST writer lays them out, files without our extension
HDUs, the CLI, and errors that name the file and the HDU."""

from __future__ import annotations

import math

import fitsio
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS
from click.testing import CliRunner
from coadd_factory import (
    SMALL,
    TINY_BUILD,
    assert_same,
    make_metadata,
    make_patch,
    tiny_exposures,
    tiny_patch,
)

from cellcoadd.builder.patch import build_patch
from cellcoadd.cli.storage import convert_command, info_command, patch_summary
from cellcoadd.errors import CellCoaddFormatError, ConfigError
from cellcoadd.geometry import SkyMap
from cellcoadd.io import api
from cellcoadd.io.foreign.cell_coadds_layout import is_cell_coadds_file
from cellcoadd.io.foreign.cell_coadds_reader import CellCoaddsFile
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata
from cellcoadd.model.units import NJY_ZERO_POINT

LSST_HDUS = ["", "", "CELL", "VISIT", "MASKDEF", "VISIT_SUMMARY", "APCORR"]


@pytest.fixture(scope="module")
def patch() -> PatchCoadd:
    return make_patch(seed=3, empty=((1, 2), (4, 4)), missing=((3, 3),))


def _lsst_part(source, target) -> None:
    """Copy the LSST HDUs only (what the LSST writer makes), with astropy like LSST does."""
    with fits.open(source) as hdus:
        kept = fits.HDUList([hdu.copy() for hdu in hdus[: len(LSST_HDUS)]])
        kept[0].header.remove("CCNHDU")  # our HDU count (an LSST writer does not state it)
        kept.writeto(target, checksum=True)


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize(
    ("n_noise", "psf_size", "band", "index"),
    [(2, 5, "r", (1, 1)), (0, 3, "y\u00b2", (0, 0)), (3, 7, 'a"b\\c', (2, 0))],
)
def test_round_trip_is_exact(tmp_path, n_noise, psf_size, band, index):
    original = make_patch(
        seed=11,
        n_noise=n_noise,
        psf_size=psf_size,
        band=band,
        patch=index,
        empty=((index[0] * 2, index[1] * 2 + 1),),
        missing=((index[0] * 2 + 1, index[1] * 2),),
    )
    path = api.write(original, tmp_path / "cells.fits", layout="cell_coadds")
    assert is_cell_coadds_file(str(path))
    read = api.read(path)
    assert_same(read, original)
    assert read.equals(original)
    with api.open(path) as lazy:
        assert lazy.format_name == "cell_coadds"
        key = next(iter(original))
        assert lazy.read_cell(key).equals(original[key])


def test_round_trip_of_a_build_and_conversions(tmp_path):
    built = build_patch(tiny_patch(), tiny_exposures(tiny_patch(), 2), TINY_BUILD, progress=False)
    lsst = api.write(built, tmp_path / "lsst.fits", layout="cell_coadds")
    assert api.read(lsst).equals(built)
    h5 = api.convert(lsst, tmp_path / "ours.h5")
    back = api.convert(h5, tmp_path / "again.fits", layout="cell_coadds")
    assert api.read(back).equals(built)
    assert lsst.read_bytes() == back.read_bytes()  # reproducible files


def test_empty_cells_are_absent_from_the_grid(tmp_path, patch):
    path = api.write(patch, tmp_path / "cells.fits", layout="cell_coadds")
    with fitsio.FITS(str(path)) as hdus:
        assert [hdu.get_extname() for hdu in hdus][: len(LSST_HDUS)] == LSST_HDUS
        ids = {tuple(int(v) for v in row) for row in hdus[1].read_column("cell_id")}
        used = hdus["CELL"].read()
    grid = {(cx - 1, cy - 1) for cx, cy in patch}  # patch (1, 1): grid cell 0 is cell (1, 1)
    empty = {(cx - 1, cy - 1) for cx, cy in patch.empty_cell_indices}
    assert empty and ids == grid - empty
    n_used = sum(cell.n_used for cell in patch.values())
    assert len(used) == n_used and used["overlaps_center"].all()


def test_mask_planes_carry_rubin_names(tmp_path, patch):
    """MASKDEF lists afw's names (our EDGE, an input detector's edge, is SENSOR_EDGE)."""
    path = api.write(patch, tmp_path / "cells.fits", layout="cell_coadds")
    with fitsio.FITS(str(path)) as hdus:
        table = hdus["MASKDEF"].read()
    pairs = zip(table["MASK_NAME"], table["BIT_VALUE"], strict=True)
    names = {str(name).strip(): int(bit) for name, bit in pairs}
    ours = patch.metadata.mask_bits.bits
    assert names["SENSOR_EDGE"] == ours["EDGE"] and "EDGE" not in names
    assert {k: names[k] for k in ("SAT", "CR", "INTRP", "BAD", "NO_DATA")} == {
        k: ours[k] for k in ("SAT", "CR", "INTRP", "BAD", "NO_DATA")
    }
    lsst = tmp_path / "lsst.fits"
    _lsst_part(path, lsst)
    assert api.read(lsst).metadata.mask_bits == patch.metadata.mask_bits  # and back


def test_rubin_plane_names_both_ways():
    from cellcoadd.io.foreign.mask_planes import from_rubin, to_rubin

    ours = {"EDGE": 4, "SAT": 1, "NO_DATA": 8, "DETECTED": 5, "UNMASKEDNAN": 9}
    afw = {"SENSOR_EDGE": 4, "SAT": 1, "NO_DATA": 8, "DETECTED": 5, "UNMASKEDNAN": 9}
    assert to_rubin(ours, "afw") == afw and from_rubin(afw, "afw") == ours
    images = to_rubin(ours, "lsst_images")
    assert images == {
        "SENSOR_EDGE": 4,
        "SATURATED": 1,
        "NO_DATA": 8,
        "DETECTED": 5,
        "UNMASKED_NAN": 9,
    }
    assert from_rubin(images, "lsst_images") == ours
    # a Rubin coadd's EDGE (the detection edge, beside its SENSOR_EDGE): lsst-images'
    # DETECTION_EDGE, and back; alone, lsst-images' DETECTION_EDGE is never our EDGE
    rubin = {"EDGE": 4, "SENSOR_EDGE": 6, "NO_DATA": 8}
    assert to_rubin(rubin, "lsst_images") == {"DETECTION_EDGE": 4, "SENSOR_EDGE": 6, "NO_DATA": 8}
    assert from_rubin(to_rubin(rubin, "lsst_images"), "lsst_images") == rubin
    assert from_rubin({"DETECTION_EDGE": 4, "NO_DATA": 8}, "lsst_images") == {
        "DETECTION_EDGE": 4,
        "NO_DATA": 8,
    }
    # kept from lsst-images, written for afw under afw's name
    assert to_rubin({"DETECTION_EDGE": 4, "EDGE": 6, "NO_DATA": 8}, "afw") == {
        "EDGE": 4,
        "SENSOR_EDGE": 6,
        "NO_DATA": 8,
    }


def test_an_empty_cell_that_is_not_canonical_keeps_a_row(tmp_path):
    original = make_patch(seed=5, empty=((1, 1),))
    cell = original[1, 1]
    meta = original.metadata
    odd = CellCoadd(
        image=cell.image,
        mask=cell.mask | meta.mask_bits.value("BAD"),
        variance=np.zeros_like(cell.variance),
        noise=cell.noise,
        mfrac=cell.mfrac,
        psf=cell.psf,
        inputs=cell.inputs,
        tract=cell.tract,
        index=cell.index,
        inner_bbox=cell.inner_bbox,
        outer_bbox=cell.outer_bbox,
        wcs=cell.wcs,
    )
    patched = PatchCoadd(meta, {**original.cells, (1, 1): odd})
    path = api.write(patched, tmp_path / "cells.fits", layout="cell_coadds")
    assert api.read(path).equals(patched)


def test_without_our_extension(tmp_path, patch):
    """An LSST reader sees only the LSST HDUs; so does ours when they are all there is."""
    ours = api.write(patch, tmp_path / "ours.fits", layout="cell_coadds")
    lsst = tmp_path / "lsst.fits"
    _lsst_part(ours, lsst)
    read = api.read(lsst)
    meta, orig = read.metadata, patch.metadata
    assert meta.skymap_config == orig.skymap_config
    assert (meta.tract, meta.patch, meta.band, meta.units) == (7, (1, 1), "r", "nJy")
    assert meta.tract_center == orig.tract_center and meta.mask_bits == orig.mask_bits
    assert (meta.n_noise, meta.psf_size) == (orig.n_noise, orig.psf_size)
    assert set(read) == set(patch) - set(patch.empty_cell_indices)
    for index, cell in read.items():
        expected = patch[index]
        for plane in ("image", "mask", "variance", "noise", "mfrac", "psf"):
            assert getattr(cell, plane).tobytes() == getattr(expected, plane).tobytes()
        assert (cell.inner_bbox, cell.outer_bbox) == (expected.inner_bbox, expected.outer_bbox)
        corners = [[0, 0], [13, 13]]
        assert np.allclose(
            cell.wcs.wcs_pix2world(corners, 0), expected.wcs.wcs_pix2world(corners, 0), atol=1e-11
        )
        used = [r for r in expected.inputs if r.is_used]
        assert [(r.visit, r.detector, r.weight) for r in cell.inputs] == [
            (r.visit, r.detector, r.weight) for r in used
        ]
        for got, want in zip(cell.inputs, used, strict=True):
            assert got.overlap_fraction == want.overlap_fraction and got.status == "used"
            for name in ("psf_e1", "psf_e2", "psf_T"):
                assert math.isclose(getattr(got, name), getattr(want, name), abs_tol=1e-12)


# ------------------------------------------------------------------------------ by hand
#
# Files laid out exactly as lsst.cell_coadds' writeMultipleCellCoaddAsFits (file VERSION
# 0.8) lays them out, written here with astropy as it does: an empty primary HDU holding
# the tract WCS (afw SkyWcs.getFitsMetadata(): CD matrix, ICRS); an unnamed binary table
# with one row per cell (cell_id 2I; image, mask, variance, psf, maskfrac, noise_NN with
# TDIM) and the grid and identity keywords; CELL, VISIT, MASKDEF, VISIT_SUMMARY and APCORR
# tables; checksums. The geometry is lsst_cells_v1's: 150 + 2 x 50 px cells, a 22 x 22
# grid per patch, 3000-px patches of 30000-px tracts with the tangent point on pixel 14999.

CELL_INNER, BORDER, PSF, NOISE = 150, 50, 11, 2
OUTER = CELL_INNER + 2 * BORDER
GRID, PATCH, TRACT = 22, (3, 4), 5063  # ECDFS in Data Preview 1
GRMIN = ((PATCH[0] * 20 - 1) * CELL_INNER, (PATCH[1] * 20 - 1) * CELL_INNER)
LSST_MASK = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5, "NO_DATA": 8}
#: grid-local cell ids written, in an order of our choice (the LSST writer keeps insertion)
CELL_IDS = [(2, 1), (0, 0), (21, 21), (1, 2)]
VISITS = [(2024112300230, "r_03", 20241123), (2024112400094, "r_03", 20241124)]
#: APCORR columns in the order written (Rubin's writer takes them from a set: any order)
APCORR_NAMES = ("base_GaussianFlux_instFlux", "base_PsfFlux_instFlux", "ext_gaap_0p7")
APCORR_VALUES = {
    (2, 1): (0.985, 1.0125, 0.97),
    (0, 0): (0.99, 1.0, math.nan),
    (1, 2): (0.975, 1.03125, 0.96),
}


def _lsst_tract_centre(tract: int) -> tuple[float, float]:
    """Tract centre of lsst_cells_v1, straight from the ring layout (120 rings)."""
    ring_size = math.pi / 121
    index = tract - 1
    for ring in range(120):
        start = ring_size * (ring + 0.5) - math.pi / 2
        edge = min(abs(start), abs(start + ring_size))
        count = int(2 * math.pi * math.cos(edge) / ring_size) + 1
        if index < count:
            ra = 2 * math.pi * index / count
            return math.degrees(ra), math.degrees(ring_size * (ring + 1) - math.pi / 2)
        index -= count
    raise AssertionError("tract beyond the rings")


def _tract_wcs_cards(crpix: float = 15000.0, tract: int = TRACT) -> dict:
    """What afw's SkyWcs.getFitsMetadata() gives for an lsst_cells_v1 tract WCS."""
    scale = 0.2 / 3600
    ra, dec = _lsst_tract_centre(tract)
    return {
        "RADESYS": "ICRS",
        "EQUINOX": 2000.0,
        "CTYPE1": "RA---TAN",
        "CTYPE2": "DEC--TAN",
        "CUNIT1": "deg",
        "CUNIT2": "deg",
        "CRPIX1": crpix,
        "CRPIX2": crpix,
        "CRVAL1": ra,
        "CRVAL2": dec,
        "CD1_1": -scale,
        "CD1_2": 0.0,
        "CD2_1": 0.0,
        "CD2_2": scale,
    }


def _write_by_hand(
    path,
    *,
    version="0.8",
    units="nJy",
    mask_value=None,
    skip=(),
    extra=None,
    wcs=None,
    skymap="lsst_cells_v1",
) -> dict:
    """An lsst.cell_coadds file written with astropy, column by column as its writer does."""
    rng = np.random.default_rng(4)
    rows = []
    for cell_id in CELL_IDS:
        planes = {
            name: rng.standard_normal((OUTER, OUTER)).astype(np.float32)
            for name in ("image", "variance", "maskfrac", *(f"noise_{n:02}" for n in range(NOISE)))
        }
        planes["mask"] = rng.choice([0, 1, 2, 4, 8, 32, 256, 33], size=(OUTER, OUTER)).astype(
            np.int32
        )
        psf = rng.uniform(size=(PSF, PSF))
        planes["psf"] = psf / psf.sum()
        rows.append((cell_id, planes))
    if mask_value is not None:
        rows[0][1]["mask"][0, 0] = mask_value

    def column(name, fmt, unit=None):
        arrays = [planes[name] for _, planes in rows]
        shape = arrays[0].shape
        return fits.Column(
            name=name,
            format=f"{arrays[0].size}{fmt}",
            dim=f"({shape[1]}, {shape[0]})",
            unit=unit,
            array=arrays,
        )

    columns = [fits.Column(name="cell_id", format="2I", array=[c for c, _ in rows])]
    columns += [column("image", "E", units), column("mask", "J"), column("variance", "E")]
    columns += [column("psf", "D"), column("maskfrac", "E")]
    columns += [column(f"noise_{n:02}", "E") for n in range(NOISE)]
    table = fits.BinTableHDU.from_columns(fits.ColDefs(columns))
    header = {
        "GRCELL1": CELL_INNER,
        "GRCELL2": CELL_INNER,
        "GRSHAPE1": GRID,
        "GRSHAPE2": GRID,
        "GRMIN1": GRMIN[0],
        "GRMIN2": GRMIN[1],
        "OCELL1": OUTER,
        "OCELL2": OUTER,
        "PSFSIZE1": PSF,
        "PSFSIZE2": PSF,
        # MultipleCellCoadd.inner_bbox: the grid box with its edge cells' borders
        "INBBOX11": GRMIN[0] - BORDER,
        "INBBOX12": GRMIN[1] - BORDER,
        "INBBOX21": GRMIN[0] + GRID * CELL_INNER - 1 + BORDER,
        "INBBOX22": GRMIN[1] + GRID * CELL_INNER - 1 + BORDER,
        "VERSION": version,
        "TUNIT2": units,
        "TUNIT4": f"{units}**2",
        "INSTRUME": "LSSTComCam",
        "FILTER": "r",
        "SKYMAP": skymap,
        "TRACT": TRACT,
        "PATCH_X": PATCH[0],
        "PATCH_Y": PATCH[1],
        "NNOISE": NOISE,
        **(extra or {}),
    }
    table.header.extend(list(header.items()))
    # CELL: (cell_x, cell_y, visit, detector, overlaps_center, overlap_fraction, weight,
    # psf_shape_ixx, psf_shape_iyy, psf_shape_ixy, psf_shape_flag), Python values as LSST's
    v1, v2 = VISITS[0][0], VISITS[1][0]
    links = [
        (2, 1, v1, 4, True, 1.0, 0.5, 3.0, 2.0, 0.25, False),
        (2, 1, v2, 5, True, 1.0, 0.25, 2.5, 2.5, 0.0, False),
        (0, 0, v1, 3, True, 1.0, 0.75, 0.0, 0.0, 0.0, True),
        (21, 21, v2, 5, True, 0.875, 1.5, 2.0, 2.0, -0.5, False),
        (1, 2, v2, 4, True, 1.0, 2.0, 2.25, 2.75, 0.5, False),
    ]
    names = "cell_x cell_y visit detector overlaps_center overlap_fraction weight".split()
    names += ["psf_shape_ixx", "psf_shape_iyy", "psf_shape_ixy", "psf_shape_flag"]
    cell = np.rec.fromrecords(links, names=names)
    visit = np.rec.fromrecords(VISITS, names=("visit", "physical_filter", "day_obs"))
    maskdef = Table(names=("MASK_NAME", "BIT_VALUE"), dtype=(str, np.uint32))
    for name, bit in LSST_MASK.items():
        maskdef.add_row((name, bit))
    keys = sorted({(v, d) for _, _, v, d, *_ in links})
    days = dict((v, d) for v, _, d in VISITS)
    vertices = [np.zeros((8, 2), dtype=np.float32) for _ in keys]
    summary = fits.BinTableHDU.from_columns(
        [
            fits.Column(name="visit", format="K", array=[v for v, _ in keys]),
            fits.Column(name="detector", format="I", array=[d for _, d in keys]),
            fits.Column(name="physical_filter", format="32A", array=["r_03" for _ in keys]),
            fits.Column(name="day_obs", format="K", array=[days[v] for v, _ in keys]),
            fits.Column(name="num_vertices", format="I", array=[5 for _ in keys]),
            fits.Column(name="polygon_vertices", format="16E", dim="(2,8)", array=vertices),
        ],
        name="VISIT_SUMMARY",
    )
    summary.header["POLYVERT"] = 8
    # APCORR: x, y and one float column per algorithm, a row per cell with a map (here
    # not the cell (21, 21)); a cell without a value for an algorithm holds NaN
    apcorr = np.rec.fromrecords(
        [(i, j, *APCORR_VALUES[i, j]) for i, j in CELL_IDS if (i, j) in APCORR_VALUES],
        dtype=[("x", int), ("y", int), *((name, float) for name in APCORR_NAMES)],
    )
    primary = fits.PrimaryHDU()
    primary.header.extend(list((wcs or _tract_wcs_cards()).items()))
    hdus = [primary, table]
    for hdu in (
        fits.BinTableHDU.from_columns(cell, name="CELL"),
        fits.BinTableHDU.from_columns(visit, name="VISIT"),
        fits.BinTableHDU.from_columns(maskdef.as_array(), name="MASKDEF"),
        summary,
        fits.BinTableHDU.from_columns(apcorr, name="APCORR"),
    ):
        if hdu.name not in skip:
            hdus.append(hdu)
    fits.HDUList(hdus).writeto(path, checksum=True, overwrite=True)
    return {"rows": rows, "links": links}


def test_a_file_written_by_hand_reads_correctly(tmp_path):
    path = tmp_path / "lsst.fits"
    written = _write_by_hand(path)
    assert is_cell_coadds_file(str(path))
    read = api.read(path)
    meta = read.metadata
    lsst = SkyMap.named("lsst_cells_v1")
    assert (meta.tract, meta.patch, meta.band) == (TRACT, PATCH, "r")
    assert (meta.units, meta.zero_point) == ("nJy", NJY_ZERO_POINT)
    # the geometry is the declared sky map's: 10 x 10 patches, tangent point on 14999
    assert meta.skymap_config == lsst.config and meta.skymap_config.name == "lsst_cells_v1"
    assert meta.tract_center == lsst[TRACT].center
    assert meta.mask_bits.bits == LSST_MASK
    assert (meta.n_noise, meta.psf_size) == (NOISE, PSF)
    assert meta.observations is not None and meta.observations.instrument == "LSSTComCam"
    assert [(v.visit, v.physical_filter, v.day_obs) for v in meta.observations.visits] == VISITS
    first = (PATCH[0] * 20 - 1, PATCH[1] * 20 - 1)  # tract-global index of grid cell (0, 0)
    expected_ids = sorted(((first[0] + i, first[1] + j) for i, j in CELL_IDS), key=lambda k: k)
    assert sorted(read) == expected_ids
    tract = WCS(fits.Header(_tract_wcs_cards()))
    # the stored geometry is the file's own WCS (to FITS precision), tract pixel for pixel
    corners = [[0, 0], [29999, 0], [29999, 29999], [GRMIN[0], GRMIN[1]]]
    ours = meta.geometry.tract.wcs
    assert (
        np.abs(ours.wcs_world2pix(tract.wcs_pix2world(corners, 0), 0) - np.array(corners)).max()
        < 1e-6
    )
    for (i, j), planes in written["rows"]:
        cell = read[first[0] + i, first[1] + j]
        assert cell.inner_bbox.x_start == GRMIN[0] + i * CELL_INNER
        assert cell.inner_bbox.y_start == GRMIN[1] + j * CELL_INNER
        assert cell.outer_bbox.x_start == cell.inner_bbox.x_start - BORDER
        assert cell.shape == (OUTER, OUTER)
        # array pixel (x, y) of a cell is tract pixel outer start + (x, y)
        x0, y0 = cell.outer_bbox.x_start, cell.outer_bbox.y_start
        sky = cell.wcs.wcs_pix2world([[3, 5], [120, 77]], 0)
        assert np.allclose(sky, tract.wcs_pix2world([[x0 + 3, y0 + 5], [x0 + 120, y0 + 77]], 0))
        # our sky map puts the cell centre in this very cell
        ((ra, dec),) = cell.wcs.wcs_pix2world([[OUTER // 2, OUTER // 2]], 0)
        where = lsst.locate([ra], [dec])[0]
        assert (where["tract"], where["cell_x"], where["cell_y"]) == (TRACT, *cell.index)
        owner = (cell.index[0] // 20, cell.index[1] // 20)  # border cells: a neighbour's
        assert (where["patch_x"], where["patch_y"]) == owner
        for name in ("image", "variance"):
            assert np.array_equal(getattr(cell, name), planes[name])
        assert np.array_equal(cell.mfrac, planes["maskfrac"])
        assert np.array_equal(cell.mask, planes["mask"])
        assert np.array_equal(cell.psf, planes["psf"])
        for n in range(NOISE):
            assert np.array_equal(cell.noise[n], planes[f"noise_{n:02}"])
        links = [link for link in written["links"] if link[:2] == (i, j)]
        assert [(r.visit, r.detector, r.weight, r.overlap_fraction) for r in cell.inputs] == [
            (v, d, w, f) for _, _, v, d, _, f, w, *_ in links
        ]
        assert all(r.status == "used" and r.band == "r" for r in cell.inputs)
        for record, (*_, ixx, iyy, ixy, flag) in zip(cell.inputs, links, strict=True):
            if flag:
                assert math.isnan(record.psf_T) and math.isnan(record.psf_e1)
                continue
            assert math.isclose(record.psf_e1, (ixx - iyy) / (ixx + iyy))
            assert math.isclose(record.psf_e2, 2 * ixy / (ixx + iyy))
            assert math.isclose(record.psf_T, (ixx + iyy) * 0.04)  # T = Ixx + Iyy, arcsec^2
    summary = patch_summary(str(path))
    assert summary["format"] == "cell_coadds" and summary["layout_version"] == "0.8"
    assert summary["inputs"]["used"] == len(written["links"])


def test_rubin_file_round_trip_keeps_its_identity(tmp_path):
    """Rubin -> cellcoadd -> Rubin: sky map, instrument, physical filter, day_obs, geometry."""
    source = tmp_path / "lsst.fits"
    _write_by_hand(source)
    again = api.write(api.read(source), tmp_path / "again.fits", layout="cell_coadds")
    lsst = tmp_path / "again_lsst_only.fits"
    _lsst_part(again, lsst)
    with fits.open(source) as a, fits.open(lsst) as b:
        for key in ("SKYMAP", "INSTRUME", "FILTER", "TRACT", "PATCH_X", "PATCH_Y", "TUNIT2"):
            assert a[1].header[key] == b[1].header[key], key
        boxes = ("INBBOX11", "INBBOX12", "INBBOX21", "INBBOX22")
        for key in ("GRMIN1", "GRMIN2", "GRSHAPE1", "GRCELL1", "OCELL1", *boxes):
            assert a[1].header[key] == b[1].header[key], key
        assert [h.name for h in b] == ["PRIMARY", "", *LSST_HDUS[2:]]
        visit_a, visit_b = a["VISIT"].data, b["VISIT"].data
        assert list(visit_b["visit"]) == list(visit_a["visit"])
        assert list(visit_b["physical_filter"]) == list(visit_a["physical_filter"])
        assert list(visit_b["day_obs"]) == list(visit_a["day_obs"])
        assert list(b["VISIT_SUMMARY"].data["day_obs"]) == list(a["VISIT_SUMMARY"].data["day_obs"])
        tract_a = WCS(a[0].header)
        tract_b = WCS(b[0].header)
        corners = [[0, 0], [29999, 29999], [14999, 14999]]
        assert np.allclose(
            tract_a.wcs_pix2world(corners, 0), tract_b.wcs_pix2world(corners, 0), rtol=0, atol=1e-10
        )
        # APCORR comes back as Rubin wrote it: every column, in order, every row and value
        assert _apcorr_of(b) == _apcorr_of(a)
    reread = api.read(lsst)
    assert reread.metadata.skymap_config.name == "lsst_cells_v1"
    assert reread.metadata.observations == api.read(source).metadata.observations


def _apcorr_of(hdus) -> tuple:
    """``APCORR`` of an open file: column names and FITS formats in order, and the rows
    (NaN as None, so that equal tables compare equal)."""
    table = hdus["APCORR"]
    columns = tuple((c.name, c.format) for c in table.columns)
    rows = tuple(
        tuple(None if isinstance(v, float) and math.isnan(v) else v for v in row.tolist())
        for row in np.asarray(table.data)
    )
    return columns, rows


def test_aperture_corrections_are_kept_through_every_format(tmp_path):
    source = tmp_path / "lsst.fits"
    _write_by_hand(source)
    read = api.read(source)
    corrections = read.metadata.aperture_corrections
    assert corrections is not None and corrections.algorithms == APCORR_NAMES
    first = (PATCH[0] * 20 - 1, PATCH[1] * 20 - 1)
    for (i, j), values in APCORR_VALUES.items():
        expected = {n: v for n, v in zip(APCORR_NAMES, values, strict=True) if not math.isnan(v)}
        assert corrections.of((first[0] + i, first[1] + j)) == expected
    assert corrections.of((first[0] + 21, first[1] + 21)) == {}  # no map: no row
    # our own formats keep them in the metadata, and give them back to the Rubin layout
    for name in ("ours.fits", "ours.h5"):
        ours = api.write(read, tmp_path / name)
        assert api.read(ours).metadata.aperture_corrections == corrections
        back = api.write(api.read(ours), tmp_path / f"back-{name}.fits", layout="cell_coadds")
        lsst = tmp_path / f"lsst-{name}.fits"
        _lsst_part(back, lsst)
        with fits.open(source) as a, fits.open(lsst) as b:
            assert _apcorr_of(b) == _apcorr_of(a)
            assert b["APCORR"].columns["x"].format == "K"  # int64 as Rubin's ("x", int)


def test_a_build_without_aperture_corrections_writes_empty_maps(tmp_path, patch):
    path = api.write(patch, tmp_path / "ours.fits", layout="cell_coadds")
    with fits.open(path) as hdus:
        assert [c.name for c in hdus["APCORR"].columns] == ["x", "y"]
        assert len(hdus["APCORR"].data) == len(hdus[1].data)
    assert api.read(path).metadata.aperture_corrections is None


def _rubin_stitch(path, plane: str = "image", bbox=None):
    """Stitch a cell_coadds file as lsst.cell_coadds' StitchedCoadd does (written here from
    its documented behaviour): the area is the grid box grown by the cell border (or
    ``bbox``, inclusive afw corners, which must lie inside it); each cell gives its inner
    box, and the cells on the grid's first and last rows and columns also give their outer
    border on that side. Returns the array and its lower-left tract pixel."""
    with fits.open(path) as hdus:
        header, data = hdus[1].header, hdus[1].data
        inner, outer = header["GRCELL1"], header["OCELL1"]
        pad, shape = (outer - inner) // 2, header["GRSHAPE1"]
        gx, gy = header["GRMIN1"], header["GRMIN2"]
        widest = (gx - pad, gy - pad, gx + shape * inner - 1 + pad, gy + shape * inner - 1 + pad)
        x0, y0, x1, y1 = widest if bbox is None else bbox
        assert widest[0] <= x0 <= x1 <= widest[2] and widest[1] <= y0 <= y1 <= widest[3]
        last_i = min((x1 - gx) // inner, shape - 1)
        last_j = min((y1 - gy) // inner, shape - 1)
        out = np.zeros((y1 - y0 + 1, x1 - x0 + 1), dtype=data[plane].dtype)
        for row in data:
            i, j = (int(v) for v in row["cell_id"])
            ox, oy = gx + i * inner - pad, gy + j * inner - pad  # outer box start
            lo_x = ox if i == 0 else ox + pad
            hi_x = ox + outer if i == last_i else ox + pad + inner
            lo_y = oy if j == 0 else oy + pad
            hi_y = oy + outer if j == last_j else oy + pad + inner
            lo_x, lo_y, hi_x, hi_y = (
                max(lo_x, x0),
                max(lo_y, y0),
                min(hi_x, x1 + 1),
                min(hi_y, y1 + 1),
            )
            if lo_x >= hi_x or lo_y >= hi_y:
                continue
            out[lo_y - y0 : hi_y - y0, lo_x - x0 : hi_x - x0] = row[plane][
                lo_y - oy : hi_y - oy, lo_x - ox : hi_x - ox
            ]
        return (
            out,
            (x0, y0),
            (header["INBBOX11"], header["INBBOX12"], header["INBBOX21"], header["INBBOX22"]),
        )


def test_rubin_stitches_our_file_to_rubins_size(tmp_path):
    full = make_patch(seed=5)  # every cell of the patch, border cells too
    path = api.write(full, tmp_path / "ours.fits", layout="cell_coadds")
    meta = full.metadata
    outer = meta.geometry.outer_bbox  # the patch's outer box: grid box + cell border
    with fits.open(path) as hdus:
        header = hdus[1].header
        inbbox = tuple(header[k] for k in ("INBBOX11", "INBBOX12", "INBBOX21", "INBBOX22"))
    assert inbbox == (outer.x_start, outer.y_start, outer.x_stop - 1, outer.y_stop - 1)
    default, start, _ = _rubin_stitch(path)
    by_inbbox, start_inbbox, _ = _rubin_stitch(path, bbox=inbbox)
    assert default.shape == by_inbbox.shape == outer.shape and start == start_inbbox
    # as Rubin's own files: the hand-written one's INBBOX is its grid box + border
    hand = tmp_path / "lsst.fits"
    _write_by_hand(hand)
    stitched, _, box = _rubin_stitch(hand, bbox=None)
    assert stitched.shape == (GRID * CELL_INNER + 2 * BORDER,) * 2
    assert box == (
        GRMIN[0] - BORDER,
        GRMIN[1] - BORDER,
        *(g + GRID * CELL_INNER - 1 + BORDER for g in GRMIN),
    )
    # the stitch holds each cell's inner box, and the edge cells' outer borders
    for cell in full.values():
        rows, cols = cell.inner_bbox.slices_in(outer)
        inner_rows, inner_cols = cell.inner_bbox.slices_in(cell.outer_bbox)
        assert np.array_equal(
            default[rows, cols], cell.image[inner_rows, inner_cols], equal_nan=True
        )
    corner = full[min(full, key=lambda index: (index[1], index[0]))]  # grid cell (0, 0)
    b = meta.cell_border
    assert np.array_equal(default[:b, :b], corner.image[:b, :b], equal_nan=True)
    # our own stitch of the patch inner box is the middle of Rubin's
    inner = meta.patch_inner_bbox
    rows, cols = inner.slices_in(outer)
    assert np.array_equal(default[rows, cols], full.stitch("image"), equal_nan=True)


def test_a_file_without_cells_is_refused(tmp_path):
    source, empty = tmp_path / "lsst.fits", tmp_path / "empty.fits"
    _write_by_hand(source)
    with fits.open(source) as hdus:
        hdus[1] = fits.BinTableHDU(hdus[1].data[:0], header=hdus[1].header)
        hdus.writeto(empty, checksum=True)
    with pytest.raises(CellCoaddFormatError, match=r"empty\.fits: HDU 1 .*cell table has no rows"):
        api.read(empty)


def test_named_sky_maps_and_aliases(tmp_path):
    path = tmp_path / "dc2.fits"
    _write_by_hand(path, skymap="DC2_cells_v1")  # DESC's name for lsst_cells_v1's geometry
    meta = api.read(path).metadata
    assert meta.skymap_config.name == "DC2_cells_v1"
    lsst = SkyMap.named("lsst_cells_v1").config
    assert meta.skymap_config == lsst.model_copy(update={"name": "DC2_cells_v1"})
    again = api.write(api.read(path), tmp_path / "again.fits", layout="cell_coadds")
    with fits.open(again) as hdus:
        assert hdus[1].header["SKYMAP"] == "DC2_cells_v1"
    # a name the file does not give: read(..., skymap=...) names it
    _write_by_hand(path, skymap="my_cells")
    with pytest.raises(CellCoaddFormatError, match="'my_cells' is not a sky map"):
        api.read(path)
    named = api.read(path, skymap="lsst_cells_v1").metadata
    assert named.skymap_config == lsst and named.tract_center == meta.tract_center
    # a sky map of another geometry is refused, against the file's grid or its own name
    with pytest.raises(CellCoaddFormatError, match="150 px inner, 150 px outer"):
        api.read(path, skymap="lsst_cells_v2")
    _write_by_hand(path, skymap="lsst_cells_v1")
    with pytest.raises(
        CellCoaddFormatError, match="geometry is not that of skymap='lsst_cells_v2'"
    ):
        api.read(path, skymap="lsst_cells_v2")
    with pytest.raises(
        ConfigError, match=r"unknown sky map name 'hsc'; known: DC2_cells_v1, lsst, "
    ):
        api.read(path, skymap="hsc")
    ours = api.write(make_patch(seed=1), tmp_path / "ours.fits")
    with pytest.raises(ConfigError, match="skymap applies to lsst.cell_coadds files only"):
        api.read(ours, skymap="lsst_cells_v1")
    # the command line names it too
    _write_by_hand(path, skymap="my_cells")
    runner = CliRunner()
    result = runner.invoke(info_command, [str(path), "--json", "--skymap", "lsst_cells_v1"])
    assert result.exit_code == 0, result.output
    assert f'"tract": {TRACT}' in result.output
    result = runner.invoke(info_command, [str(path), "--skymap", "hsc"])
    assert result.exit_code != 0 and "known: DC2_cells_v1" in result.output
    target = tmp_path / "named.h5"
    result = runner.invoke(convert_command, [str(path), str(target), "--skymap", "lsst_cells_v1"])
    assert result.exit_code == 0, result.output
    assert api.read(target).metadata.skymap_config.name == "lsst_cells_v1"


def test_the_wcs_must_agree_with_the_declared_sky_map(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, wcs=_tract_wcs_cards(crpix=14999.5))  # our old box-centre tangent
    with pytest.raises(
        CellCoaddFormatError, match=r"HDU 0.*disagrees with SKYMAP = 'lsst_cells_v1'"
    ):
        api.read(path)
    _write_by_hand(path, wcs=_tract_wcs_cards(tract=TRACT + 1))
    with pytest.raises(CellCoaddFormatError, match=r"patch corners are [\d.e+]+ px from"):
        api.read(path)


def test_the_cell_grid_must_agree_with_the_declared_sky_map(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, extra={"OCELL1": 300, "OCELL2": 300})
    with pytest.raises(
        CellCoaddFormatError, match=r"has cells of 150 px inner, 250 px outer.*has 150, 300"
    ):
        api.read(path)


def test_unknown_sky_map_without_tract_size_is_refused(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, skymap="hsc_rings_v1")
    with pytest.raises(CellCoaddFormatError, match=r"'hsc_rings_v1' is not a sky map.*TRACTPIX"):
        api.read(path)
    _write_by_hand(path, skymap="hsc_rings_v1", extra={"TRACTPIX": 30000})
    meta = api.read(path).metadata
    assert meta.skymap_config.patches_per_tract == 10
    assert meta.skymap_config.tangent_pixel == 14999 and meta.skymap_config.name == "hsc_rings_v1"


def test_legacy_units_need_a_zero_point(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, units="legacy", version="0.6")
    with pytest.raises(
        CellCoaddFormatError,
        match=r"TUNIT2 = 'legacy'.*no MAGZERO.*cellcoadd\.read\(path, legacy_zero_point=27\.0\)"
        r".*--legacy-zero-point 27",
    ):
        api.read(path)
    with CellCoaddsFile(str(path), legacy_zero_point=27.0) as opened:
        assert (opened.metadata.units, opened.metadata.zero_point) == ("count", 27.0)
    assert api.read(path, legacy_zero_point=27.5).metadata.zero_point == 27.5
    _write_by_hand(path, units="legacy", extra={"MAGZERO": 30.0})
    meta = api.read(path).metadata
    assert (meta.units, meta.zero_point) == ("count", 30.0)
    with pytest.raises(CellCoaddFormatError, match="MAGZERO = 30.0 but legacy_zero_point = 27"):
        CellCoaddsFile(str(path), legacy_zero_point=27.0)


def test_cli_takes_the_legacy_zero_point(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, units="legacy")
    runner = CliRunner()
    result = runner.invoke(info_command, [str(path)])
    assert result.exit_code != 0 and "no MAGZERO" in result.output
    result = runner.invoke(info_command, [str(path), "--json", "--legacy-zero-point", "27"])
    assert result.exit_code == 0, result.output
    assert '"zero_point": 27.0' in result.output
    ours = tmp_path / "ours.h5"
    result = runner.invoke(convert_command, [str(path), str(ours), "--legacy-zero-point", "27"])
    assert result.exit_code == 0, result.output
    assert api.read(ours).metadata.zero_point == 27.0


def test_counts_are_written_with_their_zero_point(tmp_path):
    counts = make_patch(seed=8)
    meta = counts.metadata.model_copy(
        update={
            "units": "count",
            "zero_point": 30.0,
            "build_config": counts.metadata.build_config.model_copy(
                update={"units": "count", "zero_point": 30.0}
            ),
        }
    )
    counts = PatchCoadd(PatchMetadata.model_validate(meta.model_dump()), counts.cells)
    ours = api.write(counts, tmp_path / "ours.fits", layout="cell_coadds")
    lsst = tmp_path / "lsst.fits"
    _lsst_part(ours, lsst)
    with fits.open(lsst) as hdus:
        assert hdus[1].header["TUNIT2"] == "legacy" and hdus[1].header["MAGZERO"] == 30.0
    read = api.read(lsst).metadata
    assert (read.units, read.zero_point) == ("count", 30.0)  # not 27: fluxes as written


def test_an_empty_patch_is_refused_clearly(tmp_path):
    meta = make_metadata(SMALL)
    empty = make_patch(seed=2, empty=tuple(meta.all_cell_indices))
    target = tmp_path / "empty.fits"
    with pytest.raises(
        CellCoaddFormatError, match=r"empty\.fits: .*no cell with data.*empty patch"
    ):
        api.write(empty, target, layout="cell_coadds")
    assert not target.exists()


def test_cli_info_and_convert_both_ways(tmp_path, patch):
    runner = CliRunner()
    lsst = tmp_path / "lsst.fits"
    _write_by_hand(lsst)
    result = runner.invoke(info_command, [str(lsst)])
    assert result.exit_code == 0, result.output
    assert "CELL_COADDS" in result.output and "format 0.8" in result.output
    ours = tmp_path / "ours.h5"
    result = runner.invoke(convert_command, [str(lsst), str(ours)])
    assert result.exit_code == 0, result.output
    again = tmp_path / "again.fits"
    result = runner.invoke(convert_command, [str(ours), str(again), "--layout", "cell_coadds"])
    assert result.exit_code == 0, result.output
    assert api.read(again).equals(api.read(ours))
    assert api.read(again).equals(api.read(lsst))
    result = runner.invoke(
        convert_command, [str(ours), str(tmp_path / "x.h5"), "--layout", "cell_coadds"]
    )
    assert result.exit_code != 0 and ".fits" in result.output


# ------------------------------------------------------------------------------ errors


def test_write_refuses_what_the_layout_cannot_hold(tmp_path, patch):
    with pytest.raises(ValueError, match="fits"):
        api.write(patch, tmp_path / "x.h5", layout="cell_coadds")
    with pytest.raises(ValueError, match="compress"):
        api.write(patch, tmp_path / "x.fits", layout="cell_coadds", compression="lossless")
    with pytest.raises(ValueError):
        api.write(patch, tmp_path / "x.fits.fz", layout="cell_coadds")
    with pytest.raises(ValueError, match="unknown layout"):
        api.write(patch, tmp_path / "x.fits", layout="lsst")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("options", "hdu", "words"),
    [
        ({"version": "1.0"}, "HDU 1 (cell table)", "VERSION 1.0"),
        ({"version": "0.5"}, "HDU 1 (cell table)", "not supported"),
        ({"units": "chi"}, "HDU 1 (cell table)", "chi"),
        ({"mask_value": 1 << 12}, "HDU 1 (cell table) row 0", "MASKDEF"),
        ({"skip": ("MASKDEF",)}, "HDU MASKDEF", "missing"),
    ],
)
def test_errors_name_the_file_and_the_hdu(tmp_path, options, hdu, words):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, **options)
    with pytest.raises(CellCoaddFormatError) as caught:
        api.read(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and hdu in message and words in message


def test_corrupted_pixels_are_caught(tmp_path, patch):
    path = api.write(patch, tmp_path / "cells.fits", layout="cell_coadds")
    with fitsio.FITS(str(path)) as hdus:
        offsets = hdus[1].get_offsets()
    raw = bytearray(path.read_bytes())
    raw[(offsets["data_start"] + offsets["data_end"]) // 2] ^= 0x10
    path.write_bytes(bytes(raw))
    with api.open(path) as lazy:  # the header part is intact: opening works
        with pytest.raises(CellCoaddFormatError, match=r"HDU 1 \(cell table\).*DATASUM"):
            lazy.read_cell(next(iter(lazy.cell_indices)))
    assert api.read(path, verify=False).metadata == patch.metadata


def test_corrupted_extension_is_caught(tmp_path, patch):
    path = api.write(patch, tmp_path / "cells.fits", layout="cell_coadds")
    with fitsio.FITS(str(path)) as hdus:
        offsets = hdus["CELLCOADD_INPUTS"].get_offsets()
    raw = bytearray(path.read_bytes())
    raw[offsets["data_start"] + 3] ^= 0x01
    path.write_bytes(bytes(raw))
    with pytest.raises(CellCoaddFormatError, match=r"cells\.fits: HDU \d+ \(CELLCOADD_INPUTS\)"):
        api.read(path)


def test_our_own_fits_files_are_not_taken_for_the_lsst_layout(tmp_path, patch):
    ours = api.write(patch, tmp_path / "ours.fits")
    assert not is_cell_coadds_file(str(ours))
    assert api.open(ours).format_name == "fits"
    text = tmp_path / "text.fits"
    text.write_text("hello")
    assert not is_cell_coadds_file(str(text))
    assert make_metadata(SMALL).n_noise == 2  # the factory the tests rely on
