"""Rubin's names for our mask planes, on export to Rubin's formats and back.

Rubin has two sets of names: ``lsst.afw.image.Mask`` names (``SAT``, ``CR``, ``INTRP``...),
which ``lsst.cell_coadds`` files list in ``MASKDEF``, and the names of the newer
lsst-images package (``SATURATED``, ``COSMIC_RAY``, ``INTERPOLATED``...), which it maps
from the afw ones (``lsst.images.get_legacy_*_mask_planes``). Our names are afw's, except
``EDGE``: ours marks the edge of an input detector, which Rubin's coadds call
``SENSOR_EDGE`` (afw's ``EDGE`` on a coadd, lsst-images' ``DETECTION_EDGE``, is the
detection-kernel edge of the image, a different thing).

Names outside the table are kept as they are. A name is renamed only when its new name is
not already one of the names, so the renaming can always be undone (``docs/format.md``,
"Mask planes").
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

_COLUMN = {"afw": 0, "lsst_images": 1}


def _renamed(names: list[str], table: dict[str, str]) -> dict[str, str]:
    present = set(names)
    return {
        name: table.get(name, name) if table.get(name, name) not in present else name
        for name in names
    }


def to_rubin(bits: dict[str, int], flavour: Flavour) -> dict[str, int]:
    """``bits`` (our name -> bit) with Rubin's names, bit numbers unchanged."""
    table = {ours: names[_COLUMN[flavour]] for ours, names in RUBIN_PLANES.items()}
    renamed = _renamed(list(bits), table)
    return {renamed[name]: bit for name, bit in bits.items()}


def from_rubin(bits: dict[str, int], flavour: Flavour) -> dict[str, int]:
    """``bits`` (Rubin's name -> bit) with our names: the inverse of :func:`to_rubin`."""
    table = {names[_COLUMN[flavour]]: ours for ours, names in RUBIN_PLANES.items()}
    renamed = _renamed(list(bits), table)
    return {renamed[name]: bit for name, bit in bits.items()}


def rubin_description(ours: str) -> str:
    """The description written with a plane (lsst-images stores one per plane)."""
    entry = RUBIN_PLANES.get(ours)
    return entry[2] if entry else f"cellcoadd mask bit {ours}."
