"""The LSST ``lsst.cell_coadds`` FITS layout: exact round trips through our writer, files
written by hand exactly as the LSST writer lays them out, files without our extension
HDUs, the CLI, and errors that name the file and the HDU."""

from __future__ import annotations

import math

import fitsio
import numpy as np
import pytest
from astropy.io import fits
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
from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.io.foreign.cell_coadds_layout import is_cell_coadds_file
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchCoadd
from cellcoadd.model.units import NJY_ZERO_POINT

LSST_HDUS = ["", "", "CELL", "VISIT", "MASKDEF", "VISIT_SUMMARY"]


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

CELL_INNER, BORDER, PSF, NOISE = 10, 4, 7, 2
OUTER = CELL_INNER + 2 * BORDER
#: cells_per_patch 2 with one border cell: a 4 x 4 grid; patch (1, 2) of a 3 x 3-patch tract
GRID, PATCH, TRACT_PIXELS = 4, (1, 2), 60
GRMIN = ((PATCH[0] * 2 - 1) * CELL_INNER, (PATCH[1] * 2 - 1) * CELL_INNER)
LSST_MASK = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5, "NO_DATA": 8}
#: grid-local cell ids written, in an order of our choice (the LSST writer keeps insertion)
CELL_IDS = [(2, 1), (0, 0), (3, 3), (1, 2)]


def _tract_wcs_cards() -> list[dict]:
    """What afw's SkyWcs.getFitsMetadata() gives for a tract WCS (CD matrix, ICRS)."""
    scale = 0.2 / 3600
    centre = (TRACT_PIXELS - 1) / 2 + 1
    values = {
        "RADESYS": "ICRS",
        "EQUINOX": 2000.0,
        "CTYPE1": "RA---TAN",
        "CTYPE2": "DEC--TAN",
        "CUNIT1": "deg",
        "CUNIT2": "deg",
        "CRPIX1": centre,
        "CRPIX2": centre,
        "CRVAL1": 52.5,
        "CRVAL2": -28.0,
        "CD1_1": -scale,
        "CD1_2": 0.0,
        "CD2_1": 0.0,
        "CD2_2": scale,
    }
    return [{"name": k, "value": v} for k, v in values.items()]


def _write_by_hand(path, *, version="0.8", units="nJy", mask_value=None, skip=()) -> dict:
    """An lsst.cell_coadds file written field by field with fitsio, as the layout says."""
    rng = np.random.default_rng(4)
    plane = (OUTER, OUTER)
    dtype = [("cell_id", ">i2", (2,)), ("image", ">f4", plane), ("mask", ">i4", plane)]
    dtype += [("variance", ">f4", plane), ("psf", ">f8", (PSF, PSF)), ("maskfrac", ">f4", plane)]
    dtype += [(f"noise_{n:02}", ">f4", plane) for n in range(NOISE)]
    table = np.zeros(len(CELL_IDS), dtype=dtype)
    for row, cell_id in enumerate(CELL_IDS):
        table[row]["cell_id"] = cell_id
        for name in ("image", "variance", "maskfrac", *(f"noise_{n:02}" for n in range(NOISE))):
            table[row][name] = rng.standard_normal(plane)
        table[row]["mask"] = rng.choice([0, 1, 2, 4, 8, 32, 256, 33], size=plane)
        psf = rng.uniform(size=(PSF, PSF))
        table[row]["psf"] = psf / psf.sum()
    if mask_value is not None:
        table[0]["mask"][0, 0] = mask_value
    # CELL: (cell_x, cell_y, visit, detector, overlaps_center, overlap_fraction, weight,
    # psf_shape_ixx, psf_shape_iyy, psf_shape_ixy, psf_shape_flag)
    links = [
        (2, 1, 1001, 10, True, 1.0, 0.5, 3.0, 2.0, 0.25, False),
        (2, 1, 1002, 11, True, 1.0, 0.25, 2.5, 2.5, 0.0, False),
        (0, 0, 1001, 12, True, 1.0, 0.75, 0.0, 0.0, 0.0, True),
        (3, 3, 1002, 11, True, 0.875, 1.5, 2.0, 2.0, -0.5, False),
        (1, 2, 1003, 10, True, 1.0, 2.0, 2.25, 2.75, 0.5, False),
    ]
    names = "cell_x cell_y visit detector overlaps_center overlap_fraction weight".split()
    names += ["psf_shape_ixx", "psf_shape_iyy", "psf_shape_ixy", "psf_shape_flag"]
    cell = np.array(
        links, dtype=list(zip(names, ["i8"] * 4 + ["?"] + ["f8"] * 5 + ["?"], strict=True))
    )
    visit = np.array(
        [(1001, "r_57", 20250101), (1002, "r_57", 20250102), (1003, "r_57", 20250103)],
        dtype=[("visit", "i8"), ("physical_filter", "S4"), ("day_obs", "i8")],
    )
    maskdef = np.array(
        [(n.encode(), b) for n, b in LSST_MASK.items()],
        dtype=[("MASK_NAME", "S17"), ("BIT_VALUE", "u4")],
    )
    keys = {(v, d) for _, _, v, d, *_ in links}
    summary = np.zeros(
        len(keys),
        dtype=[
            ("visit", "i8"),
            ("detector", "i2"),
            ("physical_filter", "S32"),
            ("day_obs", "i8"),
            ("num_vertices", "i2"),
            ("polygon_vertices", "f4", (8, 2)),
        ],
    )
    for row, (v, d) in enumerate(sorted(keys)):
        summary[row] = (v, d, b"r_57", 20250101, 4, np.zeros((8, 2)))
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
        "INBBOX11": GRMIN[0],
        "INBBOX12": GRMIN[1],
        "INBBOX21": GRMIN[0] + GRID * CELL_INNER - 1,
        "INBBOX22": GRMIN[1] + GRID * CELL_INNER - 1,
        "VERSION": version,
        "TUNIT2": units,
        "TUNIT4": f"{units}**2",
        "INSTRUME": "LSSTCam",
        "FILTER": "r",
        "SKYMAP": "lsst_cells_v1",
        "TRACT": 9813,
        "PATCH_X": PATCH[0],
        "PATCH_Y": PATCH[1],
        "NNOISE": NOISE,
    }
    with fitsio.FITS(str(path), "rw", clobber=True) as out:
        out.write(None, header=_tract_wcs_cards())
        out.write(table, header=[{"name": k, "value": v} for k, v in header.items()])
        for data, name in ((cell, "CELL"), (visit, "VISIT"), (maskdef, "MASKDEF")):
            if name not in skip:
                out.write(data, extname=name)
        out.write(summary, extname="VISIT_SUMMARY", header={"POLYVERT": 8})
        for hdu in out:
            hdu.write_checksum()
    return {"table": table, "links": links}


def test_a_file_written_by_hand_reads_correctly(tmp_path):
    path = tmp_path / "lsst.fits"
    written = _write_by_hand(path)
    assert is_cell_coadds_file(str(path))
    read = api.read(path)
    meta = read.metadata
    assert (meta.tract, meta.patch, meta.band) == (9813, PATCH, "r")
    assert (meta.units, meta.zero_point) == ("nJy", NJY_ZERO_POINT)
    config = meta.skymap_config
    assert (config.cell_inner, config.cell_border, config.cells_per_patch) == (10, 4, 2)
    assert (config.patch_border_cells, config.patches_per_tract, config.pixel_scale) == (1, 3, 0.2)
    assert meta.tract_center == (52.5, -28.0)
    assert meta.mask_bits.bits == LSST_MASK
    assert (meta.n_noise, meta.psf_size) == (NOISE, PSF)
    first = (PATCH[0] * 2 - 1, PATCH[1] * 2 - 1)  # tract-global index of grid cell (0, 0)
    expected_ids = sorted((first[0] + i, first[1] + j) for i, j in CELL_IDS)
    assert list(read) == expected_ids
    tract = WCS(fits.Header({c["name"]: c["value"] for c in _tract_wcs_cards()}))
    for row, (i, j) in enumerate(CELL_IDS):
        cell = read[first[0] + i, first[1] + j]
        data = written["table"][row]
        assert cell.inner_bbox.x_start == GRMIN[0] + i * CELL_INNER
        assert cell.inner_bbox.y_start == GRMIN[1] + j * CELL_INNER
        assert cell.outer_bbox.x_start == cell.inner_bbox.x_start - BORDER
        assert cell.shape == (OUTER, OUTER)
        # array pixel (x, y) of a cell is tract pixel outer start + (x, y)
        x0, y0 = cell.outer_bbox.x_start, cell.outer_bbox.y_start
        assert np.allclose(
            cell.wcs.wcs_pix2world([[3, 5]], 0), tract.wcs_pix2world([[x0 + 3, y0 + 5]], 0)
        )
        assert np.array_equal(cell.image, data["image"].astype(np.float32))
        assert np.array_equal(cell.variance, data["variance"].astype(np.float32))
        assert np.array_equal(cell.mfrac, data["maskfrac"].astype(np.float32))
        assert np.array_equal(cell.mask, data["mask"].astype(np.int32))
        assert np.array_equal(cell.psf, data["psf"].astype(np.float64))
        for n in range(NOISE):
            assert np.array_equal(cell.noise[n], data[f"noise_{n:02}"].astype(np.float32))
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
    # the masks' named bits are the file's
    assert read[first[0] + 2, first[1] + 1].mask.max() <= 256 + 32 + 8
    summary = patch_summary(str(path))
    assert summary["format"] == "cell_coadds" and summary["layout_version"] == "0.8"
    assert summary["inputs"]["used"] == len(written["links"])


def test_legacy_units_are_counts(tmp_path):
    path = tmp_path / "lsst.fits"
    _write_by_hand(path, units="legacy", version="0.6")
    meta = api.read(path).metadata
    assert (meta.units, meta.zero_point) == ("count", 27.0)


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
