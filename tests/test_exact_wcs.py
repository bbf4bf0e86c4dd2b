"""ExactWCS: a WCS sent to another process comes back bit for bit (TAN, TAN-SIP, TPV).

astropy pickles a WCS through 14-digit FITS cards; canonical_wcs returns an ExactWCS whose
pickle keeps every parameter exactly, so a computation gives the same bits in a worker.
"""

from __future__ import annotations

import copy
import json
import pickle
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS, DistortionLookupTable
from conftest import DES_HEADER
from test_survey_readers import DES_NX, DES_NY

from cellcoadd.geometry import SkyMap
from cellcoadd.geometry.exact_wcs import ExactWCS, wcs_exact_parameters
from cellcoadd.geometry.wcs_utils import canonical_wcs, shifted_wcs
from cellcoadd.model.wcs_codec import wcs_from_record, wcs_to_record

#: Pixel positions (0-based x, y) over and beyond a 4096 x 4096 image.
RNG = np.random.default_rng(2027)
PIXELS = RNG.uniform(-200.0, 4300.0, (500, 2))


def tan_sip_header() -> fits.Header:
    """A TAN-SIP image header as LSST/HSC pipelines write it: CD matrix, 17-digit values,
    third-order forward and inverse polynomials."""
    cards = [
        ("NAXIS", 2),
        ("NAXIS1", 4072),
        ("NAXIS2", 4000),
        ("CTYPE1", "RA---TAN-SIP"),
        ("CTYPE2", "DEC--TAN-SIP"),
        ("CRPIX1", 2036.5123456789012),
        ("CRPIX2", 1999.8765432109877),
        ("CRVAL1", 53.163590156789012),
        ("CRVAL2", -27.782300987654321),
        ("CD1_1", -5.5478120591234567e-05),
        ("CD1_2", 1.2345678901234567e-07),
        ("CD2_1", 1.1098765432109876e-07),
        ("CD2_2", 5.5541234567890123e-05),
        ("CUNIT1", "deg"),
        ("CUNIT2", "deg"),
        ("RADESYS", "ICRS"),
        ("A_ORDER", 3),
        ("B_ORDER", 3),
        ("AP_ORDER", 3),
        ("BP_ORDER", 3),
    ]
    for prefix, sign in (("A", 1.0), ("B", -1.0), ("AP", -1.0), ("BP", 1.0)):
        for p, q, value in ((2, 0, 1.2345678901234567e-6), (1, 1, -3.3333333333333333e-7)):
            cards.append((f"{prefix}_{p}_{q}", sign * value))
        cards += [(f"{prefix}_0_2", sign * 7.1428571428571428e-7)]
        cards += [(f"{prefix}_3_0", sign * 1.0000000000000002e-10)]
    return fits.Header(cards)


def tan_sip_wcs() -> WCS:
    return WCS(tan_sip_header())


def des_tpv_wcs() -> WCS:
    """The real DECam CCD's TPV WCS (PV distortion terms), as astropy reads it."""
    header = fits.getheader(DES_HEADER)
    header["NAXIS"], header["NAXIS1"], header["NAXIS2"] = 2, DES_NX, DES_NY
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WCS(header)


def tract_wcs() -> WCS:
    """Rubin's tract 9469 (on the equator, RA ~ 0): 30,000 px, 17-digit parameters."""
    return SkyMap.named("lsst_cells_v1")[9469].wcs


WCS_MAKERS = {"tract": tract_wcs, "TAN-SIP": tan_sip_wcs, "DES TPV": des_tpv_wcs}


def _same_parameters(a: WCS, b: WCS) -> bool:
    return json.dumps(wcs_exact_parameters(a)) == json.dumps(wcs_exact_parameters(b))


def _evaluate(wcs: WCS) -> tuple[np.ndarray, np.ndarray, WCS]:
    """In the worker: sky positions of PIXELS, pixels back, and the WCS as received."""
    sky = wcs.all_pix2world(PIXELS, 0)
    return sky, wcs.all_world2pix(sky, 0), wcs


@pytest.mark.parametrize("name", list(WCS_MAKERS))
def test_canonical_wcs_keeps_every_parameter_and_pickles_exactly(name):
    raw = WCS_MAKERS[name]()
    wcs = canonical_wcs(raw)
    assert isinstance(wcs, ExactWCS)
    assert _same_parameters(wcs, raw)  # CRVAL, CD (as PC x CDELT), SIP, PV: all 17 digits
    assert np.array_equal(wcs.all_pix2world(PIXELS, 0), raw.all_pix2world(PIXELS, 0))
    received = pickle.loads(pickle.dumps(wcs))
    assert type(received) is ExactWCS and _same_parameters(received, wcs)
    assert received.__reduce__() == wcs.__reduce__()  # the same pickle again, bit for bit
    assert received.to_header_string(relax=True) == wcs.to_header_string(relax=True)
    assert received.pixel_shape == raw.pixel_shape
    assert np.array_equal(received.all_pix2world(PIXELS, 0), wcs.all_pix2world(PIXELS, 0))
    assert _same_parameters(canonical_wcs(wcs), wcs)  # idempotent


def test_astropy_alone_loses_the_last_digits():
    """What ExactWCS is for: a plain astropy WCS comes back from a pickle rounded."""
    raw = tan_sip_wcs()
    received = pickle.loads(pickle.dumps(raw))
    assert received.wcs.crval[0] != raw.wcs.crval[0]
    assert not np.array_equal(received.all_pix2world(PIXELS, 0), raw.all_pix2world(PIXELS, 0))


def test_a_real_worker_process_computes_the_same_bits():
    """Tract, TAN-SIP and TPV WCSs through a ProcessPoolExecutor: the same sky positions
    and pixels (==), and the WCS it sends back is the one sent."""
    wcss = [canonical_wcs(make()) for make in WCS_MAKERS.values()]
    wcss.append(tract_wcs().slice((slice(14_000, 16_000), slice(100, 4200))))
    with ProcessPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(_evaluate, wcss))
    for wcs, (sky, pixels, back) in zip(wcss, results, strict=True):
        here_sky, here_pixels, _ = _evaluate(wcs)
        assert (sky == here_sky).all() and (pixels == here_pixels).all()
        assert type(back) is ExactWCS and _same_parameters(back, wcs)


@pytest.mark.parametrize("name", list(WCS_MAKERS))
def test_astropy_operations_keep_an_exact_wcs(name):
    wcs = canonical_wcs(WCS_MAKERS[name]())
    derived = {
        "copy": copy.copy(wcs),
        "deepcopy": copy.deepcopy(wcs),
        "method deepcopy": wcs.deepcopy(),
        "celestial": wcs.celestial,
        "sub": wcs.sub([1, 2]),
        "slice": wcs[10:20, 5:15],
        "strided slice": wcs[10:400:3, 5:15],
        "shifted": shifted_wcs(wcs, 812, 1999),
    }
    for what, other in derived.items():
        assert isinstance(other, ExactWCS), what
        received = pickle.loads(pickle.dumps(other))
        assert _same_parameters(received, other), what
        assert np.array_equal(received.all_pix2world(PIXELS, 0), other.all_pix2world(PIXELS, 0))
    # the unsliced copies are the WCS itself; the slice starts 5 px right, 10 px up
    for what in ("copy", "deepcopy", "method deepcopy", "celestial", "sub"):
        assert _same_parameters(derived[what], wcs), what
    assert np.array_equal(
        derived["slice"].all_pix2world(PIXELS, 0), wcs.all_pix2world(PIXELS + [5.0, 10.0], 0)
    )
    header = wcs.to_header(relax=True)
    assert header["CRVAL1"] == pytest.approx(wcs.wcs.crval[0], rel=1e-13)
    sky = wcs.pixel_to_world(PIXELS[:5, 0], PIXELS[:5, 1])
    np.testing.assert_array_equal(sky.spherical.lon.deg, wcs.all_pix2world(PIXELS[:5], 0)[:, 0])


def test_a_wcs_read_back_from_a_record_is_the_written_one():
    """Our files store the header cards (14 digits) and the exact parameters: the WCS
    read back is an ExactWCS equal to the written one, and a worker gets it exactly."""
    for make in (tract_wcs, tan_sip_wcs):
        wcs = canonical_wcs(make())
        back = wcs_from_record(json.loads(json.dumps(wcs_to_record(wcs))))
        assert isinstance(back, ExactWCS) and _same_parameters(back, wcs)
        # the same pickled header text (the record does not keep the image size, NAXISi)
        assert back.__reduce__()[1][1]["header"] == wcs.__reduce__()[1][1]["header"]
        assert pickle.loads(pickle.dumps(back)).__reduce__() == back.__reduce__()
        assert np.array_equal(back.all_pix2world(PIXELS, 0), wcs.all_pix2world(PIXELS, 0))


def test_lookup_table_distortions_pickle_as_astropy_does_with_exact_parameters():
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [1.0 / 3.0, 2.0 / 7.0]
    wcs.wcs.crpix = [100.0 / 7.0, 300.0 / 11.0]
    wcs.wcs.cdelt = [-1e-4 / 3.0, 1e-4 / 7.0]
    wcs.wcs.set()
    table = RNG.normal(0.0, 0.1, (5, 5)).astype(np.float32)
    wcs.cpdis1 = DistortionLookupTable(table, (1.0, 1.0), (0.0, 0.0), (50.0, 50.0))
    wcs.cpdis2 = DistortionLookupTable(-table, (1.0, 1.0), (0.0, 0.0), (50.0, 50.0))
    exact = canonical_wcs(wcs)
    received = pickle.loads(pickle.dumps(exact))
    assert received.cpdis1 is not None and _same_parameters(received, wcs)
    assert np.array_equal(received.all_pix2world(PIXELS, 0), wcs.all_pix2world(PIXELS, 0))


@pytest.mark.parametrize("name", ["patch.fits", "patch.h5"])
def test_a_cell_wcs_read_back_from_a_coadd_file_is_the_written_one(tmp_path, monkeypatch, name):
    """Cells on a tract with 17-digit parameters (not 14-digit ones): written to our
    FITS and HDF5 formats and read back, each cell's WCS is an ExactWCS with the written
    parameters, bit for bit, and a worker receives it unchanged."""
    import coadd_factory

    from cellcoadd.io import api

    center = (150.12345678901234, -2.9876543210987654)
    tract = SkyMap.from_centers([center], coadd_factory.SMALL)[0]
    monkeypatch.setattr(coadd_factory, "tract_wcs", lambda config, center: tract.wcs)
    original = coadd_factory.make_patch(seed=3)
    api.write(original, tmp_path / name)
    read = api.read(tmp_path / name)
    for index, cell in original.cells.items():
        back = read[index].wcs
        assert back.wcs.crval[0] == center[0] != float(f"{center[0]:.14g}")
        assert isinstance(back, ExactWCS) and _same_parameters(back, cell.wcs), index
        received = pickle.loads(pickle.dumps(back))
        assert received.__reduce__() == back.__reduce__(), index
        assert np.array_equal(received.all_pix2world(PIXELS, 0), cell.wcs.all_pix2world(PIXELS, 0))
