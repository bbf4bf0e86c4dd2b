"""Long headers parsed from their raw cards say what fitsio's read_header says."""

from __future__ import annotations

import gzip
import os
import shutil
import warnings
from pathlib import Path

import fitsio
import numpy as np
import pytest
from conftest import DES_HEADER
from test_survey_readers import PSF, des_planes, write_des, write_lsst

from cellcoadd.io._fits.headers import SHORT, RawHeader, read_header
from cellcoadd.io.exposures.mef_layout import DES_LAYOUT, LSST_LAYOUT
from cellcoadd.io.exposures.survey_readers import MefExposureFile


def _same_header(fast: fitsio.FITSHDR, slow: fitsio.FITSHDR) -> None:
    names = [r["name"] for r in slow.records()]
    assert [r["name"] for r in fast.records()] == names
    for name in names:
        if not name or name in ("COMMENT", "HISTORY"):  # blank cards have no name
            continue
        a, b = fast.get(name), slow.get(name)
        assert type(a) is type(b) and a == b, (name, a, b)
        assert fast[name] == slow[name]


def _check_every_hdu(path: Path) -> int:
    """Compare every HDU of ``path``; the number of headers read the fast way."""
    fast_ones = 0
    with fitsio.FITS(str(path)) as fits_file:
        descriptor = os.open(path, os.O_RDONLY)
        try:
            for hdu in fits_file:
                fast = read_header(hdu, descriptor)
                _same_header(fast, hdu.read_header())
                fast_ones += isinstance(fast, RawHeader)
        finally:
            os.close(descriptor)
    return fast_ones


@pytest.fixture(scope="module")
def survey_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("headers")
    files = [
        write_lsst(root / "visit_image.fits"),
        write_lsst(root / "v.fits.fz", compress="GZIP_2"),
    ]
    planes = des_planes()
    files.append(write_des(root / "D00154912_Y_c12_r1p1_immasked.fits", planes))
    files.append(
        write_des(root / "D00154912_Y_c12_r1p2_immasked.fits.fz", planes, compress="GZIP_2")
    )
    files.append(DES_HEADER)
    return files


def test_survey_headers_read_fast_say_the_same(survey_files):
    fast = sum(_check_every_hdu(path) for path in survey_files)
    assert fast >= 7  # the DES headers (255 cards) are long: read the fast way


def _long_header_file(path: Path, extra: list[dict]) -> Path:
    cards = [{"name": f"KEY{i:04d}", "value": i * 1.5, "comment": "a float"} for i in range(90)]
    cards += [
        {"name": "HIERARCH LSST BUTLER DATAID VISIT", "value": 2025061100123},
        {"name": "FLAG", "value": True},
        {"name": "BAND", "value": "r"},
        {"name": "EMPTY", "value": ""},
        *extra,
    ]
    with fitsio.FITS(str(path), "rw", clobber=True) as fits_file:
        fits_file.write(np.zeros((4, 4), np.float32), header=cards)
    return path


def test_a_long_header_with_hierarch_bools_and_blanks(tmp_path):
    path = _long_header_file(tmp_path / "long.fits", [])
    assert os.path.getsize(path) > SHORT
    assert _check_every_hdu(path) == 1


@pytest.mark.parametrize(
    "extra",
    [
        [{"name": "LONGSTR", "value": "x" * 150 + " end"}],  # CONTINUE cards: CFITSIO joins them
        [{"name": "QUOTED", "value": "it's"}],  # written 'it''s'
    ],
)
def test_cards_the_fast_parser_reads_otherwise_are_left_to_fitsio(tmp_path, extra):
    path = _long_header_file(tmp_path / "special.fits", extra)
    assert _check_every_hdu(path) == 0  # read by fitsio, and the same


def test_a_gzip_stream_is_read_by_cfitsio(survey_files, tmp_path):
    plain = survey_files[0]
    packed = tmp_path / "visit_image.fits.gz"
    with open(plain, "rb") as source, gzip.open(packed, "wb") as target:
        shutil.copyfileobj(source, target)
    a = MefExposureFile(plain, LSST_LAYOUT, PSF).header()
    b = MefExposureFile(packed, LSST_LAYOUT, PSF).header()
    assert (a.key, a.band, a.shape, a.zero_point) == (b.key, b.band, b.shape, b.zero_point)
    assert a.mask_bits.bits == b.mask_bits.bits
    assert a.wcs.to_header_string() == b.wcs.to_header_string()


def _all_cards_wcs(header: fitsio.FITSHDR, shape: tuple[int, int]):
    """The WCS astropy makes from every card of the image header (what was read before)."""
    from astropy.io import fits
    from astropy.wcs import WCS

    cards = []
    for record in header.records():
        name = str(record.get("name") or "").upper()
        if not name or name.startswith(("NAXIS", "Z", "XTENSION", "SIMPLE", "BITPIX", "EXTEND")):
            continue
        if name in ("PCOUNT", "GCOUNT", "TFIELDS", "COMMENT", "HISTORY"):
            continue
        cards.append(fits.Card.fromstring(record["card_string"]))
    out = fits.Header(cards)
    out["NAXIS"], out["NAXIS1"], out["NAXIS2"] = 2, shape[1], shape[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WCS(out)


def test_the_wcs_from_its_cards_alone_is_the_wcs_from_every_card(survey_files):
    """Only WCS keywords are handed to astropy (it verifies every card it gets): the
    canonical WCS is the same, parameters, FITS text and all, as from the whole header."""
    from cellcoadd.geometry.wcs_utils import canonical_wcs

    layouts = {"visit_image.fits": LSST_LAYOUT, "v.fits.fz": LSST_LAYOUT}
    checked = 0
    for path in survey_files:
        layout = layouts.get(path.name, DES_LAYOUT)
        if path.name.endswith("_header.fits"):
            continue  # a header without planes
        source = MefExposureFile(path, layout, PSF, zero_point=30.0)
        described = source.header().wcs
        with fitsio.FITS(str(path)) as fits_file:
            name = "IMAGE" if layout is LSST_LAYOUT else "SCI"
            hdu = fits_file[name]
            dims = tuple(int(d) for d in hdu.get_dims())
            reference = canonical_wcs(_all_cards_wcs(hdu.read_header(), dims))
        # the pickled state: header text, exact parameters and attributes
        assert described.__reduce__() == reference.__reduce__(), path.name
        checked += 1
    assert checked >= 2


def test_an_exposure_file_wcs_from_its_cards_alone_is_the_same(tmp_path):
    """cellcoadd's own exposure files: the WCS read from the WCS cards (and NAXIS) equals
    the one read from every card, bit for bit in canonical form, SIP and 17-digit values."""
    import dataclasses
    import json

    from astropy.io import fits
    from astropy.wcs import WCS
    from exposure_factory import make_exposure
    from test_exposure_io import sip_wcs

    from cellcoadd.geometry.wcs_utils import canonical_wcs
    from cellcoadd.io import write_exposure
    from cellcoadd.io._fits.wcs_header import read_wcs
    from cellcoadd.model.wcs_codec import apply_wcs_exact_keywords

    exposure = dataclasses.replace(make_exposure((359.1, -31.0), shape=(120, 140)), wcs=sip_wcs())
    path = write_exposure(exposure, tmp_path / "e.fits")
    with fitsio.FITS(str(path)) as fits_file:
        header = fits_file["IMAGE"].read_header()
        exact = json.loads(bytes(fits_file["META"].read()).decode())["wcs_exact"]
    text = "\n".join(r["card_string"] for r in header.records())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        every = WCS(fits.Header.fromstring(text, sep="\n"), naxis=2)
    apply_wcs_exact_keywords(every, {k: float(v) for k, v in exact.items()})
    a, b = canonical_wcs(read_wcs(header, exact)), canonical_wcs(every)
    assert len(header.records()) > 30  # identity, valid box, checksums... besides the WCS
    assert a.__reduce__() == b.__reduce__()  # header text, exact parameters, attributes


def test_damaged_survey_headers_are_read_or_refused_naming_the_file(survey_files, tmp_path):
    """Bytes changed anywhere in the headers (printable or not): the file is described and
    loaded, or refused with a CellCoaddFormatError naming it; nothing else escapes (a
    byte that is not ASCII used to escape from fitsio as a UnicodeDecodeError)."""
    import logging
    import random

    from cellcoadd.errors import CellCoaddFormatError
    from cellcoadd.geometry.box import Box

    box = Box(x_start=0, x_stop=40, y_start=0, y_stop=40)
    refused = 0
    for original in survey_files[:1] + [
        p for p in survey_files if p.name.endswith("p1_immasked.fits")
    ]:
        layout = DES_LAYOUT if "immasked" in original.name else LSST_LAYOUT
        raw = original.read_bytes()
        span = 23040 if layout is DES_LAYOUT else 20160
        rng = random.Random(7)
        for number in range(24):
            damaged = bytearray(raw)
            for _ in range(rng.randint(1, 6)):
                damaged[rng.randrange(span)] = (
                    rng.randrange(128, 256) if number % 3 == 0 else rng.randrange(32, 127)
                )
            path = tmp_path / f"{number}_{original.name}"
            path.write_bytes(bytes(damaged))
            source = MefExposureFile(path, layout, PSF, zero_point=30.0)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    logging.disable(logging.WARNING)
                    source.load_described(source.header(), box)
            except CellCoaddFormatError as err:
                assert path.name in str(err)
                refused += 1
            finally:
                logging.disable(logging.NOTSET)
            path.unlink()
    assert refused > 0
