"""Exposure files: one :class:`~cellcoadd.model.exposure.Exposure` per FITS file (fitsio).

Layout (format ``cellcoadd-exposure``, version :data:`EXPOSURE_FORMAT_VERSION`):

========  ==================================================================================
HDU       content
========  ==================================================================================
IMAGE     primary HDU: the image (float32/float64 as given); header: the WCS
          (``wcs.to_header(relax=True)``, SIP included) and the keywords CCFORMAT, FMTVER,
          VISIT, DETECTOR, BAND, ZEROPT, VALIDX0/VALIDX1/VALIDY0/VALIDY1 (valid box,
          half-open), VARKIND (SCALAR or ARRAY), VARIANCE (when scalar), PSFKIND
MASK      int32 bit mask; header keywords ``MP_<NAME> = bit`` for every mask bit
VARIANCE  float64 variance plane (only when the variance is an array)
PSF       PSFKIND = SAMPLED, GRID, PIXGRID: float64 cube (n_y_nodes, n_x_nodes, n, n) of
          oversampled stamps; IMAGE: the image PSF stamp (dtype as given); PSFEX, PIFF:
          uint8 copy of the model file's bytes (SHA-256 in META); none for PROFILE, VARYING
META      uint8 bytes of a UTF-8 JSON document with the exact values (see below)
========  ==================================================================================

Pixel arrays round-trip bit for bit (``-0.0`` included), except that cfitsio writes every
NaN with one canonical bit pattern (the NaN positions are kept).

PSF kinds (``PROFILE``, ``VARYING``, ``SAMPLED``, ``GRID``, ``PIXGRID``, ``IMAGE``,
``PSFEX``, ``PIFF``): see :mod:`cellcoadd.io.exposures.exposure_psf`.

cfitsio writes floating-point header values with 15 significant digits, which is not
enough to round-trip float64 (nor a WCS to 1e-9 pixel). The META document therefore holds
the exact values of the floating-point keywords (WCS parameters, see
:mod:`cellcoadd.io._fits.wcs_header`, zero point, scalar variance) together with the identity,
band (any Unicode), mask-bit names (case kept) and PSF description; the header keywords
are for people and other tools, and the reader checks they agree with META. Every HDU
carries CHECKSUM/DATASUM and ``DATACRC`` (CRC-32 of its data unit as stored, see
:mod:`cellcoadd.io._fits.checksums`), verified on read; files without ``DATACRC`` (written
before it existed) are read without that check.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import fitsio
import numpy as np
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddFormatError, DamagedDataError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import canonical_wcs, shifted_wcs
from cellcoadd.io._files.atomic import atomic_write, exists_error
from cellcoadd.io._files.disk_space import check_free_space
from cellcoadd.io._files.path_gate import gate_read, gate_write
from cellcoadd.io._files.read_checks import MAX_PLANE_PIXELS, is_file_failure
from cellcoadd.io._fits.cfitsio_messages import clear_cfitsio_messages
from cellcoadd.io._fits.checksums import (
    DATACRC_PLACEHOLDER,
    stabilise_fits_checksums,
    verify_hdu,
)
from cellcoadd.io._fits.paths import cfitsio_path, starts_like_fits
from cellcoadd.io._fits.wcs_header import as_float, read_wcs, same_float, wcs_cards
from cellcoadd.io.exposures.exposure_psf import psf_payload, read_psf
from cellcoadd.model.exposure import Exposure, ExposureError
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.sources import ExposureHeader

T = TypeVar("T")

EXPOSURE_FORMAT = "cellcoadd-exposure"
# 1.1: DATACRC keywords; 1.2: PSF kinds PIXGRID, PSFEX and PIFF (a 1.1 reader refuses them
# as unknown PSF kinds)
EXPOSURE_FORMAT_VERSION = "1.2"


def write_exposure(
    exposure: Exposure, path: str | os.PathLike[str], *, overwrite: bool = False
) -> Path:
    """Write ``exposure`` to the FITS file ``path`` atomically.

    The file is written to a temporary file in the same directory, flushed to disk and
    renamed onto ``path`` (:func:`cellcoadd.io._files.atomic.atomic_write`), so a reader never
    sees a partial file, and an existing file is never replaced unless ``overwrite``. The
    same exposure gives a byte-identical file (the checksum cards carry fixed comments, not
    the time).

    Raises
    ------
    FileExistsError
        When ``path`` exists (or appears during the write) and ``overwrite`` is false.
    ExposureError
        When the PSF cannot be stored (its callable fails, returns something other than a
        GSObject, or gives non-finite or empty stamps); nothing is written.
    OSError
        ``errno.ENOSPC`` when the file does not fit on the disk; nothing is left behind.
    """
    gate_write(path, what="exposure file", fits=True)
    target = Path(path)
    if target.exists() and not overwrite:
        raise exists_error(target)
    header_wcs, wcs_exact = wcs_cards(exposure.wcs)
    try:
        psf_kind, psf_meta, psf_array = psf_payload(exposure)
    except Exception as err:  # a user PSF model can fail in any way
        raise ExposureError(
            f"exposure (visit={exposure.visit}, detector={exposure.detector}): its PSF cannot "
            f"be stored: {type(err).__name__}: {err}"
        ) from err
    scalar_variance = isinstance(exposure.variance, float)
    # valid_box is never None once the exposure is built
    box = exposure.valid_box if exposure.valid_box is not None else Box.from_shape(exposure.shape)
    meta = {
        "format": EXPOSURE_FORMAT,
        "format_version": EXPOSURE_FORMAT_VERSION,
        "visit": int(exposure.visit),
        "detector": int(exposure.detector),
        "band": exposure.band,
        "zero_point": float(exposure.zero_point),
        "valid_box": [box.x_start, box.x_stop, box.y_start, box.y_stop],
        "variance": float(exposure.variance) if scalar_variance else None,
        "mask_bits": dict(exposure.mask_bits.bits),
        "wcs_exact": wcs_exact,
        "psf": psf_meta,
    }
    if exposure.origin != (0, 0):  # a cutout: where it lies on its detector (format 1.2)
        meta["origin"] = list(exposure.origin)
    keys: list[dict[str, Any]] = [
        {"name": "CCFORMAT", "value": EXPOSURE_FORMAT, "comment": "file format"},
        {"name": "FMTVER", "value": EXPOSURE_FORMAT_VERSION, "comment": "format version"},
        {"name": "VISIT", "value": int(exposure.visit)},
        {"name": "DETECTOR", "value": int(exposure.detector)},
        {"name": "BAND", "value": _ascii(exposure.band), "comment": "exact value in META"},
        {"name": "ZEROPT", "value": float(exposure.zero_point), "comment": "[mag] zero point"},
        {"name": "VALIDX0", "value": box.x_start, "comment": "valid box, first column"},
        {"name": "VALIDX1", "value": box.x_stop, "comment": "valid box, last column + 1"},
        {"name": "VALIDY0", "value": box.y_start, "comment": "valid box, first row"},
        {"name": "VALIDY1", "value": box.y_stop, "comment": "valid box, last row + 1"},
        {"name": "VARKIND", "value": "SCALAR" if scalar_variance else "ARRAY"},
        {"name": "PSFKIND", "value": psf_kind},
        DATACRC_PLACEHOLDER,
    ]
    if scalar_variance:
        keys.append({"name": "VARIANCE", "value": float(exposure.variance)})
    mask_keys = [
        {"name": f"MP_{name.upper()}", "value": int(bit), "comment": "mask plane bit"}
        for name, bit in exposure.mask_bits.bits.items()
    ]
    mask_keys.append(DATACRC_PLACEHOLDER)
    meta_bytes = np.frombuffer(json.dumps(meta, allow_nan=False).encode("utf-8"), np.uint8)

    def write_hdus(fits_file: fitsio.FITS) -> None:
        fits_file.write(exposure.image, header=header_wcs + keys, extname="IMAGE")
        fits_file.write(exposure.mask, header=mask_keys, extname="MASK")
        if not scalar_variance:
            fits_file.write(exposure.variance, header=[DATACRC_PLACEHOLDER], extname="VARIANCE")
        if psf_array is not None:
            fits_file.write(psf_array, header=[DATACRC_PLACEHOLDER], extname="PSF")
        fits_file.write(meta_bytes, header=[DATACRC_PLACEHOLDER], extname="META")
        for hdu in fits_file:
            hdu.write_checksum()

    arrays: list[np.ndarray] = [exposure.image, meta_bytes]
    arrays += [
        a for a in (exposure.mask, psf_array, exposure.variance) if isinstance(a, np.ndarray)
    ]
    needed = sum(a.nbytes for a in arrays) + 2880 * (8 + 2 * len(arrays))

    def write_file(temporary: Path) -> None:
        # created by CFITSIO itself, so it gets the usual permissions (mkstemp would give 0600)
        with fitsio.FITS(cfitsio_path(temporary), "rw", clobber=True) as fits_file:
            write_hdus(fits_file)
        stabilise_fits_checksums(temporary)

    return atomic_write(
        target,
        write_file,
        overwrite=overwrite,
        prepare=lambda _: check_free_space(target, needed),
        on_failure=clear_cfitsio_messages,
    )


def read_exposure(
    path: str | os.PathLike[str],
    box: Box | None = None,
    *,
    wcs: WCS | None = None,
    trust_psf: bool = False,
) -> Exposure:
    """Read an exposure written by :func:`write_exposure`, or its cutout over ``box``.

    Parameters
    ----------
    path : path-like
        The exposure file.
    box : Box, optional
        Pixels to read (half-open, in the file's pixels; clipped to the image). Only
        those pixels are read, and the result is an exposure with ``origin`` and WCS
        of the cutout. The checksums of a file are verified when it is read whole; a
        cutout verifies its small HDUs (META, PSF) only.
    wcs : astropy.wcs.WCS, optional
        The file's WCS as :func:`read_exposure_header` returned it (canonical), used
        instead of parsing the header again (saves ~6 ms); its CRPIX and CRVAL are
        checked against the file's. The result is the same.
    trust_psf : bool
        Allow a stored Piff model: it holds pickled objects, which run code when loaded
        (:func:`cellcoadd.io.read_piff`). Only for files you trust.

    Raises
    ------
    CellCoaddFormatError
        For a missing, unreadable, truncated, corrupted (CHECKSUM/DATASUM or DATACRC) or
        inconsistent file, or one of another kind, or a ``wcs`` of another file; never
        another exception type.
    """
    return _with_file(path, lambda fits_file, raw: _read(fits_file, raw, box, wcs, trust_psf))


def read_exposure_header(path: str | os.PathLike[str]) -> ExposureHeader:
    """What a build needs to know of an exposure file before its pixels: identity, band,
    WCS (in :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs` form), shape, valid box,
    zero point and mask bits (no pixel is read)."""
    return _with_file(path, lambda fits_file, raw: _header(fits_file, raw))


def _with_file(path: str | os.PathLike[str], read: Callable[[fitsio.FITS, BinaryIO], T]) -> T:
    # no CFITSIO syntax, a regular file (a directory, pipe or device could block CFITSIO)
    try:
        resolved = gate_read(path, what="exposure file", fits=True)
    except FileNotFoundError:
        raise CellCoaddFormatError(path, "no such exposure file") from None
    # start and leave with an empty CFITSIO message stack (see cellcoadd.io.api.open)
    clear_cfitsio_messages()
    try:
        if not starts_like_fits(resolved):
            # CFITSIO would first inflate a gzip (or compress, bzip2) stream into memory
            raise _fail("not a FITS file (it does not start with SIMPLE)")
        with fitsio.FITS(resolved) as fits_file, open(resolved, "rb") as raw:
            return read(fits_file, raw)
    except CellCoaddFormatError as err:
        raise CellCoaddFormatError(path, err.problem) from None
    except Exception as err:  # a library's error on a malformed file is a format error
        if not is_file_failure(err):  # a programming error is not the file's fault
            raise
        raise CellCoaddFormatError(path, f"unreadable exposure file ({err})") from err
    finally:
        clear_cfitsio_messages()


# -- writing helpers -----------------------------------------------------------------
def _ascii(text: str) -> str:
    """A header-safe rendering of ``text`` (the exact value is kept in META)."""
    return text.encode("ascii", "backslashreplace").decode("ascii")


# -- reading helpers -----------------------------------------------------------------
def _fail(problem: str) -> CellCoaddFormatError:
    # the path is filled in by read_exposure
    return CellCoaddFormatError("", problem)


def _open_parts(
    fits_file: fitsio.FITS, raw: BinaryIO, verify_all: bool
) -> tuple[list[str], dict[str, Any], fitsio.FITSHDR]:
    """HDU names, META and the IMAGE header, checked; checksums of every HDU (or of the
    small ones only)."""
    names = [hdu.get_extname() for hdu in fits_file]
    for required in ("IMAGE", "MASK", "META"):
        if required not in names:
            raise _fail(f"missing HDU {required} (HDUs: {names})")
    _check_declared_sizes(fits_file, names, raw)
    for hdu in fits_file:
        if verify_all or hdu.get_extname() in ("META", "PSF"):
            try:
                verify_hdu(raw, hdu.get_offsets())
            except DamagedDataError as err:
                raise _fail(f"HDU {hdu.get_extname() or hdu.get_extnum()}: {err}") from None
    meta = _read_meta(fits_file["META"].read())
    image_header = fits_file["IMAGE"].read_header()
    _check_keywords(image_header, meta)
    return names, meta, image_header


def _image_shape(fits_file: fitsio.FITS) -> tuple[int, int]:
    dims = fits_file["IMAGE"].get_dims()
    if len(dims) != 2:
        raise _fail(f"IMAGE must be 2-D, got dimensions {dims}")
    return int(dims[0]), int(dims[1])


def _meta_origin(meta: dict[str, Any]) -> tuple[int, int]:
    origin = meta.get("origin", [0, 0])
    if not (isinstance(origin, list) and len(origin) == 2 and all(type(v) is int for v in origin)):
        raise _fail("META origin must hold 2 integers")
    return origin[0], origin[1]


def _header(fits_file: fitsio.FITS, raw: BinaryIO) -> ExposureHeader:
    _, meta, image_header = _open_parts(fits_file, raw, verify_all=False)
    x0, x1, y0, y1 = (int(v) for v in meta["valid_box"])
    return ExposureHeader(
        visit=int(meta["visit"]),
        detector=int(meta["detector"]),
        band=meta["band"],
        wcs=canonical_wcs(read_wcs(image_header, meta["wcs_exact"])),
        shape=_image_shape(fits_file),
        valid_box=Box(x_start=x0, x_stop=x1, y_start=y0, y_stop=y1),
        zero_point=as_float(meta["zero_point"], "zero_point"),
        mask_bits=MaskBits(bits=meta["mask_bits"]),
    )


def _read(
    fits_file: fitsio.FITS,
    raw: BinaryIO,
    box: Box | None = None,
    wcs: WCS | None = None,
    trust_psf: bool = False,
) -> Exposure:
    """The exposure in ``fits_file`` (its cutout over ``box``); ``raw`` is the same file,
    for the checksums; ``wcs`` its canonical WCS if already read."""
    names, meta, image_header = _open_parts(fits_file, raw, verify_all=box is None)
    full = Box.from_shape(_image_shape(fits_file))
    cut = full if box is None else box.intersection(full)
    if cut.is_empty:
        raise _fail(f"box {box} is outside the image {full}")

    _check_plane_dims(fits_file, names, full.shape)

    def pixels(hdu: str) -> np.ndarray:
        if cut == full:
            return _native(fits_file[hdu].read())
        return _native(fits_file[hdu][cut.y_start : cut.y_stop, cut.x_start : cut.x_stop])

    image = pixels("IMAGE")
    mask = pixels("MASK")
    if image.ndim != 2 or mask.shape != image.shape or mask.dtype != np.int32:
        raise _fail("IMAGE and MASK must be 2-D of the same shape, MASK int32")
    mask_bits = MaskBits(bits=meta["mask_bits"])
    _check_mask_keywords(fits_file["MASK"].read_header(), mask_bits)

    if meta["variance"] is None:
        if "VARIANCE" not in names:
            raise _fail("missing HDU VARIANCE for an array variance")
        variance: float | np.ndarray = pixels("VARIANCE")
    else:
        variance = as_float(meta["variance"], "variance")
    psf_array = _native(fits_file["PSF"].read()) if "PSF" in names else None
    x0, x1, y0, y1 = (int(v) for v in meta["valid_box"])
    valid = Box(x_start=x0, x_stop=x1, y_start=y0, y_stop=y1).intersection(cut)
    if wcs is None:
        wcs = canonical_wcs(read_wcs(image_header, meta["wcs_exact"]))
    else:
        _check_same_wcs(wcs, meta["wcs_exact"])
    ox, oy = _meta_origin(meta)
    return Exposure(
        image=image,
        # the canonical WCS shifted: canonical too (it pickles exactly; tested)
        wcs=wcs if cut == full else shifted_wcs(wcs, cut.x_start, cut.y_start),
        wcs_is_canonical=True,
        variance=variance,
        psf=read_psf(meta["psf"], psf_array, trusted=trust_psf),
        visit=int(meta["visit"]),
        detector=int(meta["detector"]),
        band=meta["band"],
        zero_point=as_float(meta["zero_point"], "zero_point"),
        mask=mask,
        mask_bits=mask_bits,
        valid_box=valid.shifted(-cut.x_start, -cut.y_start),
        origin=(ox + cut.x_start, oy + cut.y_start),
    )


#: Largest ratio of declared to stored bytes of a tile-compressed HDU (deflate cannot
#: compress more than about 1032:1; RICE less).
_MAX_COMPRESSION = 1100


def _check_same_wcs(wcs: WCS, exact: dict[str, Any]) -> None:
    """Refuse a WCS given for this file whose CRPIX or CRVAL are not the file's (to the
    ~14 digits of a header, as a WCS given by the caller may have been read from one)."""
    for key in ("CRPIX1", "CRPIX2", "CRVAL1", "CRVAL2"):
        axis = int(key[-1]) - 1
        given = float((wcs.wcs.crpix if key.startswith("CRPIX") else wcs.wcs.crval)[axis])
        if key in exact:
            value = as_float(exact[key], key)
            if not abs(given - value) <= 1e-11 * max(1.0, abs(value)):
                raise _fail(f"the WCS given for this file has another {key} ({given})")


def _check_plane_dims(fits_file: fitsio.FITS, names: list[str], shape: tuple[int, int]) -> None:
    """Before any pixel is read: MASK and VARIANCE have the IMAGE's shape."""
    for name in ("MASK", "VARIANCE"):
        if name in names:
            dims = tuple(int(d) for d in fits_file[name].get_dims())
            if dims != shape:
                raise _fail(f"{name} has dimensions {dims}, IMAGE {shape}")


def _check_declared_sizes(fits_file: fitsio.FITS, names: list[str], raw: BinaryIO) -> None:
    """Before any data is read: no image HDU declares more than
    :data:`~cellcoadd.io._files.read_checks.MAX_PLANE_PIXELS` pixels, nor more bytes than
    its stored data unit can hold (a tile-compressed HDU is inflated whole by CFITSIO)."""
    size = os.fstat(raw.fileno()).st_size
    for name in ("IMAGE", "MASK", "VARIANCE", "PSF", "META"):
        if name not in names:
            continue
        hdu = fits_file[name]
        dims = [int(d) for d in hdu.get_dims()]
        pixels = int(np.prod(dims, dtype=np.float64)) if dims else 0
        if hdu.get_exttype() == "IMAGE_HDU" and pixels > MAX_PLANE_PIXELS:
            shape = " x ".join(str(d) for d in reversed(dims))  # NAXIS1 first
            raise _fail(
                f"HDU {name} declares a {shape} image ({pixels} pixels), more than the "
                f"{MAX_PLANE_PIXELS} accepted: refused before reading it"
            )
        header = hdu.read_header()
        bitpix = header.get("ZBITPIX", header.get("BITPIX", 8))
        declared = int(np.prod(dims, dtype=np.float64)) * abs(int(bitpix)) // 8
        offsets = hdu.get_offsets()
        stored = min(int(offsets["data_end"]) - int(offsets["data_start"]), size)
        if declared > _MAX_COMPRESSION * max(stored, 0) + 2880:
            raise _fail(
                f"{name} declares {dims} pixels ({declared} bytes) but stores {stored} bytes"
            )


def _read_meta(data: np.ndarray) -> dict[str, Any]:
    if data.dtype != np.uint8 or data.ndim != 1:
        raise _fail("META must be a 1-D byte array")
    try:
        meta = json.loads(data.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _fail(f"META is not valid JSON ({err})") from None
    if not isinstance(meta, dict) or meta.get("format") != EXPOSURE_FORMAT:
        raise _fail(f"not a {EXPOSURE_FORMAT} file")
    version = str(meta.get("format_version", ""))
    if version.split(".")[0] != EXPOSURE_FORMAT_VERSION.split(".")[0]:
        raise _fail(f"unsupported format version {version!r} (reader: {EXPOSURE_FORMAT_VERSION})")
    required: dict[str, type | tuple[type, ...]] = {
        "visit": int,
        "detector": int,
        "band": str,
        "zero_point": (int, float),
        "valid_box": list,
        "mask_bits": dict,
        "wcs_exact": dict,
        "psf": dict,
    }
    for key, kind in required.items():
        if not isinstance(meta.get(key), kind) or isinstance(meta.get(key), bool):
            raise _fail(f"META field {key!r} is missing or of the wrong type")
    if "variance" not in meta:
        raise _fail("META field 'variance' is missing")
    if len(meta["valid_box"]) != 4:
        raise _fail("META valid_box must hold 4 integers")
    return meta


def _check_keywords(header: fitsio.FITSHDR, meta: dict[str, Any]) -> None:
    """The human-readable IMAGE keywords must agree with META."""
    expected_ints = {
        "VISIT": meta["visit"],
        "DETECTOR": meta["detector"],
        "VALIDX0": meta["valid_box"][0],
        "VALIDX1": meta["valid_box"][1],
        "VALIDY0": meta["valid_box"][2],
        "VALIDY1": meta["valid_box"][3],
    }
    for key, value in expected_ints.items():
        if key not in header or header[key] != value:
            raise _fail(f"IMAGE keyword {key} disagrees with META ({value})")
    if header.get("CCFORMAT") != EXPOSURE_FORMAT:
        raise _fail("IMAGE keyword CCFORMAT is missing or wrong")
    if not same_float(header.get("ZEROPT"), float(meta["zero_point"])):
        raise _fail("IMAGE keyword ZEROPT disagrees with META")
    if meta["variance"] is not None and not same_float(
        header.get("VARIANCE"), float(meta["variance"])
    ):
        raise _fail("IMAGE keyword VARIANCE disagrees with META")


def _check_mask_keywords(header: fitsio.FITSHDR, mask_bits: MaskBits) -> None:
    planes = {k: header[k] for k in header.keys() if k.startswith("MP_")}
    expected = {f"MP_{name.upper()}": bit for name, bit in mask_bits.bits.items()}
    if planes != expected:
        raise _fail(f"MASK keywords {planes} disagree with META mask bits {expected}")


def _native(array: np.ndarray) -> np.ndarray:
    """``array`` in native byte order, bits unchanged."""
    if array.dtype.byteorder in ("=", "|"):
        return array
    return array.astype(array.dtype.newbyteorder("="))
