"""Exact round trip of an astropy WCS through a FITS header (exposure files).

cfitsio writes floating-point header values with 15 significant digits, which is not
enough to round-trip float64 (nor a WCS to 1e-9 pixel). The writer therefore returns,
next to the header cards, the exact float64 values of every floating-point WCS keyword
(:func:`~cellcoadd.model.wcs_codec.wcs_exact_keywords`: CRPIXi, CRVALi, CDELTi, PCi_j,
LONPOLE, LATPOLE and the SIP coefficients ``A_p_q``, ``B_p_q``, ``AP_p_q``, ``BP_p_q``),
stored by the caller elsewhere (JSON). The reader parses the header, checks each rounded
value against its exact one (relative tolerance :data:`HEADER_RTOL`) and sets the exact
values on the parsed WCS. The exact encoding itself is the model's WCS codec
(:mod:`cellcoadd.model.wcs_codec`); this module only adds the FITS header around it.
"""

from __future__ import annotations

import re
import warnings
from typing import Any

import fitsio
from astropy.io import fits
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddFormatError
from cellcoadd.model.wcs_codec import apply_wcs_exact_keywords, wcs_exact_keywords, wcs_header

#: Relative agreement required between a header float (15 digits) and its exact value.
HEADER_RTOL = 1e-13
#: Keywords that can take part in an image's celestial WCS: wcslib's (any alternate
#: letter), SIP, distortion tables, and the dates and observatory position wcslib's fixes
#: read. astropy verifies every card it is given (~20 us each: 6 ms for a DECam CCD's 255
#: cards), so the others are left out; the WCS is the same
#: (tested on DES TPV, LSST SIP and cellcoadd's exposure files).
WCS_KEYWORD = re.compile(
    r"(WCSAXES|WCSNAME|(CTYPE|CUNIT|CRPIX|CRVAL|CDELT|CROTA|CRDER|CSYER|CNAME)\d+"
    r"|(CD|PC|PV|PS)\d+_\d+|LONPOLE|LATPOLE|RADESYS|EQUINOX)[A-Z]?"
    r"|RADECSYS|EPOCH|(A|B|AP|BP)_(ORDER|DMAX|\d+_\d+)|(CPDIS|CPERR|DP|DQ)\d+|D2IM\w*|AXISCORR"
    r"|(MJD|DATE)-(OBS|AVG|BEG|END)|MJDREF[IF]?|DATEREF|TIMESYS|TIMEUNIT|OBSGEO-[XYZLBH]"
    r"|OBS-(LAT|LONG|ELEV)|RESTFRQ|RESTWAV|SPECSYS|SSYSOBS|VELOSYS|ZSOURCE|VELANGL"
)


def _fail(problem: str) -> CellCoaddFormatError:
    # the caller (read_exposure) fills in the path
    return CellCoaddFormatError("", problem)


def as_float(value: Any, what: str) -> float:
    """``value`` as a float; CellCoaddFormatError (naming ``what``) unless it is a number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(f"{what} must be a number")
    return float(value)


def same_float(header_value: Any, exact: float) -> bool:
    """Whether a header value is the number ``exact`` to :data:`HEADER_RTOL`."""
    if isinstance(header_value, bool) or not isinstance(header_value, (int, float)):
        return False
    return abs(float(header_value) - exact) <= HEADER_RTOL * max(1.0, abs(exact))


def wcs_cards(wcs: WCS) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """fitsio header cards of ``wcs`` and the exact values of its floating-point keywords.

    Returns
    -------
    cards : list of dict
        ``{"name", "value", "comment"}`` records of ``wcs.to_header(relax=True)`` (SIP
        included), floating-point values at full precision (cfitsio rounds them).
    exact : dict of str to float
        The float64 value of every floating-point keyword present in the header.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        header = wcs_header(wcs)
    exact = wcs_exact_keywords(wcs)
    cards = []
    for card in header.cards:
        value = card.value
        if card.keyword in exact:
            value = exact[card.keyword]
        cards.append({"name": card.keyword, "value": value, "comment": card.comment})
    exact = {k: v for k, v in exact.items() if k in header}
    return cards, exact


def read_wcs(header: fitsio.FITSHDR, exact: dict[str, Any]) -> WCS:
    """The celestial WCS of ``header`` with the ``exact`` values of :func:`wcs_cards`.

    Raises
    ------
    CellCoaddFormatError
        (without a path) when a header value disagrees with its exact value, an exact
        value is not a number, or the header holds no celestial WCS.
    """
    names = [str(record.get("name") or "").upper() for record in header.records()]
    text = "\n".join(
        record["card_string"]
        for record, name in zip(header.records(), names, strict=True)
        if WCS_KEYWORD.fullmatch(name) or name.startswith("NAXIS")
    )
    values = {key: as_float(value, f"WCS value {key}") for key, value in exact.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        astropy_header = fits.Header.fromstring(text, sep="\n")
        for key, value in values.items():
            if key not in astropy_header or not same_float(astropy_header[key], value):
                raise _fail(f"WCS keyword {key} disagrees with its exact value in META")
        wcs = WCS(astropy_header, naxis=2)
    if not wcs.has_celestial:
        raise _fail("the IMAGE header holds no celestial WCS")
    # astropy re-renders header floats with at most 20 characters when it builds the WCS,
    # so the exact values are set on the parsed WCS itself
    apply_wcs_exact_keywords(wcs, values)
    return wcs
