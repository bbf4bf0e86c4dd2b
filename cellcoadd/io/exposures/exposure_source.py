"""cellcoadd's own exposure files as exposure sources (headers now, cutouts on demand)."""

from __future__ import annotations

import os

from cellcoadd.geometry.box import Box
from cellcoadd.io.exposures.exposure_io import read_exposure, read_exposure_header
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.sources import ExposureHeader, ExposureSource


class ExposureFile(ExposureSource):
    """An exposure file written by :func:`cellcoadd.write_exposure`, read on demand.

    Picklable (it holds the path only), so worker processes load their own inputs.

    Parameters
    ----------
    path : path-like
        The exposure file.
    trust_psf : bool
        Allow a stored Piff model (pickled objects: see :func:`read_exposure`).
    """

    def __init__(self, path: str | os.PathLike[str], *, trust_psf: bool = False):
        self.path = os.fspath(path)
        self.trust_psf = trust_psf

    def header(self) -> ExposureHeader:
        return read_exposure_header(self.path)

    def load(self, box: Box | None = None) -> Exposure:
        return read_exposure(self.path, box, trust_psf=self.trust_psf)

    def load_described(self, header: ExposureHeader, box: Box | None = None) -> Exposure:
        # the header's WCS (canonical) instead of parsing the file's again
        return read_exposure(self.path, box, wcs=header.wcs, trust_psf=self.trust_psf)

    def __repr__(self) -> str:
        return f"ExposureFile({self.path!r})"
