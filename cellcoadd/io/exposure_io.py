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
PSF       PSFKIND = GRID: float64 cube (n_y_nodes, n_x_nodes, n, n) of pre-pixel stamps;
          PSFKIND = IMAGE: the image PSF stamp (dtype as given)
META      uint8 bytes of a UTF-8 JSON document with the exact values (see below)
========  ==================================================================================

Pixel arrays round-trip bit for bit (``-0.0`` included), except that cfitsio writes every
NaN with one canonical bit pattern (the NaN positions are kept).

PSF kinds: ``PROFILE`` (a GSObject with an exact JSON description, see
:mod:`cellcoadd.io.psf_codec`), ``VARYING`` (a :class:`~cellcoadd.io.psf_codec.VaryingPsf`,
exact), ``GRID`` (any other callable, sampled on a 5 x 5 grid of oversampled pre-pixel
stamps and read back as a :class:`~cellcoadd.io.psf_codec.GridPsf`), ``SAMPLED`` (a
GSObject outside the whitelist, sampled once and read back as an InterpolatedImage) and
``IMAGE`` (a ``galsim.Image`` PSF, bit-identical).

cfitsio writes floating-point header values with 15 significant digits, which is not
enough to round-trip float64 (nor a WCS to 1e-9 pixel). The META document therefore holds
the exact values of the floating-point keywords (WCS parameters, zero point, scalar
variance) together with the identity, band (any Unicode), mask-bit names (case kept) and
PSF description; the header keywords are for people and other tools, and the reader
checks they agree with META. Every HDU carries CHECKSUM/DATASUM, verified on read.
"""

from __future__ import annotations

import json
import os
import secrets
import warnings
from pathlib import Path
from typing import Any

import fitsio
import galsim
import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, Sip

from cellcoadd.geometry.box import Box
from cellcoadd.io.common import (
    check_free_space,
    clear_cfitsio_messages,
    disk_full_error,
    stabilise_fits_checksums,
)
from cellcoadd.io.errors import CellCoaddFormatError
from cellcoadd.io.psf_codec import GridPsf, VaryingPsf, can_encode, decode_psf, encode_psf
from cellcoadd.model.exposure import Exposure, ExposureError
from cellcoadd.model.maskbits import MaskBits

EXPOSURE_FORMAT = "cellcoadd-exposure"
EXPOSURE_FORMAT_VERSION = "1.0"
PSF_GRID_NODES = 5
PSF_GRID_OVERSAMPLE = 4
# relative agreement required between a header float (15 digits) and its exact value
_HEADER_RTOL = 1e-13


def write_exposure(
    exposure: Exposure, path: str | os.PathLike[str], *, overwrite: bool = False
) -> Path:
    """Write ``exposure`` to the FITS file ``path`` atomically.

    The file is written to a temporary file in the same directory, flushed to disk and
    renamed onto ``path``, so a reader never sees a partial file. The same exposure gives
    a byte-identical file (the checksum cards carry fixed comments, not the time).

    Raises
    ------
    FileExistsError
        When ``path`` exists and ``overwrite`` is false.
    ExposureError
        When the PSF cannot be stored (its callable fails, returns something other than a
        GSObject, or gives non-finite or empty stamps); nothing is written.
    OSError
        ``errno.ENOSPC`` when the file does not fit on the disk; nothing is left behind.
    """
    target = Path(path)
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; pass overwrite=True to replace it")
    header_wcs, wcs_exact = _wcs_cards(exposure.wcs)
    try:
        psf_kind, psf_meta, psf_array = _psf_payload(exposure)
    except Exception as err:  # a user PSF model can fail in any way
        raise ExposureError(
            f"exposure (visit={exposure.visit}, detector={exposure.detector}): its PSF cannot "
            f"be stored: {type(err).__name__}: {err}"
        ) from err
    scalar_variance = isinstance(exposure.variance, float)
    box = exposure.valid_box
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
    ]
    if scalar_variance:
        keys.append({"name": "VARIANCE", "value": float(exposure.variance)})
    mask_keys = [
        {"name": f"MP_{name.upper()}", "value": int(bit), "comment": "mask plane bit"}
        for name, bit in exposure.mask_bits.bits.items()
    ]
    meta_bytes = np.frombuffer(json.dumps(meta, allow_nan=False).encode("utf-8"), np.uint8)

    def write(fits_file: fitsio.FITS) -> None:
        fits_file.write(exposure.image, header=header_wcs + keys, extname="IMAGE")
        fits_file.write(exposure.mask, header=mask_keys, extname="MASK")
        if not scalar_variance:
            fits_file.write(exposure.variance, extname="VARIANCE")
        if psf_array is not None:
            fits_file.write(psf_array, extname="PSF")
        fits_file.write(meta_bytes, extname="META")
        for hdu in fits_file:
            hdu.write_checksum()

    arrays = [exposure.image, exposure.mask, meta_bytes]
    arrays += [a for a in (psf_array, exposure.variance) if isinstance(a, np.ndarray)]
    needed = sum(a.nbytes for a in arrays) + 2880 * (8 + 2 * len(arrays))
    _atomic_fits_write(target, write, needed)
    return target


def read_exposure(path: str | os.PathLike[str]) -> Exposure:
    """Read an exposure written by :func:`write_exposure`.

    Raises
    ------
    CellCoaddFormatError
        For a missing, unreadable, truncated, corrupted (checksum) or inconsistent file,
        or one of another kind; never another exception type.
    """
    if os.path.exists(path) and not os.path.isfile(path):
        # a directory, pipe or device: CFITSIO could block on it
        raise CellCoaddFormatError(path, "not a regular file")
    # start and leave with an empty CFITSIO message stack (see cellcoadd.io.api.open)
    clear_cfitsio_messages()
    try:
        with fitsio.FITS(os.fspath(path)) as fits_file:
            return _read(fits_file)
    except CellCoaddFormatError as err:
        raise CellCoaddFormatError(path, err.problem) from None
    except Exception as err:  # any library error on a malformed file becomes a format error
        raise CellCoaddFormatError(path, f"unreadable exposure file ({err})") from err
    finally:
        clear_cfitsio_messages()


# -- writing helpers -----------------------------------------------------------------
def _ascii(text: str) -> str:
    """A header-safe rendering of ``text`` (the exact value is kept in META)."""
    return text.encode("ascii", "backslashreplace").decode("ascii")


def _wcs_cards(wcs: WCS) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Header cards of ``wcs`` and the exact values of its floating-point keywords."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        header = wcs.to_header(relax=True)
    exact = _exact_wcs_values(wcs)
    cards = []
    for card in header.cards:
        value = card.value
        if card.keyword in exact:
            value = exact[card.keyword]
        cards.append({"name": card.keyword, "value": value, "comment": card.comment})
    exact = {k: v for k, v in exact.items() if k in header}
    return cards, exact


def _exact_wcs_values(wcs: WCS) -> dict[str, float]:
    """Exact float64 values of the WCS keywords ``to_header`` writes (rounded there)."""
    core = wcs.wcs
    pc = core.get_pc()
    cdelt = core.get_cdelt()
    values: dict[str, float] = {"LONPOLE": float(core.lonpole), "LATPOLE": float(core.latpole)}
    for i in range(2):
        values[f"CRPIX{i + 1}"] = float(core.crpix[i])
        values[f"CRVAL{i + 1}"] = float(core.crval[i])
        values[f"CDELT{i + 1}"] = float(cdelt[i])
        for j in range(2):
            values[f"PC{i + 1}_{j + 1}"] = float(pc[i, j])
    sip = wcs.sip
    if sip is not None:
        for prefix, coeffs in (("A", sip.a), ("B", sip.b), ("AP", sip.ap), ("BP", sip.bp)):
            if coeffs is None:
                continue
            for p, q in zip(*np.nonzero(coeffs), strict=True):
                values[f"{prefix}_{p}_{q}"] = float(coeffs[p, q])
    return values


def _psf_payload(exposure: Exposure) -> tuple[str, dict[str, Any], np.ndarray | None]:
    """``(PSFKIND, META description, PSF HDU array or None)`` of the exposure's PSF."""
    psf = exposure.psf
    if isinstance(psf, galsim.Image):
        scale = psf.scale if psf.wcs is not None and psf.wcs.isPixelScale() else None
        return "IMAGE", {"kind": "image", "scale": scale}, np.ascontiguousarray(psf.array)
    if isinstance(psf, galsim.GSObject):
        if can_encode(psf):
            return "PROFILE", {"kind": "profile", "profile": encode_psf(psf)}, None
        grid = GridPsf.sample(
            lambda x, y: psf,
            (1, 1),
            _typical_scale(exposure),
            n_nodes=1,
            oversample=PSF_GRID_OVERSAMPLE,
        )
        return "SAMPLED", {"kind": "sampled", "scale": grid.scale}, grid.stamps
    if isinstance(psf, VaryingPsf) and can_encode(psf):
        return "VARYING", {"kind": "varying", "profile": encode_psf(psf)}, None
    if isinstance(psf, GridPsf):
        grid = psf
    else:
        grid = GridPsf.sample(
            psf,
            exposure.shape,
            _typical_scale(exposure),
            n_nodes=PSF_GRID_NODES,
            oversample=PSF_GRID_OVERSAMPLE,
        )
    meta = {
        "kind": "grid",
        "scale": grid.scale,
        "x_nodes": [float(v) for v in grid.x_nodes],
        "y_nodes": [float(v) for v in grid.y_nodes],
    }
    return "GRID", meta, np.ascontiguousarray(grid.stamps, dtype=np.float64)


def _typical_scale(exposure: Exposure) -> float:
    """Pixel scale (arcsec) at the detector centre: sqrt of the pixel area."""
    ny, nx = exposure.shape
    jac = exposure.local_jacobian((nx - 1) / 2.0, (ny - 1) / 2.0)
    return float(np.sqrt(abs(np.linalg.det(jac))))


def _atomic_fits_write(target: Path, write: Any, needed: int) -> None:
    """Run ``write(fits)`` on a temporary file next to ``target``, then rename it.

    ``needed`` is an upper estimate of the file size, checked against the free space
    first; a disk that fills up midway gives ``OSError(ENOSPC)``. Either way no file is
    left behind.
    """
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory")
    # created by CFITSIO itself, so it gets the usual permissions (mkstemp would give 0600)
    tmp_name = str(directory / f".{target.name}.tmp-{secrets.token_hex(8)}")
    check_free_space(target, needed)
    try:
        with fitsio.FITS(tmp_name, "rw", clobber=True) as fits_file:
            write(fits_file)
        stabilise_fits_checksums(tmp_name)
        with open(tmp_name, "rb") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException as err:
        full = disk_full_error(target, err) if isinstance(err, Exception) else None
        if os.path.exists(tmp_name):
            os.remove(tmp_name)
        clear_cfitsio_messages()
        if full is not None:
            raise full from err
        raise
    try:  # make the rename itself durable where the platform allows it
        dir_fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


# -- reading helpers -----------------------------------------------------------------
def _fail(problem: str) -> CellCoaddFormatError:
    # the path is filled in by read_exposure
    return CellCoaddFormatError("", problem)


def _read(fits_file: fitsio.FITS) -> Exposure:
    names = [hdu.get_extname() for hdu in fits_file]
    for required in ("IMAGE", "MASK", "META"):
        if required not in names:
            raise _fail(f"missing HDU {required} (HDUs: {names})")
    for hdu in fits_file:
        try:
            hdu.verify_checksum()
        except ValueError as err:
            raise _fail(f"HDU {hdu.get_extname() or hdu.get_extnum()}: {err}") from None
    meta = _read_meta(fits_file["META"].read())
    image_header = fits_file["IMAGE"].read_header()
    _check_keywords(image_header, meta)

    image = _native(fits_file["IMAGE"].read())
    mask = _native(fits_file["MASK"].read())
    if image.ndim != 2 or mask.shape != image.shape or mask.dtype != np.int32:
        raise _fail("IMAGE and MASK must be 2-D of the same shape, MASK int32")
    mask_bits = MaskBits(bits=meta["mask_bits"])
    _check_mask_keywords(fits_file["MASK"].read_header(), mask_bits)

    if meta["variance"] is None:
        if "VARIANCE" not in names:
            raise _fail("missing HDU VARIANCE for an array variance")
        variance: float | np.ndarray = _native(fits_file["VARIANCE"].read())
    else:
        variance = _as_float(meta["variance"], "variance")
    psf_array = _native(fits_file["PSF"].read()) if "PSF" in names else None
    x0, x1, y0, y1 = (int(v) for v in meta["valid_box"])
    return Exposure(
        image=image,
        wcs=_read_wcs(image_header, meta["wcs_exact"]),
        variance=variance,
        psf=_read_psf(meta["psf"], psf_array),
        visit=int(meta["visit"]),
        detector=int(meta["detector"]),
        band=meta["band"],
        zero_point=_as_float(meta["zero_point"], "zero_point"),
        mask=mask,
        mask_bits=mask_bits,
        valid_box=Box(x_start=x0, x_stop=x1, y_start=y0, y_stop=y1),
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
    required = {
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


def _as_float(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(f"{what} must be a number")
    return float(value)


def _same_float(header_value: Any, exact: float) -> bool:
    if isinstance(header_value, bool) or not isinstance(header_value, (int, float)):
        return False
    return abs(float(header_value) - exact) <= _HEADER_RTOL * max(1.0, abs(exact))


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
    if not _same_float(header.get("ZEROPT"), float(meta["zero_point"])):
        raise _fail("IMAGE keyword ZEROPT disagrees with META")
    if meta["variance"] is not None and not _same_float(
        header.get("VARIANCE"), float(meta["variance"])
    ):
        raise _fail("IMAGE keyword VARIANCE disagrees with META")


def _check_mask_keywords(header: fitsio.FITSHDR, mask_bits: MaskBits) -> None:
    planes = {k: header[k] for k in header.keys() if k.startswith("MP_")}
    expected = {f"MP_{name.upper()}": bit for name, bit in mask_bits.bits.items()}
    if planes != expected:
        raise _fail(f"MASK keywords {planes} disagree with META mask bits {expected}")


def _read_wcs(header: fitsio.FITSHDR, exact: dict[str, Any]) -> WCS:
    text = "\n".join(record["card_string"] for record in header.records())
    values = {key: _as_float(value, f"WCS value {key}") for key, value in exact.items()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        astropy_header = fits.Header.fromstring(text, sep="\n")
        for key, value in values.items():
            if key not in astropy_header or not _same_float(astropy_header[key], value):
                raise _fail(f"WCS keyword {key} disagrees with its exact value in META")
        wcs = WCS(astropy_header, naxis=2)
    if not wcs.has_celestial:
        raise _fail("the IMAGE header holds no celestial WCS")
    # astropy re-renders header floats with at most 20 characters when it builds the WCS,
    # so the exact values are set on the parsed WCS itself
    _apply_exact_wcs_values(wcs, values)
    return wcs


def _apply_exact_wcs_values(wcs: WCS, values: dict[str, float]) -> None:
    """Inverse of :func:`_exact_wcs_values` on a WCS parsed from the rounded header."""
    core = wcs.wcs
    crpix, crval = core.crpix.copy(), core.crval.copy()
    cdelt, pc = core.get_cdelt().copy(), core.get_pc().copy()
    for i in range(2):
        crpix[i] = values.get(f"CRPIX{i + 1}", crpix[i])
        crval[i] = values.get(f"CRVAL{i + 1}", crval[i])
        cdelt[i] = values.get(f"CDELT{i + 1}", cdelt[i])
        for j in range(2):
            pc[i, j] = values.get(f"PC{i + 1}_{j + 1}", pc[i, j])
    core.crpix, core.crval, core.cdelt, core.pc = crpix, crval, cdelt, pc
    core.lonpole = values.get("LONPOLE", core.lonpole)
    core.latpole = values.get("LATPOLE", core.latpole)
    sip = wcs.sip
    if sip is not None:
        coeffs = {}
        for prefix, array in (("A", sip.a), ("B", sip.b), ("AP", sip.ap), ("BP", sip.bp)):
            if array is None:
                coeffs[prefix] = None
                continue
            array = array.copy()
            for p, q in zip(*np.nonzero(array), strict=True):
                array[p, q] = values.get(f"{prefix}_{p}_{q}", array[p, q])
            coeffs[prefix] = array
        wcs.sip = Sip(coeffs["A"], coeffs["B"], coeffs["AP"], coeffs["BP"], crpix)
    core.set()


def _read_psf(desc: Any, array: np.ndarray | None) -> Any:
    if not isinstance(desc, dict):
        raise _fail("META psf must be an object")
    kind = desc.get("kind")
    if kind in ("profile", "varying"):
        psf = decode_psf(desc.get("profile"))
        expected = VaryingPsf if kind == "varying" else galsim.GSObject
        if not isinstance(psf, expected):
            raise _fail(f"PSF description does not match its kind {kind!r}")
        return psf
    if array is None:
        raise _fail(f"missing HDU PSF for a PSF of kind {kind!r}")
    if kind == "image":
        scale = desc.get("scale")
        if scale is None:
            return galsim.Image(array)
        return galsim.Image(array, scale=_as_float(scale, "PSF scale"))
    if kind == "sampled":
        grid = GridPsf(
            x_nodes=np.zeros(1), y_nodes=np.zeros(1), stamps=array, scale=desc.get("scale")
        )
        return grid(0.0, 0.0)
    if kind == "grid":
        x_nodes = np.array([_as_float(v, "PSF node") for v in desc.get("x_nodes", [])])
        y_nodes = np.array([_as_float(v, "PSF node") for v in desc.get("y_nodes", [])])
        return GridPsf(
            x_nodes=x_nodes,
            y_nodes=y_nodes,
            stamps=array,
            scale=_as_float(desc.get("scale"), "PSF scale"),
        )
    raise _fail(f"unknown PSF kind {kind!r}")


def _native(array: np.ndarray) -> np.ndarray:
    """``array`` in native byte order, bits unchanged."""
    if array.dtype.byteorder in ("=", "|"):
        return array
    return array.astype(array.dtype.newbyteorder("="))
