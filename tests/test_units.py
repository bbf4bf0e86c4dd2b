"""Units and conventions tools can read: nJy or counts at a zero point (metadata, BUNIT,
MAGZERO, MP_* keywords, HDF5 attributes), astropy NDData of a cell, the stitched image's
WCS, and the convention of the input PSF moments."""

from __future__ import annotations

import json

import astropy.units as u
import galsim
import h5py
import numpy as np
import pytest
from astropy.io import fits
from astropy.nddata import CCDData, VarianceUncertainty
from coadd_factory import make_patch
from exposure_factory import make_exposure
from pydantic import ValidationError

from cellcoadd import BuildConfig, SkyMap, SkyMapConfig, build_cell
from cellcoadd.io import api
from cellcoadd.io.coadd import format_version
from cellcoadd.io.exposures.mef_layout import NJY_ZERO_POINT as LAYOUT_NJY_ZERO_POINT
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd, PatchMetadata
from cellcoadd.model.units import NJY_ZERO_POINT, legacy_units

CONFIG = SkyMapConfig(cell_inner=50, cell_border=20, cells_per_patch=2, patches_per_tract=1)
OLD_TEXT = "counts at zero point 30 per coadd pixel"  # what builds wrote before format 1.2


@pytest.fixture(scope="module")
def tract():
    return SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0]


@pytest.fixture(scope="module")
def patch():
    return make_patch(seed=5, arbitrary_bits=False)


def counts_patch(patch: PatchCoadd, zero_point: float) -> PatchCoadd:
    meta = patch.metadata.model_copy(
        update={
            "units": "count",
            "zero_point": zero_point,
            "build_config": patch.metadata.build_config.model_copy(
                update={"units": "count", "zero_point": zero_point}
            ),
        }
    )
    return PatchCoadd(meta, patch.cells)


# ---------------------------------------------------------------- configuration, metadata


def test_njy_zero_point_lives_in_the_model_layer():
    assert NJY_ZERO_POINT == pytest.approx(31.4, abs=1e-4)
    assert NJY_ZERO_POINT == 2.5 * np.log10(3631e9)
    assert LAYOUT_NJY_ZERO_POINT is NJY_ZERO_POINT  # the survey readers import it


def test_build_config_units():
    default = BuildConfig()
    assert (default.units, default.zero_point) == ("nJy", NJY_ZERO_POINT)
    stated = BuildConfig(zero_point=27.5)  # a zero point alone means counts at it
    assert (stated.units, stated.zero_point) == ("count", 27.5)
    assert BuildConfig(units="counts", zero_point=30).units == "count"
    assert BuildConfig(units="nJy", zero_point=31.4000656).zero_point == NJY_ZERO_POINT
    with pytest.raises(ValidationError, match="need a zero_point"):
        BuildConfig(units="count")
    with pytest.raises(ValidationError, match="nJy"):
        BuildConfig(units="nJy", zero_point=30.0)
    with pytest.raises(ValidationError):
        BuildConfig(units="Jy")
    for config in (default, stated):
        assert BuildConfig.model_validate_json(config.model_dump_json()) == config
    # the build configuration of a format 1.1 file: no units, zero point 30
    assert BuildConfig.model_validate({"n_noise": 2, "zero_point": 30.0}).units == "count"


def test_metadata_units_are_astropy_units(patch):
    meta = patch.metadata
    assert (meta.units, meta.zero_point, meta.unit) == ("nJy", NJY_ZERO_POINT, u.nJy)
    assert u.Unit(meta.units, format="fits") == u.nJy
    counts = counts_patch(patch, 28.25).metadata
    assert counts.unit == u.count and u.Unit(counts.units, format="fits") == u.count
    fields = meta.model_dump(exclude={"units", "zero_point"})
    # the free text builds wrote before format 1.2 is taken, and stored parsable
    old_text = PatchMetadata(**fields, units=OLD_TEXT)
    assert (old_text.units, old_text.zero_point) == ("count", 30.0)
    with pytest.raises(ValidationError):
        PatchMetadata(**fields, units="counts per pixel")  # other free text
    with pytest.raises(ValidationError):
        PatchMetadata(**fields, units="3.63078 nJy")  # never a rounded scaled unit
    with pytest.raises(ValidationError, match="nJy"):
        PatchMetadata(**fields, units="nJy", zero_point=30.0)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (OLD_TEXT, ("count", 30.0)),
        ("counts at zero point 27.5", ("count", 27.5)),
        ("nJy", ("nJy", NJY_ZERO_POINT)),
        ("count", ("count", None)),
        ("ADU", None),
    ],
)
def test_legacy_units_text(text, expected):
    assert legacy_units(text) == expected


def test_old_free_text_units_still_read(patch):
    data = json.loads(patch.metadata.model_dump_json())
    del data["zero_point"], data["build_config"]["units"]
    data["build_config"]["zero_point"] = 27.123456789
    data.update(units="counts at zero point 27.1235 per coadd pixel", format_version="1.1")
    old = PatchMetadata.model_validate(data)
    # the configuration's exact zero point, not the text's 6 digits
    assert (old.units, old.zero_point, old.build_config.units) == ("count", 27.123456789, "count")
    # any other free text of an old file: counts at the build's zero point
    data["units"] = "counts per pixel"
    assert PatchMetadata.model_validate(data).zero_point == 27.123456789
    data["format_version"] = FORMAT_VERSION  # new files are strict
    with pytest.raises(ValidationError):
        PatchMetadata.model_validate(data)


@pytest.mark.parametrize("name", ["old.fits", "old.h5"])
def test_format_1_1_files_with_free_text_units_read(tmp_path, monkeypatch, patch, name):
    def old_payload(metadata):
        data = json.loads(metadata.model_dump_json())
        del data["zero_point"], data["build_config"]["units"]
        data["build_config"]["zero_point"] = 30.0
        data.update(units=OLD_TEXT, format_version="1.1")
        return json.dumps(data).encode("utf-8"), "1.1"

    monkeypatch.setattr(format_version, "metadata_payload", old_payload)
    api.write(patch, tmp_path / name)
    monkeypatch.undo()
    read = api.read(tmp_path / name)
    meta = read.metadata
    assert (meta.format_version, meta.units, meta.zero_point) == ("1.1", "count", 30.0)
    assert meta.build_config.units == "count" and meta.build_config.zero_point == 30.0
    assert read[next(iter(patch))].equals(patch[next(iter(patch))])
    # written again, it is a current file with the mapped units
    api.write(read, tmp_path / f"new_{name}")
    again = api.read(tmp_path / f"new_{name}").metadata
    assert (again.format_version, again.units, again.zero_point) == (FORMAT_VERSION, "count", 30.0)


# ---------------------------------------------------------------- keywords and attributes


@pytest.mark.parametrize("name", ["units.fits", "units.fits.fz"])
def test_fits_bunit_magzero_and_mask_planes(tmp_path, patch, name):
    for case, coadd in (("njy", patch), ("counts", counts_patch(patch, 28.25))):
        path = tmp_path / f"{case}_{name}"
        api.write(coadd, path)
        bits = coadd.metadata.mask_bits.bits
        with fits.open(path) as hdus:
            planes = {hdu.header.get("EXTNAME"): hdu.header for hdu in hdus[1:]}
            checked = 0
            for index in coadd:
                prefix = f"CELL_{index[0]:+03d}_{index[1]:+03d}_"
                for plane, power in (("IMAGE", 1), ("NOISE", 1), ("VARIANCE", 2)):
                    header = planes[prefix + plane]
                    assert u.Unit(header["BUNIT"], format="fits") == coadd.metadata.unit**power
                    if case == "counts":
                        assert header["MAGZERO"] == 28.25
                    else:
                        assert header["BUNIT"] == ("nJy", "nJy2")[power - 1]
                        assert "MAGZERO" not in header
                mask = planes[prefix + "MASK"]
                assert {name: mask[f"MP_{name}"] for name in bits} == bits
                assert "BUNIT" not in mask and "BUNIT" not in planes[prefix + "PSF"]
                checked += 1
            assert checked == len(coadd)
        assert api.read(path).equals(coadd)


def test_hdf5_attributes(tmp_path, patch):
    for case, coadd in (("njy", patch), ("counts", counts_patch(patch, 28.25))):
        path = tmp_path / f"{case}.h5"
        api.write(coadd, path, compression="lossless")
        with h5py.File(path, "r") as h5:
            for group in h5["cells"].values():
                for plane, power in (("image", 1), ("noise", 1), ("variance", 2)):
                    attrs = group[plane].attrs
                    unit = u.Unit(attrs["BUNIT"].decode(), format="fits")
                    assert unit == coadd.metadata.unit**power
                    assert ("MAGZERO" in attrs) == (case == "counts")
                    if case == "counts":
                        assert attrs["MAGZERO"] == 28.25
                mask = group["mask"].attrs
                bits = coadd.metadata.mask_bits.bits
                assert {name: int(mask[f"MP_{name}"]) for name in bits} == bits
        assert api.read(path).equals(coadd)


def test_mask_bit_names_that_are_not_fits_keywords_stay_in_the_json(patch):
    bits = MaskBits(bits={**MaskBits().bits, "lower": 9, "BADPIX_CRAY": 10})
    meta = patch.metadata.model_copy(update={"mask_bits": bits})
    names = [key for key, _, _ in meta.unit_cards()["mask"]]
    assert "MP_BADPIX_CRAY" in names and "MP_lower" not in names


# ---------------------------------------------------------------- astropy NDData


def _sky(wcs, x, y):
    return wcs.pixel_to_world(x, y)


@pytest.fixture(scope="module")
def built(tract):
    cell = tract.cell(0, 0)
    star = (*cell.center_sky, galsim.DeltaFunction(flux=5e3))
    exposures = [
        make_exposure(
            cell.center_sky,
            sources=[star],
            visit=visit,
            rotation_deg=25.0 * visit,
            noise_sigma=2.0,
            seed=visit,
        )
        for visit in range(3)
    ]
    return cell, exposures


def test_cell_to_nddata(built, tmp_path):
    cell, exposures = built
    coadd = build_cell(cell, exposures, BuildConfig(n_noise=1, psf_size=25))
    coadd.mask[3:6, 4:9] |= MaskBits().value("SAT")
    coadd.mask[10, 11] |= MaskBits().value("INTRP")
    nd = coadd.to_nddata("nJy", mask_bits=MaskBits())
    assert isinstance(nd, CCDData) and nd.unit == u.nJy
    np.testing.assert_array_equal(nd.data, coadd.image)
    assert isinstance(nd.uncertainty, VarianceUncertainty)
    assert nd.uncertainty.unit == u.nJy**2
    np.testing.assert_array_equal(nd.uncertainty.array, coadd.variance)
    np.testing.assert_array_equal(nd.mask, coadd.mask != 0)  # True = flagged
    assert nd.mask.dtype == bool and nd.mask[4, 5] and nd.mask[10, 11]
    assert nd.meta["MP_SAT"] == 1 and (nd.meta["CELL_X"], nd.meta["CELL_Y"]) == cell.index
    only_sat = coadd.to_nddata(u.nJy, bad_bits=["SAT"])
    assert only_sat.mask[4, 5] and not only_sat.mask[10, 11]
    xs, ys = np.array([0.0, 17.0, 60.5]), np.array([0.0, 44.0, 3.25])
    a, b = _sky(nd.wcs, xs, ys), _sky(coadd.wcs, xs, ys)
    assert np.all(a.separation(b).to_value(u.arcsec) < 1e-9)
    # the inner box: its own WCS, same sky positions
    inner = coadd.to_nddata("nJy", inner=True)
    np.testing.assert_array_equal(inner.data, coadd.inner.image)
    dx = cell.inner_bbox.x_start - cell.outer_bbox.x_start
    dy = cell.inner_bbox.y_start - cell.outer_bbox.y_start
    a, b = _sky(inner.wcs, xs, ys), _sky(coadd.wcs, xs + dx, ys + dy)
    assert np.all(a.separation(b).to_value(u.arcsec) < 1e-9)
    # through a FITS file written by astropy and back
    path = tmp_path / "cell_ccd.fits"
    nd.write(path)
    back = CCDData.read(path)
    assert back.unit == u.nJy
    np.testing.assert_array_equal(back.data, coadd.image)
    np.testing.assert_array_equal(back.uncertainty.array, coadd.variance)
    assert isinstance(back.uncertainty, VarianceUncertainty)
    np.testing.assert_array_equal(back.mask, nd.mask)
    a, b = _sky(back.wcs, xs, ys), _sky(coadd.wcs, xs, ys)
    assert np.all(a.separation(b).to_value(u.arcsec) < 1e-6)


def test_patch_to_nddata_uses_the_metadata(patch):
    index = next(iter(patch))
    nd = patch.to_nddata(index)
    assert nd.unit == u.nJy and "MAGZERO" not in nd.meta
    counts = counts_patch(patch, 28.25).to_nddata(index)
    assert counts.unit == u.count and counts.meta["MAGZERO"] == 28.25
    assert counts.uncertainty.unit == u.count**2


# ---------------------------------------------------------------- stitching


def test_stitched_wcs_maps_pixels_like_the_cells(patch):
    image, wcs, box = patch.stitched("image")
    np.testing.assert_array_equal(image, patch.stitch("image"), strict=True)
    assert box == patch.patch_inner_bbox
    side = patch.metadata.cell_inner
    rng = np.random.default_rng(1)
    for index in patch.inner_cell_indices:
        cell = patch[index]
        inner, outer = cell.inner_bbox, cell.outer_bbox
        # tract pixels inside the cell's inner box, sub-pixel positions too
        x = inner.x_start + rng.uniform(-0.5, side - 0.5, 5)
        y = inner.y_start + rng.uniform(-0.5, side - 0.5, 5)
        a = _sky(wcs, x - box.x_start, y - box.y_start)
        b = _sky(cell.wcs, x - outer.x_start, y - outer.y_start)
        assert np.all(a.separation(b).to_value(u.arcsec) < 1e-9)
        rows, cols = inner.slices_in(box)
        stitched_view = image[rows, cols]
        np.testing.assert_array_equal(stitched_view, cell.inner.image)
    # without stored cells the sky map gives the same WCS
    bare = PatchCoadd(patch.metadata, {})
    xs, ys = np.array([0.0, 5.5, 15.0]), np.array([0.0, 9.0, 2.5])
    a, b = _sky(bare.stitch_wcs, xs, ys), _sky(wcs, xs, ys)
    assert np.all(a.separation(b).to_value(u.arcsec) < 1e-6)


# ---------------------------------------------------------------- pixel values


def test_njy_and_counts_scale_a_stars_flux(built):
    cell, exposures = built
    flux_counts_30 = 5e3  # the star's counts at the exposures' zero point 30
    magnitude = 30.0 - 2.5 * np.log10(flux_counts_30)
    sums = {}
    for name, config in {
        "nJy": BuildConfig(n_noise=0, psf_size=25),
        "count30": BuildConfig(n_noise=0, psf_size=25, zero_point=30.0),
        "count27": BuildConfig(n_noise=0, psf_size=25, units="count", zero_point=27.0),
    }.items():
        image = build_cell(cell, exposures, config).image.astype(float)
        ny, nx = image.shape
        sums[name] = image[ny // 2 - 15 : ny // 2 + 16, nx // 2 - 15 : nx // 2 + 16].sum()
    # aperture sums hold the noise too: compare the ratios, which are exact per pixel
    assert sums["nJy"] / sums["count30"] == pytest.approx(10 ** (0.4 * (NJY_ZERO_POINT - 30)))
    assert sums["count27"] / sums["count30"] == pytest.approx(10 ** (0.4 * (27.0 - 30.0)))
    assert sums["nJy"] == pytest.approx(10 ** (-0.4 * (magnitude - NJY_ZERO_POINT)), rel=0.02)
    # 1 nJy is AB magnitude 31.4
    assert 10 ** (-0.4 * (magnitude - NJY_ZERO_POINT)) == pytest.approx(
        (10 ** (-0.4 * magnitude) * 3631 * u.Jy).to_value(u.nJy)
    )


def test_default_build_records_njy(tract):
    cell = tract.cell(1, 0)
    from cellcoadd import build_patch

    exposure = make_exposure(cell.center_sky, shape=(400, 400))
    coadd = build_patch(
        tract.patch(0, 0), [exposure], BuildConfig(n_noise=0, psf_size=11), progress=False
    )
    assert (coadd.metadata.units, coadd.metadata.zero_point) == ("nJy", NJY_ZERO_POINT)
    counts = build_patch(
        tract.patch(0, 0),
        [exposure],
        BuildConfig(n_noise=0, psf_size=11, zero_point=30.0),
        progress=False,
    )
    assert (counts.metadata.units, counts.metadata.zero_point) == ("count", 30.0)


# ---------------------------------------------------------------- PSF moments


@pytest.mark.parametrize(
    ("rotation", "scale"), [(0.0, 0.2), (30.0, 0.26), (-71.0, 0.24)], ids=["aligned", "r30", "r-71"]
)
def test_input_psf_moments_on_the_coadd_grid(tract, rotation, scale):
    """An elliptical Gaussian PSF gives T = Ixx + Iyy (arcsec^2) and the distortions e1,
    e2 of its sky shape, whatever the exposure's rotation and pixel scale (measured on the
    coadd's grid, x West / y North, not on the exposure's axes)."""
    cell = tract.cell(0, 0)
    sigma, e1, e2 = 0.6, 0.12, -0.07
    psf = galsim.Gaussian(sigma=sigma).shear(e1=e1, e2=e2)  # e1, e2: distortions
    exposure = make_exposure(cell.center_sky, psf=psf, rotation_deg=rotation, pixel_scale=scale)
    record = build_cell(cell, [exposure], BuildConfig(n_noise=0, psf_size=45)).inputs[0]
    assert record.is_used
    e = np.hypot(e1, e2)
    moments = sigma**2 * np.array([[1 + e1, e2], [e2, 1 - e1]]) / np.sqrt(1 - e * e)
    moments += scale**2 / 12 * np.eye(2)  # the exposure's square pixel
    size = np.trace(moments)
    assert record.psf_T == pytest.approx(size, rel=5e-3)
    assert record.psf_e1 == pytest.approx((moments[0, 0] - moments[1, 1]) / size, abs=2e-3)
    assert record.psf_e2 == pytest.approx(2 * moments[0, 1] / size, abs=2e-3)
    fwhm = 2 * np.sqrt(2 * np.log(2)) * np.linalg.det(moments) ** 0.25
    assert record.psf_fwhm == pytest.approx(fwhm, rel=5e-3)


def test_round_gaussian_psf_has_T_two_sigma_squared(tract):
    cell = tract.cell(0, 0)
    sigma = 0.7
    exposure = make_exposure(
        cell.center_sky, psf=galsim.Gaussian(sigma=sigma), pixel_scale=0.05, shape=(500, 500)
    )
    record = build_cell(cell, [exposure], BuildConfig(n_noise=0, psf_size=45)).inputs[0]
    assert record.psf_T == pytest.approx(2 * sigma**2 + 2 * 0.05**2 / 12, rel=5e-3)
    assert abs(record.psf_e1) < 1e-3 and abs(record.psf_e2) < 1e-3
