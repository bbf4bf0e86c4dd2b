"""Layouts of single-epoch multi-extension FITS exposure files (LSST, DES, your own).

A :class:`MefLayout` says where a survey's exposure file keeps each thing cellcoadd needs:
the HDUs of the image, the mask and the variance (or the inverse-variance weight), the
names of the mask bits, the header keywords of the zero point, the identity and the band,
and whether the image is already background subtracted. It is pure description (no I/O);
:class:`cellcoadd.io.exposures.survey_readers.MefExposureFile` reads files with it.

Two layouts are provided:

``LSST_LAYOUT``
    The single-detector ``ExposureF`` files written by the LSST Science Pipelines (afw;
    ``calexp``, ``visit_image``): an empty primary HDU holding the metadata, then the
    ``IMAGE``, ``MASK`` and ``VARIANCE`` HDUs (``EXTNAME`` and ``EXTTYPE``), each with the
    TAN-SIP WCS; mask planes named by ``MP_<NAME> = bit`` keywords of the mask header;
    identity from the Butler's ``LSST BUTLER DATAID VISIT/DETECTOR/BAND`` keywords;
    calibration from ``FLUXMAG0`` (older ``calexp``), the ``PhotoCalib`` of the afw archive
    (``PHOTOCALIB_ID``; current files) or ``BUNIT = 'nJy'`` (``visit_image``).
    The PSF (an afw archive HDU) and the exact WCS (an AST archive; the header's TAN-SIP is
    an approximation) are not readable without the pipelines: give the PSF separately.
``DES_LAYOUT``
    The DES single-epoch (``finalcut``/``immasked``) files: ``SCI``, ``MSK``, ``WGT`` HDUs,
    often tile-compressed (``.fits.fz``), TPV WCS in the ``SCI`` header, DESDM ``BADPIX_*``
    mask bits, ``EXPNUM``/``CCDNUM``/``BAND`` (or the ``FILTER`` keyword's first word),
    ``MAGZERO``/``MAGZP`` when present. The image is sky subtracted; a ``_bkg.fits.fz``
    background file, when given, is subtracted too (as pizza-cutter does).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, field_validator, model_validator

from cellcoadd.errors import (
    CellCoaddIncompatibleValuesError,
    CellCoaddRangeError,
    CellCoaddValueError,
)
from cellcoadd.model.mask_presets import DES_BAD_MASK_BITS, LSST_BAD_MASK_BITS
from cellcoadd.model.units import NJY_ZERO_POINT  # AB magnitude of 1 nJy (31.4)

#: HDU given by EXTNAME (or EXTTYPE; case-insensitive) or by number (0 = primary).
HduRef = str | int

ZeroPointKind = Literal["mag", "fluxmag0", "bunit", "photocalib"]

__all__ = [
    "DES_BAD_MASK_BITS",
    "DES_LAYOUT",
    "DES_MASK_VALUES",
    "LSST_BAD_MASK_BITS",
    "LSST_LAYOUT",
    "MefLayout",
    "ZeroPointKey",
    "bits_from_values",
    "zero_point_from",
]


class ZeroPointKey(BaseModel):
    """One header keyword that can give the zero point, and how to read it.

    ``kind``: ``"mag"`` (the value is the zero point, e.g. ``MAGZERO``), ``"fluxmag0"``
    (counts of a magnitude-0 source: zero point ``2.5 log10(value)``) or ``"bunit"`` (the
    pixel unit; ``'nJy'`` means zero point 31.4, any other unit gives nothing) or
    ``"photocalib"`` (the keyword is the id of a ``PhotoCalib`` in the file's afw archive,
    :mod:`cellcoadd.io.exposures.lsst_photocalib`; read by the file reader).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    keyword: str
    kind: ZeroPointKind = "mag"


def zero_point_from(kind: ZeroPointKind, value: object) -> float | None:
    """The zero point a header value gives, or None when it gives none (always for
    ``"photocalib"``, which needs the file).

    Examples
    --------
    >>> zero_point_from("mag", 30.25)  # MAGZERO
    30.25
    >>> round(zero_point_from("fluxmag0", 10 ** (0.4 * 28.7)), 9)  # FLUXMAG0
    28.7
    >>> zero_point_from("bunit", "nJy") == NJY_ZERO_POINT, zero_point_from("bunit", "adu")
    (True, None)
    """
    if kind == "photocalib":
        return None
    if kind == "bunit":
        if isinstance(value, str) and value.strip().lower() == "njy":
            return NJY_ZERO_POINT
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    number = float(value)
    if not math.isfinite(number):
        return None
    if kind == "fluxmag0":
        return 2.5 * math.log10(number) if number > 0 else None
    return number


class MefLayout(BaseModel):
    """Where a multi-extension FITS exposure file keeps what cellcoadd needs.

    Parameters
    ----------
    name : str
        A label for messages.
    image_hdu, mask_hdu : str or int
        HDU of the image and of the integer bit mask (EXTNAME, else EXTTYPE, or number).
    variance_hdu, weight_hdu : str or int, optional
        Exactly one: the variance plane, or an inverse-variance weight (variance =
        1 / weight; pixels of weight <= 0 get the mask bit ``zero_weight_bit``).
    zero_weight_bit : str
        Name of the mask bit set where the weight is not positive (with ``weight_hdu``).
    mask_bits : dict of str to int, optional
        Bit *numbers* of the mask's named bits; None: read from the ``MP_<NAME>``
        keywords of the mask header (LSST style).
    zero_point_keys : tuple of ZeroPointKey
        Keywords tried in order, in the primary header then the image header; the first
        that gives a zero point wins. None found: the reader's ``zero_point`` argument.
    visit_keys, detector_keys, band_keys : tuple of str
        Keywords tried in order (primary, then image header).
    filter_key : str, optional
        Fallback for the band: the first word of this keyword's value, cut at ``_``
        (``'r DECam SDSS c0002 6415.0 1480.0'`` -> ``r``, ``'r_57'`` -> ``r``).
    background_subtracted : bool
        Whether the image is background subtracted; if not, ``background_hdu`` or a
        background file given to the reader is subtracted (one of them is required).
    background_hdu : str or int, optional
        HDU of a background image in the exposure file itself.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "custom"
    image_hdu: HduRef
    mask_hdu: HduRef
    variance_hdu: HduRef | None = None
    weight_hdu: HduRef | None = None
    zero_weight_bit: str = "ZERO_WEIGHT"
    mask_bits: dict[str, int] | None = None
    zero_point_keys: tuple[ZeroPointKey, ...] = ()
    visit_keys: tuple[str, ...] = ("VISIT",)
    detector_keys: tuple[str, ...] = ("DETECTOR",)
    band_keys: tuple[str, ...] = ("BAND",)
    filter_key: str | None = "FILTER"
    background_subtracted: bool = True
    background_hdu: HduRef | None = None

    @field_validator("mask_bits")
    @classmethod
    def _check_bits(cls, bits: dict[str, int] | None) -> dict[str, int] | None:
        if bits is not None:
            for name, bit in bits.items():
                if not 0 <= bit <= 30:
                    raise CellCoaddRangeError(
                        f"mask bit {name!r} = {bit} is outside 0..30", value=bit, low=0, high=30
                    )
        return bits

    @model_validator(mode="after")
    def _check_planes(self) -> MefLayout:
        if (self.variance_hdu is None) == (self.weight_hdu is None):
            raise CellCoaddIncompatibleValuesError(
                "give exactly one of variance_hdu and weight_hdu",
                values={"variance_hdu": self.variance_hdu, "weight_hdu": self.weight_hdu},
            )
        if self.weight_hdu is not None and self.mask_bits is not None:
            if self.zero_weight_bit in self.mask_bits:
                raise CellCoaddValueError(
                    f"zero_weight_bit {self.zero_weight_bit!r} is a file bit",
                    value=self.zero_weight_bit,
                )
        return self


def bits_from_values(values: dict[str, int]) -> dict[str, int]:
    """Bit numbers of a ``{name: 2**bit}`` table (as C headers define them)."""
    out = {}
    for name, value in values.items():
        if value <= 0 or value & (value - 1):
            raise CellCoaddValueError(
                f"mask value {name} = {value} is not a power of two", value=value
            )
        out[name] = value.bit_length() - 1
    return out


#: DESDM bad-pixel bits of the ``MSK`` HDU (despyfits/imsupport ``mask_bits.h``).
DES_MASK_VALUES: dict[str, int] = {
    "BADPIX_BPM": 1,  # hot/dead pixel or column from the bad-pixel map
    "BADPIX_SATURATE": 2,
    "BADPIX_INTERP": 4,  # interpolated over
    "BADPIX_BADAMP": 8,  # bad amplifier
    "BADPIX_CRAY": 16,  # cosmic ray
    "BADPIX_STAR": 32,  # bright star
    "BADPIX_TRAIL": 64,  # bleed trail
    "BADPIX_EDGEBLEED": 128,
    "BADPIX_SSXTALK": 256,  # crosstalk from a super-saturated source
    "BADPIX_EDGE": 512,  # glowing CCD edges
    "BADPIX_STREAK": 1024,  # satellite or meteor streak
    "BADPIX_SUSPECT": 2048,  # nominally useful but not perfect
    "BADPIX_FIXED": 4096,  # corrected by pixcorrect
    "BADPIX_NEAREDGE": 8192,
    "BADPIX_TAPEBUMP": 16384,
}

LSST_LAYOUT = MefLayout(
    name="lsst",
    image_hdu="IMAGE",
    mask_hdu="MASK",
    variance_hdu="VARIANCE",
    mask_bits=None,  # MP_<NAME> keywords
    zero_point_keys=(
        ZeroPointKey(keyword="FLUXMAG0", kind="fluxmag0"),
        ZeroPointKey(keyword="PHOTOCALIB_ID", kind="photocalib"),
        ZeroPointKey(keyword="BUNIT", kind="bunit"),
    ),
    visit_keys=("LSST BUTLER DATAID VISIT", "VISIT", "EXPID"),
    detector_keys=("LSST BUTLER DATAID DETECTOR", "DETECTOR", "CCDNUM"),
    band_keys=("LSST BUTLER DATAID BAND", "BAND"),
    filter_key="FILTER",
    background_subtracted=True,
)

DES_LAYOUT = MefLayout(
    name="des",
    image_hdu="SCI",
    mask_hdu="MSK",
    weight_hdu="WGT",
    zero_weight_bit="ZERO_WEIGHT",
    mask_bits=bits_from_values(DES_MASK_VALUES),
    zero_point_keys=(ZeroPointKey(keyword="MAGZERO"), ZeroPointKey(keyword="MAGZP")),
    visit_keys=("EXPNUM",),
    detector_keys=("CCDNUM",),
    band_keys=("BAND",),
    filter_key="FILTER",
    background_subtracted=True,  # immasked images are sky subtracted; _bkg is optional
)
