"""Loading a described source reuses its header's WCS and gives what a plain load gives."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
from conftest import DES_PSF
from exposure_factory import make_exposure
from test_survey_readers import PSF, des_planes, des_tpv_wcs, write_des, write_lsst

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.exact_wcs import ExactWCS
from cellcoadd.geometry.wcs_utils import canonical_wcs, shifted_wcs
from cellcoadd.io import read_exposure, write_exposure
from cellcoadd.io.exposures.exposure_source import ExposureFile
from cellcoadd.io.exposures.mef_layout import DES_LAYOUT, LSST_LAYOUT
from cellcoadd.io.exposures.survey_readers import MefExposureFile
from cellcoadd.model.sources import DescribedSource, describe

BOXES = [
    Box(x_start=37, x_stop=211, y_start=58, y_stop=255),
    Box(x_start=0, x_stop=64, y_start=3, y_stop=40),
    None,
]


def _same_wcs(a, b) -> bool:
    """The same parameters and the same pickled state (what a worker receives), bit for bit."""
    same = isinstance(a, ExactWCS) and a.__reduce__() == b.__reduce__() and a.naxis == b.naxis
    for name in ("crpix", "crval", "cdelt", "pc"):
        same = same and np.array_equal(getattr(a.wcs, name), getattr(b.wcs, name))
    if a.sip is not None or b.sip is not None:
        same = same and a.sip is not None and b.sip is not None
        same = same and all(np.array_equal(getattr(a.sip, k), getattr(b.sip, k)) for k in "ab")
        same = same and np.array_equal(a.sip.crpix, b.sip.crpix)
    return bool(same and a.wcs.get_pv() == b.wcs.get_pv())


def _same_exposure(a, b) -> None:
    """Bit for bit: planes, identity, place, and the WCS."""
    for name in ("image", "mask", "variance"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
    assert (a.key, a.origin, a.valid_box, a.zero_point) == (
        b.key,
        b.origin,
        b.valid_box,
        b.zero_point,
    )
    assert _same_wcs(a.wcs, b.wcs)


def _is_canonical(wcs) -> bool:
    """A round trip (what sending it to another process does) changes nothing."""
    again = canonical_wcs(wcs)
    x, y = np.meshgrid(np.linspace(-50.5, 3000.25, 7), np.linspace(-20.0, 4100.75, 9))
    same_values = np.array_equal(wcs.all_pix2world(x, y, 0), again.all_pix2world(x, y, 0))
    return _same_wcs(wcs, again) and same_values


def _sip_exposure_file(tmp_path):
    exposure = make_exposure(
        center=(150.1, 2.2), shape=(260, 300), rotation_deg=31.0, sip=True, noise_sigma=2.0, seed=4
    )
    exposure = dataclasses.replace(exposure, variance=np.full(exposure.shape, 1.5))
    return write_exposure(exposure, tmp_path / "sip.fits")


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    root = tmp_path_factory.mktemp("described")
    made = {
        "cellcoadd SIP": ExposureFile(_sip_exposure_file(root)),
        "LSST SIP": MefExposureFile(write_lsst(root / "visit_image.fits"), LSST_LAYOUT, PSF),
    }
    des = write_des(root / "D00154912_Y_c12_r1p1_immasked.fits", des_planes())
    made["DES TPV"] = MefExposureFile(des, DES_LAYOUT, DES_PSF, zero_point=31.2)
    return made


@pytest.mark.parametrize("name", ["cellcoadd SIP", "LSST SIP", "DES TPV"])
def test_described_load_equals_plain_load(sources, name):
    source = sources[name]
    described = describe(source)
    assert isinstance(described, DescribedSource)
    assert _is_canonical(described.header.wcs)
    # the header as a worker receives it (pickled) serves as well as the original
    travelled = pickle.loads(pickle.dumps(described))
    for box in BOXES:
        plain = source.load(box)
        assert _is_canonical(plain.wcs)
        _same_exposure(described.load(box), plain)
        _same_exposure(travelled.load(box), plain)


@pytest.mark.parametrize("name", ["cellcoadd SIP", "LSST SIP", "DES TPV"])
def test_an_integer_shift_of_a_canonical_wcs_is_canonical(sources, name):
    wcs = sources[name].header().wcs
    for dx, dy in [(1, 0), (0, 7), (37, 58), (1023, 2047), (-5, 3)]:
        assert _is_canonical(shifted_wcs(wcs, dx, dy)), (dx, dy)


def test_the_real_des_tpv_wcs_shifts_canonically():
    wcs = canonical_wcs(des_tpv_wcs())
    # -6470.667 - 1999 is not the double nearest -8469.667: a header round trip would
    # change it, the exact pickle keeps it, so the plain shift is canonical as it is
    shifted = shifted_wcs(wcs, 812, 1999, canonical=False)
    y_ref = shifted.wcs.crpix[1]
    assert y_ref == wcs.wcs.crpix[1] - 1999 != float(f"{y_ref:.14g}")
    assert _is_canonical(shifted)


def test_a_wcs_of_another_file_is_refused(sources, tmp_path):
    path = sources["cellcoadd SIP"].path
    other = shifted_wcs(sources["cellcoadd SIP"].header().wcs, 3, 0)
    with pytest.raises(CellCoaddFormatError, match=r"sip\.fits.*another CRPIX1"):
        read_exposure(path, Box(x_start=0, x_stop=10, y_start=0, y_stop=10), wcs=other)


def test_a_source_without_load_described_is_loaded_plainly(sources):
    """Objects with only header() and load() (no ExposureSource base) still work."""
    inner = sources["cellcoadd SIP"]
    calls = []

    class Plain:
        def header(self):
            return inner.header()

        def load(self, box=None):
            calls.append(box)
            return inner.load(box)

    box = BOXES[0]
    described = DescribedSource(Plain(), inner.header())
    _same_exposure(described.load(box), inner.load(box))
    assert calls == [box]


def test_a_shift_of_a_wcs_with_many_digits_is_canonical():
    """Canonical form keeps all 17 digits of CRPIX, CRVAL and CD (a header keeps 14);
    the shifted reference pixel too."""
    from astropy.wcs import WCS

    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = [150.123456789012345, 2.98765432109876]
    wcs.wcs.crpix = [1234.5678901234567, 987.65432109876543]
    wcs.wcs.cd = [[-5.5e-5, 1.234567890123e-7], [1.1e-7, 5.5e-5]]
    wcs.wcs.set()
    canonical = canonical_wcs(wcs)
    for name in ("crpix", "crval"):  # the digits a header round trip would drop
        assert np.array_equal(getattr(canonical.wcs, name), getattr(wcs.wcs, name)), name
    assert np.array_equal(canonical.wcs.get_pc(), wcs.wcs.cd)
    for dx, dy in [(1, 0), (100, 37), (1233, 986), (-7, 2048)]:
        assert _is_canonical(shifted_wcs(canonical, dx, dy)), (dx, dy)
