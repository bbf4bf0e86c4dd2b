"""What FITS viewers and generic readers see in our FITS files: compressed float planes that
decode to the stored floats in BUNIT, bit-exact round trips, and a WCS on every pixel plane."""

from __future__ import annotations

import warnings

import fitsio
import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from coadd_factory import assert_same, make_patch

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.io import api
from cellcoadd.io.coadd import fits_format
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchCoadd

FLOAT_PLANES = [p.name for p in cell_planes.PLANES if p.compression == "float_bits"]
GRID_PLANES = [p.name for p in cell_planes.PLANES if p.on_cell_grid]


@pytest.fixture(scope="module")
def arbitrary() -> PatchCoadd:
    """Every float32 bit pattern: NaN payloads, infinities, -0.0, subnormals."""
    return make_patch(seed=27, n_noise=2, arbitrary_bits=True)


def _with_special_pixels(patch: PatchCoadd) -> PatchCoadd:
    cells = {}
    for index, cell in patch.items():
        image = np.array(cell.image, copy=True)
        image[0, 0] = np.float32(-0.47)
        image[0, 1] = np.nan  # the usual quiet NaN, 0x7FC00000
        image[0, 2] = np.inf
        image[0, 3] = np.float32(-0.0)
        cells[index] = CellCoadd(
            image=image,
            mask=cell.mask,
            variance=cell.variance,
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
    return PatchCoadd(patch.metadata, cells)


def test_compressed_round_trip_is_bit_exact(tmp_path, arbitrary):
    path = api.write(arbitrary, tmp_path / "patch.fits.fz")
    back = api.read(path)
    assert_same(back, arbitrary)
    for index, cell in arbitrary.items():
        for name in FLOAT_PLANES:
            want = getattr(cell, name).view(np.uint32)
            assert np.array_equal(getattr(back[index], name).view(np.uint32), want), name


def test_viewers_decode_compressed_planes_to_the_floats_in_bunit(tmp_path):
    patch = _with_special_pixels(make_patch(seed=5, arbitrary_bits=False))
    path = api.write(patch, tmp_path / "patch.fits.fz")
    index, cell = next(iter(patch.items()))
    name = fits_format.extname(index, "image")
    with fits.open(path) as hdus:  # astropy, as a viewer reads it
        hdu = hdus[name]
        assert isinstance(hdu, fits.CompImageHDU)
        assert hdu.header["BUNIT"] == "nJy"
        data = hdu.data
        assert data.dtype.kind == "f"
        assert data[0, 0] == np.float32(-0.47)  # not an integer bit pattern
        assert np.isnan(data[0, 1]) and np.isnan(data[0, 2])  # viewers show NaN for inf
        finite = np.isfinite(cell.image)
        assert np.array_equal(data[finite], cell.image[finite])
    raw = fitsio.read_header(str(path), ext=name)  # the stored binary table's header
    assert raw["ZQUANTIZ"] == "NONE" and raw["ZCMPTYPE"] == "GZIP_2"
    assert raw["ZBITPIX"] == -32 and "CCBITS" not in raw
    assert raw["CCNFNUM"] == 2  # the quiet NaN and the infinity are listed
    with fitsio.FITS(str(path)) as hdus:  # CFITSIO
        data = hdus[name].read()
        assert data.dtype.kind == "f" and data[0, 0] == np.float32(-0.47)
    back = api.read(path)[index]
    bits = back.image.view(np.uint32)
    assert bits[0, 1] == 0x7FC00000 and back.image[0, 2] == np.inf
    assert bits[0, 3] == 0x80000000  # -0.0


@pytest.mark.parametrize("suffix", [".fits", ".fits.fz"])
def test_every_pixel_plane_has_the_cells_wcs(tmp_path, suffix):
    patch = make_patch(seed=6, n_noise=2, arbitrary_bits=False)
    path = api.write(patch, tmp_path / f"patch{suffix}")
    index, cell = next(iter(patch.items()))
    pixels = np.array([[0.0, 0.0], [3.5, 7.25], [cell.shape[1] - 1.0, cell.shape[0] - 1.0]])
    expected = cell.wcs.all_pix2world(pixels, 0)
    with fits.open(path) as hdus, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # astropy's notes on fixed-up cards
        for plane in GRID_PLANES:
            header = hdus[fits_format.extname(index, plane)].header
            wcs = WCS(header).celestial
            assert wcs.has_celestial, plane
            np.testing.assert_allclose(wcs.all_pix2world(pixels, 0), expected, rtol=0, atol=1e-10)
        psf = hdus[fits_format.extname(index, "psf")].header  # a stamp: no sky grid
        assert "CTYPE1" not in psf


def test_a_corrupted_nonfinite_list_is_refused(tmp_path):
    patch = _with_special_pixels(make_patch(seed=7, arbitrary_bits=False))
    path = api.write(patch, tmp_path / "patch.fits.fz")
    index = next(iter(patch))
    name = fits_format.extname(index, "image")
    with fits.open(path, mode="update", disable_image_compression=True) as hdus:
        hdus[name].header["CCNFBITS"] = "bm90IHpsaWI="  # valid base64, not zlib
    with pytest.raises(CellCoaddFormatError, match=r"CCNFBITS cannot be decoded"):
        api.read(path, verify=False)
