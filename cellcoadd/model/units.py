"""Pixel units of a coadd: nJy, or counts at a stated AB zero point.

A coadd's image, noise and variance planes are in one of two units, chosen by
:attr:`cellcoadd.model.build_config.BuildConfig.units`:

``"nJy"``
    Flux density per coadd pixel in nanojansky: counts at the AB zero point
    :data:`NJY_ZERO_POINT` ``= 2.5 log10(3631e9) = 31.4``, i.e. a source of AB magnitude
    ``m`` has a total of ``10**(-0.4 (m - 31.4))`` nJy. The default of new builds (as in
    Rubin's coadds).
``"count"``
    Counts at the zero point stated with them (``zero_point``, AB mag): a source of
    magnitude ``m`` sums to ``10**(-0.4 (m - zero_point))``.

Both are stored as astropy-parsable unit strings (``astropy.units.Unit("nJy")``,
``Unit("count")``), never as a scaled unit such as ``"3.63078 nJy"`` (readers such as
lsst-images refuse rounded scale factors): the zero point of counts travels as its own
number (FITS ``MAGZERO``). Variances are in the unit squared (``"nJy2"``, ``"count2"``,
FITS unit syntax). Files of format 1.0 and 1.1 held free text such as
``"counts at zero point 30 per coadd pixel"``; :func:`legacy_units` maps it.
"""

from __future__ import annotations

import math
import re
from typing import Any, Literal

from cellcoadd.errors import CellCoaddIncompatibleValuesError, CellCoaddValueError

#: AB magnitude of 1 nJy: ``-2.5 log10(1e-9 / 3631) = 2.5 log10(3631e9) = 31.4`` (31.40006).
NJY_ZERO_POINT = 2.5 * math.log10(3631.0e9)

#: The units a coadd can be in (astropy unit strings).
PixelUnit = Literal["nJy", "count"]
PIXEL_UNITS: tuple[str, ...] = ("nJy", "count")

#: Accepted spellings of the units (the values are the stored forms).
UNIT_ALIASES: dict[str, str] = {
    "njy": "nJy",
    "nanojansky": "nJy",
    "count": "count",
    "counts": "count",
    "ct": "count",
}

#: Zero points closer than this (mag) to :data:`NJY_ZERO_POINT` are taken as it.
NJY_ZERO_POINT_TOLERANCE = 1e-6

_FITS_NAME = re.compile(r"^[A-Z0-9_]+$")

_LEGACY_COUNTS = re.compile(
    r"^\s*counts?\s+at\s+(?:the\s+)?zero\s*point\s+([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\b",
    re.IGNORECASE,
)


def normalise_unit(text: object) -> str | None:
    """The stored form (``"nJy"`` or ``"count"``) of a unit spelling, None if unknown."""
    if not isinstance(text, str):
        return None
    return UNIT_ALIASES.get(text.strip().lower())


def legacy_units(text: str) -> tuple[str, float | None] | None:
    """``(unit, zero_point)`` of a free-text units string of format 1.0/1.1 files.

    ``"counts at zero point 30 per coadd pixel"`` (what builds wrote) gives
    ``("count", 30.0)``; ``"nJy"`` gives ``("nJy", NJY_ZERO_POINT)``; ``"count"`` gives
    ``("count", None)`` (the zero point must come from elsewhere). Anything else: None.
    """
    unit = normalise_unit(text)
    if unit == "nJy":
        return unit, NJY_ZERO_POINT
    if unit == "count":
        return unit, None
    match = _LEGACY_COUNTS.match(text)
    if match is not None:
        return "count", float(match.group(1))
    return None


def zero_point_of(unit: str, zero_point: float | None) -> float:
    """The AB zero point of pixels in ``unit``: 31.4 for nJy, ``zero_point`` for counts."""
    if unit == "nJy":
        return NJY_ZERO_POINT
    if zero_point is None:
        raise CellCoaddValueError("counts need a zero point")
    return zero_point


def is_njy_zero_point(zero_point: float) -> bool:
    """Whether ``zero_point`` is :data:`NJY_ZERO_POINT` (within the tolerance)."""
    return abs(zero_point - NJY_ZERO_POINT) <= NJY_ZERO_POINT_TOLERANCE


def variance_unit(unit: str) -> str:
    """The unit of a variance of pixels in ``unit``, FITS syntax: ``"nJy2"``, ``"count2"``."""
    return f"{unit}2"


def unit_cards_by_kind(unit: str, zero_point: float) -> dict[str, list[tuple[str, object, str]]]:
    """Unit keywords of the planes by unit kind (:data:`~cellcoadd.model.planes.UnitKind`)
    that has one, as ``(name, value, comment)``.

    ``"flux"`` (``image``, ``noise``): ``BUNIT`` (plus ``MAGZERO`` for counts);
    ``"flux_squared"`` (``variance``): ``BUNIT`` of the unit squared (plus ``MAGZERO``).
    Used for FITS header cards and HDF5 attributes alike.
    """
    magzero: list[tuple[str, object, str]] = []
    if unit != "nJy":
        magzero = [("MAGZERO", float(zero_point), "[mag] AB zero point of the pixel values")]
    flux = [("BUNIT", unit, "pixel unit"), *magzero]
    return {
        "flux": flux,
        "flux_squared": [("BUNIT", variance_unit(unit), "pixel unit (variance)"), *magzero],
    }


def mask_plane_cards(bits: dict[str, int]) -> list[tuple[str, object, str]]:
    """``MP_<NAME> = bit`` keywords of a mask plane (the LSST/afw convention), by bit.

    Names that are not upper-case ASCII (letters, digits, ``_``) are left out: FITS
    keywords cannot hold them (the metadata JSON names every bit).
    """
    return [
        (f"MP_{name}", bit, "mask plane bit")
        for name, bit in sorted(bits.items(), key=lambda item: item[1])
        if _FITS_NAME.match(name)
    ]


def flux_scale(from_zero_point: float, to_zero_point: float) -> float:
    """Factor taking counts at ``from_zero_point`` to counts at ``to_zero_point``."""
    return float(10.0 ** (0.4 * (to_zero_point - from_zero_point)))


__all__ = [
    "NJY_ZERO_POINT",
    "PIXEL_UNITS",
    "PixelUnit",
    "flux_scale",
    "is_njy_zero_point",
    "legacy_units",
    "mask_plane_cards",
    "normalise_unit",
    "unit_cards_by_kind",
    "variance_unit",
    "zero_point_of",
]


def check_units(units: str, zero_point: float, zero_point_given: bool) -> None:
    """Refuse a unit and zero point that contradict each other.

    Raises
    ------
    ValueError
        For nJy at another zero point than :data:`NJY_ZERO_POINT`, or counts without a
        stated zero point.
    """
    if units == "nJy" and zero_point != NJY_ZERO_POINT:
        raise CellCoaddIncompatibleValuesError(
            f"units 'nJy' mean the AB zero point {NJY_ZERO_POINT:.5f}, not "
            f"{zero_point}; use units 'count' for counts at another zero point",
            values={"units": units, "zero_point": zero_point},
        )
    if units == "count" and not zero_point_given:
        raise CellCoaddValueError("units 'count' need a zero_point (mag)", value=units)


def stored_units(
    data: dict[str, Any], *, before_units: bool, build_zero_point: float | None
) -> dict[str, Any]:
    """Patch metadata (as read) with ``units`` in stored form and its ``zero_point``.

    Parameters
    ----------
    data : dict
        The metadata fields; ``units`` may be a spelling or, in files of format 1.0 and
        1.1 (``before_units``), free text (:func:`legacy_units`; unknown text there is
        counts at the build's zero point).
    before_units : bool
        Whether the metadata predate unit strings.
    build_zero_point : float, optional
        The zero point the build configuration states (exact, where the free text of old
        files is rounded).
    """
    text = data.get("units")
    unit = normalise_unit(text)
    stated: float | None = None
    if unit is None and isinstance(text, str):
        legacy = legacy_units(text)
        if legacy is None and before_units:
            legacy = ("count", None)
        if legacy is not None:
            unit, stated = legacy
    if unit is None:
        return data  # refused by the field's validation
    data = {**data, "units": unit}
    zero_point = data.get("zero_point")
    if unit == "nJy":
        if zero_point is None or (
            isinstance(zero_point, (int, float)) and is_njy_zero_point(float(zero_point))
        ):
            data["zero_point"] = NJY_ZERO_POINT
    elif zero_point is None:
        if stated is not None and build_zero_point is not None:
            if abs(stated - build_zero_point) < 1e-3:
                stated = build_zero_point  # the text is rounded (%g); the config is exact
        zero_point = stated if stated is not None else build_zero_point
        if zero_point is not None:
            data["zero_point"] = zero_point
    return data
