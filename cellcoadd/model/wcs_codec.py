"""The one exact codec of a celestial astropy WCS in files (JSON records and FITS keywords).

FITS header cards print floating-point values with ~14 significant digits, so a WCS
written only as a header does not come back bit for bit. :func:`wcs_to_record` stores the
header cards *and* the numerical parameters at full double precision
(:func:`~cellcoadd.geometry.exact_wcs.wcs_exact_parameters`, whose home is the geometry
layer, beside the WCS that pickles with them); :func:`wcs_from_record` rebuilds the WCS
exactly, as an :class:`~cellcoadd.geometry.exact_wcs.ExactWCS`.
:func:`wcs_exact_keywords` / :func:`apply_wcs_exact_keywords` carry the same exact values
keyed by FITS keyword, for files whose WCS lives in a header
(:mod:`cellcoadd.io._fits.wcs_header`). Lookup-table distortions (CPDIS/DET2IM) are refused.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning

from cellcoadd.errors import CellCoaddValueError
from cellcoadd.geometry.exact_wcs import (
    SIP_NAMES,
    ExactWCS,
    apply_wcs_exact_parameters,
    wcs_exact_parameters,
)


def wcs_header(wcs: WCS) -> fits.Header:
    """``wcs.to_header(relax=True)`` (SIP included) without astropy's fix-up warnings.

    Floating-point values there are rounded when printed as FITS cards; the exact values
    are :func:`wcs_exact_parameters`.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        return wcs.to_header(relax=True)


def wcs_exact_keywords(wcs: WCS) -> dict[str, float]:
    """:func:`wcs_exact_parameters` keyed by the FITS keywords they are rounded in.

    ``LONPOLE``, ``LATPOLE``, then ``CRPIXi``, ``CRVALi``, ``CDELTi``, ``PCi_j`` for each
    axis ``i``, then the non-zero SIP coefficients ``A_p_q``, ``B_p_q``, ``AP_p_q``,
    ``BP_p_q`` (PV values are not included). :func:`apply_wcs_exact_keywords` sets them back.
    """
    exact = wcs_exact_parameters(wcs)
    values: dict[str, float] = {"LONPOLE": exact["lonpole"], "LATPOLE": exact["latpole"]}
    for i in range(2):
        values[f"CRPIX{i + 1}"] = exact["crpix"][i]
        values[f"CRVAL{i + 1}"] = exact["crval"][i]
        values[f"CDELT{i + 1}"] = exact["cdelt"][i]
        for j in range(2):
            values[f"PC{i + 1}_{j + 1}"] = exact["pc"][i][j]
    for _, prefix, coeffs in _sip_items(exact):
        for p, q in zip(*np.nonzero(coeffs), strict=True):
            values[f"{prefix}_{p}_{q}"] = float(coeffs[p, q])
    return values


def apply_wcs_exact_keywords(wcs: WCS, values: dict[str, float]) -> None:
    """Set the exact values of :func:`wcs_exact_keywords` on ``wcs`` parsed from the rounded
    header (in place); parameters without a value in ``values`` are kept, and so are SIP
    coefficients that are zero in ``wcs``.
    """
    exact = wcs_exact_parameters(wcs)
    exact["lonpole"] = values.get("LONPOLE", exact["lonpole"])
    exact["latpole"] = values.get("LATPOLE", exact["latpole"])
    for i in range(2):
        exact["crpix"][i] = values.get(f"CRPIX{i + 1}", exact["crpix"][i])
        exact["crval"][i] = values.get(f"CRVAL{i + 1}", exact["crval"][i])
        exact["cdelt"][i] = values.get(f"CDELT{i + 1}", exact["cdelt"][i])
        for j in range(2):
            exact["pc"][i][j] = values.get(f"PC{i + 1}_{j + 1}", exact["pc"][i][j])
    exact["pv"] = []  # PV values are not in the keyword form: keep the parsed ones
    for name, prefix, coeffs in _sip_items(exact):
        for p, q in zip(*np.nonzero(coeffs), strict=True):
            coeffs[p, q] = values.get(f"{prefix}_{p}_{q}", coeffs[p, q])
        exact["sip"][name] = coeffs
    apply_wcs_exact_parameters(wcs, exact)


def wcs_to_record(
    wcs: WCS, *, card_values: dict[str, tuple[str, Any]] | None = None
) -> dict[str, Any]:
    """A JSON-able description of a celestial WCS from which :func:`wcs_from_record` rebuilds
    it exactly.

    ``card_values``, optional, remembers ``(keyword, value)`` by the text of each header
    card across calls (parsing card values is most of the cost; the same text always gives
    the same value).

    ``header`` holds the ``(keyword, value)`` cards of :func:`wcs_header`; because FITS
    cards print only ~14 significant digits, ``exact`` repeats the numerical parameters
    (:func:`wcs_exact_parameters`) at full double precision. Lookup-table distortions are
    not representable and are refused.
    """
    if (
        wcs.cpdis1 is not None
        or wcs.cpdis2 is not None
        or wcs.det2im1 is not None
        or (wcs.det2im2 is not None)
    ):
        raise CellCoaddValueError("WCS lookup-table distortions (CPDIS/DET2IM) cannot be stored")
    exact = wcs_exact_parameters(wcs)
    if card_values is not None:
        fast = _wcslib_cards(wcs, card_values)
        if fast is not None:
            return {"header": fast, "exact": exact}
    header = wcs_header(wcs)
    if card_values is None:
        return {"header": [[card.keyword, card.value] for card in header.cards], "exact": exact}
    cards = []
    for card in header.cards:
        image = getattr(card, "_image", None)  # the card's text as wcslib printed it
        if not isinstance(image, str) or getattr(card, "_modified", True):
            cards.append([card.keyword, card.value])
            continue
        parsed = card_values.get(image)
        if parsed is None:
            parsed = card_values[image] = (card.keyword, card.value)
        cards.append(list(parsed))
    return {"header": cards, "exact": exact}


#: The ``relax`` flags ``WCS.to_header(relax=True)`` gives wcslib (all extensions, 14 digits).
_TO_HEADER_FLAGS = 0xFF | 0x4000  # WCSHDO_all | WCSHDO_P14
#: Keywords ``WCS.to_header`` removes from wcslib's header.
_DROPPED_KEYWORDS = frozenset(("", "COMMENT"))


def _wcslib_cards(wcs: WCS, card_values: dict[str, tuple[str, Any]]) -> list[list[Any]] | None:
    """The ``[keyword, value]`` cards of :func:`wcs_header` for a WCS without SIP, from
    wcslib's header text, each distinct card parsed once (``card_values``, by its text).

    Without SIP, ``WCS.to_header(relax=True)`` is wcslib's header (``relax`` = all
    extensions, 14 digits) parsed by astropy, without its blank and COMMENT cards; parsing
    that header again for every cell cost more than the rest of describing its WCS.
    None (use :func:`wcs_header`) for a WCS with SIP, which astropy edits further.
    """
    if wcs.sip is not None or wcs.wcs is None:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        text = wcs.wcs.to_header(_TO_HEADER_FLAGS)
    cards: list[list[Any]] = []
    for start in range(0, len(text), 80):
        image = text[start : start + 80]
        parsed = card_values.get(image)
        if parsed is None:
            if image.rstrip() == "END":
                break
            card = fits.Card.fromstring(image)
            parsed = card_values[image] = (card.keyword, card.value)
        if parsed[0] not in _DROPPED_KEYWORDS:
            cards.append(list(parsed))
    return cards


def wcs_from_record(record: dict[str, Any]) -> ExactWCS:
    """Rebuild the WCS described by :func:`wcs_to_record` (bit-exact parameters), in
    canonical form (:func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`): it pickles
    exactly."""
    header = fits.Header([(str(key), value) for key, value in record["header"]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        wcs = ExactWCS(header, relax=True)
    apply_wcs_exact_parameters(wcs, record["exact"])
    return wcs


def _sip_items(exact: dict[str, Any]) -> Iterator[tuple[str, str, np.ndarray]]:
    """``(name, keyword prefix, float64 copy)`` of each SIP matrix present in ``exact``."""
    sip = exact["sip"]
    if sip is None:
        return
    for name in SIP_NAMES:
        if sip[name] is not None:
            yield name, name.upper(), np.array(sip[name], dtype=float)
