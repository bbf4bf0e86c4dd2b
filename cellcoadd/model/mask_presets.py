"""Survey presets of ``BuildConfig.bad_mask_bits``: which named mask bits count as bad.

A preset is a name (``"des"``, ``"lsst"``) that a configuration file or
:meth:`~cellcoadd.model.build_config.BuildConfig.for_survey` can give instead of the list
of bit names. The names are those the survey readers define
(:mod:`cellcoadd.io.exposures.mef_layout`).
"""

from __future__ import annotations

from collections.abc import Iterable

#: Bits DES nulls in its weight maps (Y3 practice, as in pizza-cutter), saturation, and the
#: ``ZERO_WEIGHT`` bit the reader sets where the weight is not positive.
DES_BAD_MASK_BITS: tuple[str, ...] = (
    "BADPIX_BPM",
    "BADPIX_SATURATE",
    "BADPIX_BADAMP",
    "BADPIX_CRAY",
    "BADPIX_TRAIL",
    "BADPIX_EDGEBLEED",
    "BADPIX_SSXTALK",
    "BADPIX_EDGE",
    "BADPIX_STREAK",
    "ZERO_WEIGHT",
)

#: The LSST Science Pipelines' mask planes of unusable pixels (``NO_DATA``, as always).
LSST_BAD_MASK_BITS: tuple[str, ...] = ("BAD", "SAT", "CR", "EDGE", "NO_DATA")

#: preset name -> bad mask bits
MASK_PRESETS: dict[str, tuple[str, ...]] = {
    "des": DES_BAD_MASK_BITS,
    "lsst": LSST_BAD_MASK_BITS,
}


def fitting_presets(defined: Iterable[str]) -> list[str]:
    """The presets whose every bit is among the ``defined`` mask-bit names.

    >>> fitting_presets(["BAD", "SAT", "CR", "EDGE", "NO_DATA", "DETECTED"])
    ['lsst']
    >>> fitting_presets(["BAD"])
    []
    """
    names = set(defined)
    return [name for name, bits in MASK_PRESETS.items() if names.issuperset(bits)]
