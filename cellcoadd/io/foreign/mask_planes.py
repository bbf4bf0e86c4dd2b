"""Rubin's names for our mask planes, on export to Rubin's formats and back.

Rubin has two sets of names: ``lsst.afw.image.Mask`` names (``SAT``, ``CR``, ``INTRP``...),
which ``lsst.cell_coadds`` files list in ``MASKDEF``, and the names of the newer
lsst-images package (``SATURATED``, ``COSMIC_RAY``, ``INTERPOLATED``...), which it maps
from the afw ones (``lsst.images.get_legacy_*_mask_planes``). Our names are afw's, except
``EDGE``: ours marks the edge of an input detector, which Rubin's coadds call
``SENSOR_EDGE`` (afw's ``EDGE`` on a coadd, lsst-images' ``DETECTION_EDGE``, is the
detection-kernel edge of the image, a different thing).

Names outside the table are kept as they are, except on the way to lsst-images, which
renames some of Rubin's own afw planes (:data:`RUBIN_LSST_IMAGES`): a Rubin coadd's
``EDGE`` (kept under that name when the coadd also has ``SENSOR_EDGE``) is lsst-images'
``DETECTION_EDGE``. A name is renamed only when its new name is not already taken, so the
renaming can always be undone (``docs/format.md``, "Mask planes").
"""

from __future__ import annotations

from typing import Literal

__all__ = ["RUBIN_PLANES", "Flavour", "from_rubin", "rubin_description", "to_rubin"]

#: ``"afw"``: ``lsst.cell_coadds`` files; ``"lsst_images"``: lsst-images objects.
Flavour = Literal["afw", "lsst_images"]

#: Our name -> (afw name, lsst-images name, description of the plane in a cellcoadd coadd).
RUBIN_PLANES: dict[str, tuple[str, str, str]] = {
    "BAD": ("BAD", "BAD", "Detector defect in an input exposure (interpolated before coaddition)."),
    "SAT": ("SAT", "SATURATED", "Saturated in an input exposure (interpolated before coaddition)."),
    "CR": ("CR", "COSMIC_RAY", "Cosmic ray in an input exposure (interpolated before coaddition)."),
    "EDGE": ("SENSOR_EDGE", "SENSOR_EDGE", "Edge of an input exposure's detector."),
    "NO_DATA": ("NO_DATA", "NO_DATA", "No input data (empty cell, or outside the valid region)."),
    "INTRP": ("INTRP", "INTERPOLATED", "Interpolated over."),
    "SUSPECT": ("SUSPECT", "SUSPECT", "Near saturation or non-linear in an input exposure."),
    "STREAK": ("STREAK", "STREAK", "Satellite trail in an input exposure."),
}

#: Rubin's afw plane names that lsst-images renames (``lsst.images.get_legacy_*_mask_planes``)
#: and that are not ours: they come from a Rubin coadd read in. Afw name -> lsst-images name.
RUBIN_LSST_IMAGES: dict[str, str] = {
    "EDGE": "DETECTION_EDGE",
    "UNMASKEDNAN": "UNMASKED_NAN",
}

_COLUMN = {"afw": 0, "lsst_images": 1}


def _renamed(names: list[str], table: dict[str, str]) -> dict[str, str]:
    present = set(names)
    return {
        name: table.get(name, name) if table.get(name, name) not in present else name
        for name in names
    }


def _rename(bits: dict[str, int], table: dict[str, str]) -> dict[str, int]:
    renamed = _renamed(list(bits), table)
    return {renamed[name]: bit for name, bit in bits.items()}


def to_rubin(bits: dict[str, int], flavour: Flavour) -> dict[str, int]:
    """``bits`` (our name -> bit) with Rubin's names, bit numbers unchanged.

    For lsst-images, the names of Rubin's own planes that are left (a Rubin coadd's
    ``EDGE``, when our ``EDGE`` could not become ``SENSOR_EDGE``) then get lsst-images'
    names (:data:`RUBIN_LSST_IMAGES`); for afw, lsst-images' names of those planes (kept
    from a coadd imported from lsst-images: ``DETECTION_EDGE``) get afw's (``EDGE``)."""
    table = {ours: names[_COLUMN[flavour]] for ours, names in RUBIN_PLANES.items()}
    out = _rename(bits, table)
    if flavour == "lsst_images":
        return _rename(out, RUBIN_LSST_IMAGES)
    # lsst-images names kept from a Rubin coadd imported from lsst-images: afw's names
    return _rename(out, {new: old for old, new in RUBIN_LSST_IMAGES.items()})


def from_rubin(bits: dict[str, int], flavour: Flavour) -> dict[str, int]:
    """``bits`` (Rubin's name -> bit) with our names: the inverse of :func:`to_rubin`.

    lsst-images' ``DETECTION_EDGE`` becomes ``EDGE`` only beside a ``SENSOR_EDGE`` (as
    :func:`to_rubin` makes them of a Rubin coadd's two planes); alone it keeps its name,
    so that it is never taken for our ``EDGE``, the edge of an input detector."""
    if flavour == "lsst_images":
        back = {new: old for old, new in RUBIN_LSST_IMAGES.items()}
        if "SENSOR_EDGE" not in bits:
            del back["DETECTION_EDGE"]
        bits = _rename(bits, back)
    table = {names[_COLUMN[flavour]]: ours for ours, names in RUBIN_PLANES.items()}
    return _rename(bits, table)


def rubin_description(ours: str) -> str:
    """The description written with a plane (lsst-images stores one per plane)."""
    entry = RUBIN_PLANES.get(ours)
    return entry[2] if entry else f"cellcoadd mask bit {ours}."
