"""PSF model files (PSFEx ``.psf``, Piff): recognised by content, parsed whole on reading.

=============================  ==========================================================
reader                         what it does
=============================  ==========================================================
:func:`read_psf_file`          the model in a file, by its content (not its name): a
                               PSFEx file if HDU 1 is a table with a ``PSF_MASK`` column,
                               a Piff file if a table carries Piff's version or WCS
                               columns; anything else is refused
:func:`read_psfex`             a PSFEx file, parsed and checked into a
                               :class:`~cellcoadd.model.psf.PsfexData`
:func:`read_piff`              a Piff file: **only with** ``trusted=True``
=============================  ==========================================================

Piff files hold *pickled* Python objects (the WCS of the fit): unpickling a crafted file
runs arbitrary code. A Piff model is therefore loaded only when the caller names the file
as trusted (``read_piff(path, trusted=True)``, ``trust_psf = true`` in a manifest entry,
``trust_psf=True`` for survey readers and exposure files holding a Piff model).

Every file goes through the path gate (:func:`cellcoadd.io._files.path_gate.read_bytes`:
no CFITSIO syntax, a regular file, at most :data:`MAX_PSF_FILE_BYTES`) and must start
like a FITS file, so a gzip stream is never inflated. Problems raise
:class:`~cellcoadd.errors.CellCoaddFormatError` naming the file.
"""

from __future__ import annotations

import io
import os
import tempfile
import warnings
from typing import Any

import numpy as np
from astropy.io import fits

from cellcoadd.errors import CellCoaddFormatError, PsfError
from cellcoadd.io._files.path_gate import read_bytes
from cellcoadd.io._fits.paths import FITS_MAGIC
from cellcoadd.model.psf import PiffPsf, PsfexData, PsfexPsf, PsfModel

#: Largest PSF model file read (bytes): PSFEx files are ~100 KB, Piff files a few MB.
MAX_PSF_FILE_BYTES = 256 * 1024 * 1024

PathLike = str | os.PathLike[str]


def _read_bytes(path: PathLike) -> tuple[str, bytes]:
    try:
        data = read_bytes(path, what="PSF model file", max_bytes=MAX_PSF_FILE_BYTES)
    except FileNotFoundError:
        raise CellCoaddFormatError(path, "no such PSF model file") from None
    return os.fspath(path), data


def _hdus(source: str, data: bytes) -> fits.HDUList:
    """The HDU list of ``data``, headers checked against the real size before any data."""
    if not data.startswith(FITS_MAGIC):
        # astropy, like CFITSIO, would inflate a gzip or bzip2 stream into memory
        raise CellCoaddFormatError(source, "not a FITS file (it does not start with SIMPLE)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hdus = fits.open(io.BytesIO(data), memmap=False, lazy_load_hdus=False)
            hdus.verify("exception")
    except Exception as err:  # astropy raises many types for malformed files
        raise CellCoaddFormatError(source, f"not a readable FITS file ({err})") from None
    end = 0
    for index, hdu in enumerate(hdus):
        info = hdu.fileinfo()
        if info is None:
            continue
        declared = info["datLoc"] + info["datSpan"]
        if declared > len(data):
            raise CellCoaddFormatError(
                source,
                f"HDU {index}: declares data up to byte {declared}, the file has {len(data)} "
                "(truncated?)",
            )
        end = max(end, declared)
    return hdus


def _kind(hdus: fits.HDUList) -> str | None:
    if len(hdus) > 1 and isinstance(hdus[1], fits.BinTableHDU):
        if "PSF_MASK" in [name.upper() for name in hdus[1].columns.names]:
            return "psfex"
    for hdu in hdus[1:]:
        if not isinstance(hdu, fits.BinTableHDU):
            continue
        names = {name.lower() for name in hdu.columns.names}
        if "PIFF_VERSION" in hdu.header or "piff_version" in names or "wcs_str_0000" in names:
            return "piff"
    return None


def read_psf_file(path: PathLike, *, trusted: bool = False, **piff_options: Any) -> PsfModel:
    """The PSF model in ``path``, recognised by its content.

    Parameters
    ----------
    path : path-like
        A PSFEx or Piff model file (any name).
    trusted : bool
        Needed for a Piff file (it holds pickled objects, see the module docstring).
    **piff_options
        ``chipnum=``, ``origin=`` of :class:`~cellcoadd.model.psf.PiffPsf`.

    Raises
    ------
    CellCoaddFormatError
        For a file that is neither, an untrusted Piff file, or a malformed model.
    """
    source, data = _read_bytes(path)
    hdus = _hdus(source, data)
    kind = _kind(hdus)
    if kind == "psfex":
        return _psfex(source, data, hdus)
    if kind == "piff":
        return _piff(source, data, trusted, **piff_options)
    raise CellCoaddFormatError(
        source, "not a PSF model file: neither a PSFEx table (PSF_MASK) nor a Piff model"
    )


def read_psfex(path: PathLike) -> PsfexPsf:
    """A PSFEx ``.psf`` file, parsed whole and checked.

    Raises
    ------
    CellCoaddFormatError
        Naming the file, for anything that is not a usable PSFEx model: a missing or
        non-numeric keyword, ``POLSCAL`` or ``PSF_SAMP`` of 0, non-finite coefficients,
        a truncated table.
    """
    source, data = _read_bytes(path)
    return parse_psfex(data, source)


def parse_psfex(data: bytes, source: str = "<bytes>") -> PsfexPsf:
    """:func:`read_psfex` of a file's bytes (``source`` names it in errors)."""
    hdus = _hdus(source, data)
    if _kind(hdus) != "psfex":
        raise CellCoaddFormatError(source, "not a PSFEx model: HDU 1 has no PSF_MASK column")
    return _psfex(source, data, hdus)


def _psfex(source: str, data: bytes, hdus: fits.HDUList) -> PsfexPsf:
    hdu = hdus[1]
    header = hdu.header

    def number(key: str, kind: type = float) -> Any:
        value = header.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CellCoaddFormatError(
                source, f"HDU 1: {key} = {value!r} is not a number (or missing)"
            )
        if kind is int and not isinstance(value, int):
            raise CellCoaddFormatError(source, f"HDU 1: {key} = {value!r} is not an integer")
        return kind(value)

    expected = {"POLNAXIS": 2, "POLNGRP": 1, "POLGRP1": 1, "POLGRP2": 1, "PSFNAXIS": 3}
    for key, value in expected.items():
        if number(key, int) != value:
            raise CellCoaddFormatError(
                source, f"HDU 1: {key} = {header[key]}, cellcoadd reads only {value}"
            )
    for key, axis in (("POLNAME1", "X"), ("POLNAME2", "Y")):
        name = str(header.get(key, ""))
        if not (name.startswith(axis) and name.endswith("IMAGE")):
            raise CellCoaddFormatError(source, f"HDU 1: {key} = {name!r}, expected {axis}_IMAGE")
    if len(hdu.data) != 1:
        raise CellCoaddFormatError(source, f"HDU 1: {len(hdu.data)} rows, expected 1")
    try:
        basis = np.array(hdu.data.field("PSF_MASK")[0], dtype=np.float64)
    except Exception as err:  # a malformed table may fail in any way
        raise CellCoaddFormatError(source, f"HDU 1: cannot read PSF_MASK ({err})") from None
    axes = (number("PSFAXIS3", int), number("PSFAXIS2", int), number("PSFAXIS1", int))
    if basis.shape != axes:
        raise CellCoaddFormatError(
            source, f"HDU 1: PSF_MASK has shape {basis.shape}, PSFAXIS3/2/1 declare {axes}"
        )
    try:
        parsed = PsfexData(
            basis=basis,
            degree=number("POLDEG1", int),
            zero=(number("POLZERO1"), number("POLZERO2")),
            scale=(number("POLSCAL1"), number("POLSCAL2")),
            sample=number("PSF_SAMP"),
        )
        return PsfexPsf(parsed, data=data, source=source)
    except PsfError as err:
        raise CellCoaddFormatError(source, f"HDU 1: {err}") from None


def read_piff(
    path: PathLike, *, trusted: bool = False, chipnum: int | None = None, origin: int = 1
) -> PiffPsf:
    """A Piff model file, loaded whole (needs the optional extra ``cellcoadd[piff]``).

    Parameters
    ----------
    path : path-like
        The Piff file.
    trusted : bool
        Must be True: loading a Piff file unpickles objects stored in it, which runs
        code chosen by whoever wrote the file. Pass it only for files you trust.
    chipnum, origin
        See :class:`~cellcoadd.model.psf.PiffPsf`.

    Raises
    ------
    CellCoaddFormatError
        Without ``trusted=True``, for a file that is not a Piff model, or one Piff cannot
        load.
    """
    source, data = _read_bytes(path)
    if _kind(_hdus(source, data)) != "piff":
        raise CellCoaddFormatError(source, "not a Piff model file")
    return _piff(source, data, trusted, chipnum=chipnum, origin=origin)


def parse_piff(
    data: bytes,
    source: str = "<bytes>",
    *,
    trusted: bool = False,
    chipnum: int | None = None,
    origin: int = 1,
) -> PiffPsf:
    """:func:`read_piff` of a file's bytes (``source`` names it in errors)."""
    if _kind(_hdus(source, data)) != "piff":
        raise CellCoaddFormatError(source, "not a Piff model file")
    return _piff(source, data, trusted, chipnum=chipnum, origin=origin)


def _piff(
    source: str, data: bytes, trusted: bool, chipnum: int | None = None, origin: int = 1
) -> PiffPsf:
    if trusted is not True:
        raise CellCoaddFormatError(
            source,
            "a Piff model file holds pickled Python objects, which run code when loaded: "
            "load it only if you trust it (read_piff(path, trusted=True), trust_psf = true "
            "in a manifest entry, trust_psf=True in the readers)",
        )
    try:
        import piff
    except ImportError:
        raise CellCoaddFormatError(
            source, "reading Piff models needs the optional extra: pip install 'cellcoadd[piff]'"
        ) from None
    # piff reads from a file name only: a private copy of the very bytes checked here
    with tempfile.TemporaryDirectory() as directory:
        copy = os.path.join(directory, "model.piff")
        with open(copy, "wb") as stream:
            stream.write(data)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = piff.read(copy)
        except Exception as err:  # Piff and fitsio raise many types for malformed files
            raise CellCoaddFormatError(source, f"not a loadable Piff model ({err})") from None
    try:
        return PiffPsf(model, data=data, source=source, chipnum=chipnum, origin=origin)
    except PsfError as err:
        raise CellCoaddFormatError(source, str(err)) from None
