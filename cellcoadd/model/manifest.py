"""The list of input exposures of a build, as a file the command line reads.

A manifest is a TOML, JSON or CSV file with one entry per exposure (see
:mod:`cellcoadd.io.exposures.manifest_io` for the file forms and ``schemas/Manifest.v1.json``)::

    [[exposures]]
    path = "D00154912_r_c12_immasked.fits.fz"
    layout = "des"
    psf = "D00154912_r_c12_psfexcat.psf"
    background = "D00154912_r_c12_bkg.fits.fz"

    [[exposures]]
    path = "calexp_2024031500123_R22_S11.fits"
    layout = "lsst"
    psf = "calexp_2024031500123_R22_S11.piff"
    trust_psf = true  # a Piff file holds pickled objects: loaded only when trusted
    zero_point = 31.4

Relative paths are relative to the manifest's directory.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from cellcoadd.errors import CellCoaddValueError

#: Built-in layouts: cellcoadd's own exposure files, the LSST single-detector files, the
#: DES single-epoch files. A dict describes another multi-extension layout (the fields
#: of :class:`cellcoadd.io.exposures.mef_layout.MefLayout`).
LayoutName = Literal["cellcoadd", "lsst", "des"]


class ManifestEntry(BaseModel):
    """One input exposure.

    Parameters
    ----------
    path : str
        The exposure file.
    layout : "cellcoadd", "lsst", "des" or dict
        How the file is laid out (a dict: a generic multi-extension layout).
    psf : str, optional
        PSF model file, PSFEx or Piff (recognised by content). Required for ``lsst`` and
        ``des``; cellcoadd's own files hold their PSF.
    trust_psf : bool
        Allow a Piff model (in ``psf``, or stored in a cellcoadd exposure file): Piff
        files hold pickled objects, which run code when loaded. Only for files you trust.
    background : str, optional
        Background image file to subtract (DES ``_bkg.fits.fz``).
    zero_point : float, optional
        Zero point, mag, when the file's header has none.
    visit, detector : int, optional
        Identity, when the header has none.
    band : str, optional
        Band, when the header has none.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: str = Field(min_length=1)
    layout: LayoutName | dict[str, Any] = "cellcoadd"
    psf: str | None = None
    background: str | None = None
    zero_point: float | None = Field(None, gt=-50.0, lt=100.0, description="mag")
    visit: int | None = None
    detector: int | None = None
    band: str | None = None
    trust_psf: bool = False

    @field_validator("psf", "background", "band")
    @classmethod
    def _not_blank(cls, value: str | None) -> str | None:
        if value is not None and not value.strip():
            raise CellCoaddValueError("must not be blank (leave it out instead)", value=value)
        return value


class Manifest(BaseModel):
    """The input exposures of a build, in the order they are coadded."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    exposures: tuple[ManifestEntry, ...] = Field(min_length=1)
