"""Find a survey's exposure files in a directory and write a manifest listing them.

What ``cellcoadd init --survey des|lsst DIR`` does: match each exposure file to its PSF
model file (and, for DES, its background file) by name, without opening any file, and
write a commented TOML manifest (:mod:`cellcoadd.model.manifest`) to start from.

Names are matched by prefix: a PSF file ``<base>_psfexcat.psf`` (or ``<base>_psfcat.psf``,
``<base>.psf``, ``<base>.piff``, ``<base>_piff.fits``) belongs to every exposure whose name
without its extension is ``<base>`` or starts with ``<base>_``; the longest such base
wins. Backgrounds are ``<base>_bkg.fits`` or ``<base>_bkg.fits.fz``. DES exposures are the
``*_immasked.fits[.fz]`` files when there are any, else every other FITS file; LSST
exposures are the FITS files that are neither PSF nor background files.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from cellcoadd.errors import CellCoaddFormatError

Survey = Literal["des", "lsst"]

_FITS_SUFFIXES = (".fits.fz", ".fits.gz", ".fits")
_PSF_SUFFIXES = ("_psfexcat.psf", "_psfcat.psf", "_piff.fits", ".psf", ".piff")
_BACKGROUND_SUFFIXES = ("_bkg.fits.fz", "_bkg.fits")
_HEADER_ZERO_POINTS = {"des": "MAGZERO or MAGZP", "lsst": "FLUXMAG0, PHOTOCALIB_ID or BUNIT"}


@dataclass(frozen=True)
class FoundExposure:
    """An exposure file with the PSF and background files matched to it (None: none)."""

    path: Path
    psf: Path | None
    background: Path | None


def _cut(name: str, suffixes: tuple[str, ...]) -> str | None:
    lower = name.lower()
    for suffix in suffixes:
        if lower.endswith(suffix):
            return name[: -len(suffix)]
    return None


def _belongs(base: str, stem: str) -> bool:
    return stem == base or stem.startswith(base + "_")


def _best(stem: str, candidates: dict[str, Path]) -> Path | None:
    bases = [base for base in candidates if _belongs(base, stem)]
    return candidates[max(bases, key=len)] if bases else None


def find_survey_files(directory: str | os.PathLike[str], survey: Survey) -> list[FoundExposure]:
    """The exposure files of ``survey`` in ``directory`` (not its sub-directories), sorted
    by name, each with its PSF model and background files.

    Raises
    ------
    CellCoaddFormatError
        When ``directory`` is not a readable directory.
    """
    root = Path(directory)
    try:
        names = sorted(p.name for p in root.iterdir() if p.is_file())
    except OSError as err:
        raise CellCoaddFormatError(root, f"cannot list the directory: {err.strerror}") from None
    psfs: dict[str, Path] = {}
    backgrounds: dict[str, Path] = {}
    images: list[str] = []
    for name in names:
        psf_base = _cut(name, _PSF_SUFFIXES)
        background_base = _cut(name, _BACKGROUND_SUFFIXES)
        if psf_base is not None:
            psfs.setdefault(psf_base, root / name)
        elif background_base is not None:
            backgrounds.setdefault(background_base, root / name)
        elif _cut(name, _FITS_SUFFIXES) is not None and "psf" not in name.lower():
            images.append(name)
    if survey == "des":
        immasked = [n for n in images if "_immasked." in n.lower()]
        images = immasked or images
    found = []
    for name in images:
        stem = _cut(name, _FITS_SUFFIXES) or name
        background = _best(stem, backgrounds) if survey == "des" else None
        found.append(FoundExposure(root / name, _best(stem, psfs), background))
    return found


def manifest_toml(found: list[FoundExposure], survey: Survey, base: Path) -> str:
    """A commented TOML manifest of ``found`` (paths relative to ``base``, the directory
    the manifest is written to). Exposures without a PSF file are written commented out."""
    zero_points = _HEADER_ZERO_POINTS[survey]
    lines = [
        f"# cellcoadd manifest: {survey.upper()} exposures (`cellcoadd init --survey {survey}`).",
        "# One [[exposures]] table per exposure file, coadded in this order; paths are",
        "# relative to this file's directory. Fields (docs/manifest.md):",
        "#   path        the exposure file",
        f'#   layout      "{survey}" here; "des", "lsst", "cellcoadd" or a table of HDUs',
        "#   psf         its PSF model file: .psf is PSFEx, anything else Piff",
        "#   background  a background image to subtract (DES _bkg.fits.fz)",
        f"#   zero_point  mag, only for files whose header has no {zero_points}",
        "#   visit, detector, band   only for files whose header lacks them",
        "",
    ]
    for exposure in found:
        entry = [
            "[[exposures]]",
            f"path = {_quoted(exposure.path, base)}",
            f'layout = "{survey}"',
        ]
        if exposure.psf is not None:
            entry.append(f"psf = {_quoted(exposure.psf, base)}")
        if exposure.background is not None:
            entry.append(f"background = {_quoted(exposure.background, base)}")
        entry.append(f"# zero_point = 30.0  # if the header has no {zero_points}")
        if exposure.psf is None:
            lines.append(f"# no PSF model file found for {exposure.path.name}: add psf = ...")
            entry = [line if line.startswith("#") else f"# {line}" for line in entry]
            entry.insert(3, '# psf = "..."')
        lines += [*entry, ""]
    return "\n".join(lines)


def _quoted(path: Path, base: Path) -> str:
    return json.dumps(os.path.relpath(path, base).replace(os.sep, "/"))
