"""Geometry: sky map -> tract -> patch -> cell, pixel boxes, WCS helpers, catalog trimming."""

from cellcoadd.geometry.box import Box
from cellcoadd.geometry.catalog import flag_unique, sky_ids, trim_to_cell, trim_to_patch
from cellcoadd.geometry.config import SkyMapConfig
from cellcoadd.geometry.skymap import SkyMap, SkyMapSpec
from cellcoadd.geometry.tract import Cell, Patch, Tract

__all__ = [
    "Box",
    "Cell",
    "Patch",
    "SkyMap",
    "SkyMapConfig",
    "SkyMapSpec",
    "Tract",
    "flag_unique",
    "sky_ids",
    "trim_to_cell",
    "trim_to_patch",
]
