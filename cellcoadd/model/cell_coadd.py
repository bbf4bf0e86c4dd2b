"""The in-memory coadd of one cell: pixel planes, PSF, inputs, identity and WCS.

Array conventions
-----------------
Every plane covers the cell's *outer* box: ``plane[j, i]`` is tract pixel
``(outer_bbox.x_start + i, outer_bbox.y_start + j)``, and ``wcs`` maps array pixel
``(0, 0)`` (0-based, pixel centres at integers) to that tract pixel's sky position.

* ``image``: surface brightness in the patch's units, float32.
* ``mask``: int32 bit mask, bits named by the patch's :class:`~cellcoadd.model.maskbits.MaskBits`.
* ``variance``: per-pixel variance of ``image``, float32.
* ``noise``: ``K`` noise realizations coadded exactly like the image, float32, ``(K, ny, nx)``.
* ``mfrac``: fraction of the coadd weight that came from masked input pixels, float32.
* ``psf``: odd square float64 stamp of the coadd PSF at the cell centre (pixel response
  included), centred on its central pixel, summing to 1.

A cell with no used input is *empty*: every float plane is NaN, the mask has ``NO_DATA``
set everywhere (checked by :class:`~cellcoadd.model.patch_coadd.PatchCoadd`) and its
rejected inputs are still listed. :meth:`CellCoadd.empty` builds one.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, NamedTuple

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning, Sip

from cellcoadd.errors import InvalidCoaddError
from cellcoadd.geometry.box import Box
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.maskbits import MaskBits

#: Tolerance on ``|sum(psf) - 1|`` for a non-empty cell.
PSF_SUM_TOLERANCE = 1e-6


class CellPlanes(NamedTuple):
    """Views of a cell's planes cut to a sub-box (the inner box, for :attr:`CellCoadd.inner`)."""

    image: np.ndarray
    mask: np.ndarray
    variance: np.ndarray
    noise: np.ndarray
    mfrac: np.ndarray


class CellCoadd:
    """Coadd of one cell (validated at construction).

    Parameters
    ----------
    image, variance, mfrac : ndarray, shape ``outer_bbox.shape``
        Float planes. Other float dtypes are converted to float32 (float64 values are
        rounded); integer or complex arrays are refused.
    mask : ndarray of int, shape ``outer_bbox.shape``
        Bit mask; converted to int32 (values must fit).
    noise : ndarray, shape ``(K, ny, nx)``
        ``K >= 0`` noise realizations (float, converted to float32).
    psf : ndarray, shape ``(n, n)`` with ``n`` odd
        PSF stamp (float, converted to float64); sums to 1 unless the cell is empty.
    inputs : iterable of InputRecord (or dicts)
        Every input that overlapped the cell, used or rejected.
    tract : int
        Tract number.
    index : (int, int)
        Tract-global cell index ``(cx, cy)``; may be negative for border cells at tract edges.
    inner_bbox, outer_bbox : Box
        Inner and outer boxes in tract pixels; the inner box lies inside the outer one.
    wcs : astropy.wcs.WCS
        Celestial WCS of the outer-box arrays (see the module docstring).

    Raises
    ------
    InvalidCoaddError
        When a field has the wrong type, dtype, shape or is inconsistent with another.
    """

    def __init__(
        self,
        *,
        image: np.ndarray,
        mask: np.ndarray,
        variance: np.ndarray,
        noise: np.ndarray,
        mfrac: np.ndarray,
        psf: np.ndarray,
        inputs: Iterable[InputRecord | dict[str, Any]],
        tract: int,
        index: tuple[int, int],
        inner_bbox: Box,
        outer_bbox: Box,
        wcs: WCS,
    ) -> None:
        self.tract = _as_int("tract", tract)
        self.index = _as_index(index)
        if not isinstance(outer_bbox, Box) or not isinstance(inner_bbox, Box):
            raise InvalidCoaddError(f"cell {self.index}: inner_bbox and outer_bbox must be Box")
        if outer_bbox.is_empty or inner_bbox.is_empty:
            raise InvalidCoaddError(f"cell {self.index}: boxes must not be empty")
        if not outer_bbox.contains_box(inner_bbox):
            raise InvalidCoaddError(
                f"cell {self.index}: inner_bbox {inner_bbox} is not inside outer_bbox {outer_bbox}"
            )
        self.inner_bbox = inner_bbox
        self.outer_bbox = outer_bbox
        shape = outer_bbox.shape
        name = f"cell {self.index}"
        self.image = _float_plane(name, "image", image, shape, np.float32)
        self.variance = _float_plane(name, "variance", variance, shape, np.float32)
        self.mfrac = _float_plane(name, "mfrac", mfrac, shape, np.float32)
        self.mask = _mask_plane(name, mask, shape)
        noise = _float_array(name, "noise", noise, np.float32)
        if noise.ndim != 3 or noise.shape[1:] != shape:
            raise InvalidCoaddError(
                f"{name}: noise must have shape (K, {shape[0]}, {shape[1]}), got {noise.shape}"
            )
        self.noise = noise
        self.psf = _float_array(name, "psf", psf, np.float64)
        if (
            self.psf.ndim != 2
            or self.psf.shape[0] != self.psf.shape[1]
            or self.psf.shape[0] % 2 == 0
        ):
            raise InvalidCoaddError(
                f"{name}: psf must be an odd square 2-D stamp, got shape {self.psf.shape}"
            )
        try:
            self.inputs: list[InputRecord] = [
                item if isinstance(item, InputRecord) else InputRecord.model_validate(item)
                for item in inputs
            ]
        except ValueError as err:
            raise InvalidCoaddError(f"{name}: invalid input record: {err}") from err
        keys = [record.key for record in self.inputs]
        if len(set(keys)) != len(keys):
            raise InvalidCoaddError(f"{name}: inputs list a (visit, detector) more than once")
        self.wcs = _check_wcs(name, wcs)
        if self.is_empty:
            if not np.isnan(self.image).all():
                raise InvalidCoaddError(
                    f"{name}: an empty cell (no used input) must have a NaN image"
                )
        else:
            total = float(np.sum(self.psf))
            if not abs(total - 1.0) <= PSF_SUM_TOLERANCE:
                raise InvalidCoaddError(f"{name}: psf must sum to 1 (got {total!r})")

    @classmethod
    def empty(
        cls,
        *,
        tract: int,
        index: tuple[int, int],
        inner_bbox: Box,
        outer_bbox: Box,
        wcs: WCS,
        n_noise: int,
        psf_size: int,
        inputs: Iterable[InputRecord | dict[str, Any]] = (),
        mask_bits: MaskBits | None = None,
    ) -> CellCoadd:
        """A cell with no used input: NaN planes and PSF, ``NO_DATA`` everywhere in the mask.

        ``inputs`` lists the rejected inputs (none may be used).
        """
        bits = mask_bits if mask_bits is not None else MaskBits()
        shape = outer_bbox.shape
        return cls(
            image=np.full(shape, np.nan, dtype=np.float32),
            mask=np.full(shape, bits.value("NO_DATA"), dtype=np.int32),
            variance=np.full(shape, np.nan, dtype=np.float32),
            noise=np.full((n_noise, *shape), np.nan, dtype=np.float32),
            mfrac=np.full(shape, np.nan, dtype=np.float32),
            psf=np.full((psf_size, psf_size), np.nan, dtype=np.float64),
            inputs=inputs,
            tract=tract,
            index=index,
            inner_bbox=inner_bbox,
            outer_bbox=outer_bbox,
            wcs=wcs,
        )

    @property
    def n_used(self) -> int:
        """Number of inputs that contributed."""
        return sum(record.is_used for record in self.inputs)

    @property
    def n_noise(self) -> int:
        """Number ``K`` of noise realizations."""
        return int(self.noise.shape[0])

    @property
    def is_empty(self) -> bool:
        """Whether no input contributed (then the planes hold no data)."""
        return self.n_used == 0

    @property
    def shape(self) -> tuple[int, int]:
        """Shape ``(ny, nx)`` of every plane (the outer box)."""
        return self.outer_bbox.shape

    @property
    def inner(self) -> CellPlanes:
        """Views (not copies) of image, mask, variance, noise and mfrac cut to the inner box."""
        rows, cols = self.inner_bbox.slices_in(self.outer_bbox)
        return CellPlanes(
            image=self.image[rows, cols],
            mask=self.mask[rows, cols],
            variance=self.variance[rows, cols],
            noise=self.noise[:, rows, cols],
            mfrac=self.mfrac[rows, cols],
        )

    def equals(self, other: object) -> bool:
        """Whether ``other`` is the same cell bit for bit.

        Arrays must have equal dtypes, shapes and bytes (so NaN payloads and -0.0 count),
        inputs must be :meth:`~cellcoadd.model.inputs.InputRecord.identical`, and identity,
        boxes and WCS (:func:`wcs_to_record`) equal.
        """
        if not isinstance(other, CellCoadd):
            return False
        if (self.tract, self.index, self.inner_bbox, self.outer_bbox) != (
            other.tract,
            other.index,
            other.inner_bbox,
            other.outer_bbox,
        ):
            return False
        for plane in ("image", "mask", "variance", "noise", "mfrac", "psf"):
            if not arrays_identical(getattr(self, plane), getattr(other, plane)):
                return False
        if len(self.inputs) != len(other.inputs) or not all(
            a.identical(b) for a, b in zip(self.inputs, other.inputs, strict=True)
        ):
            return False
        return wcs_to_record(self.wcs) == wcs_to_record(other.wcs)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CellCoadd):
            return NotImplemented
        return self.equals(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return (
            f"CellCoadd(tract={self.tract}, index={self.index}, outer={self.outer_bbox}, "
            f"inputs={len(self.inputs)} ({self.n_used} used), K={self.n_noise}, "
            f"psf={self.psf.shape[0]}x{self.psf.shape[1]})"
        )


def arrays_identical(first: np.ndarray, second: np.ndarray) -> bool:
    """Whether two arrays have the same dtype, shape and bytes (NaN payloads, -0.0 included)."""
    return (
        first.dtype == second.dtype
        and first.shape == second.shape
        and first.tobytes() == second.tobytes()
    )


def wcs_header(wcs: WCS) -> fits.Header:
    """``wcs.to_header(relax=True)`` (SIP included) without astropy's fix-up warnings.

    Floating-point values there are rounded when printed as FITS cards; the exact values
    are :func:`wcs_exact_parameters`.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        return wcs.to_header(relax=True)


def wcs_exact_parameters(wcs: WCS) -> dict[str, Any]:
    """The numerical parameters of a celestial WCS at full double precision (JSON-able).

    Keys: ``crpix``, ``crval``, ``cdelt`` (lists of 2 floats), ``pc`` (2 x 2), ``lonpole``,
    ``latpole``, ``pv`` (``[i, m, value]`` triples) and ``sip`` (None, or the ``a``, ``b``,
    ``ap``, ``bp`` coefficient matrices as nested lists, each possibly None).
    :func:`apply_wcs_exact_parameters` sets them back.
    """
    params = wcs.wcs
    exact: dict[str, Any] = {
        "crpix": [float(v) for v in params.crpix],
        "crval": [float(v) for v in params.crval],
        "cdelt": [float(v) for v in params.get_cdelt()],
        "pc": [[float(v) for v in row] for row in params.get_pc()],
        "lonpole": float(params.lonpole),
        "latpole": float(params.latpole),
        "pv": [[int(i), int(m), float(v)] for i, m, v in params.get_pv()],
        "sip": None,
    }
    if wcs.sip is not None:
        exact["sip"] = {
            name: None if coeffs is None else np.asarray(coeffs, dtype=float).tolist()
            for name, coeffs in zip(
                _SIP_NAMES, (wcs.sip.a, wcs.sip.b, wcs.sip.ap, wcs.sip.bp), strict=True
            )
        }
    return exact


def apply_wcs_exact_parameters(wcs: WCS, exact: dict[str, Any]) -> None:
    """Set the parameters of :func:`wcs_exact_parameters` on ``wcs`` (in place), bit-exact.

    An empty ``pv`` list leaves the PV values of ``wcs`` as they are.
    """
    params = wcs.wcs
    params.crpix = exact["crpix"]
    params.crval = exact["crval"]
    params.cdelt = exact["cdelt"]
    params.pc = exact["pc"]
    params.lonpole = exact["lonpole"]
    params.latpole = exact["latpole"]
    if exact["pv"]:
        params.set_pv([(int(i), int(m), float(v)) for i, m, v in exact["pv"]])
    sip = exact.get("sip")
    if sip is not None:
        wcs.sip = Sip(
            *(
                None if sip[name] is None else np.asarray(sip[name], dtype=float)
                for name in _SIP_NAMES
            ),
            np.asarray(exact["crpix"], dtype=float),
        )
    params.set()


def wcs_exact_keywords(wcs: WCS) -> dict[str, float]:
    """:func:`wcs_exact_parameters` keyed by the FITS keywords they are rounded in.

    ``LONPOLE``, ``LATPOLE``, then ``CRPIXi``, ``CRVALi``, ``CDELTi``, ``PCi_j`` for each
    axis ``i``, then the non-zero SIP coefficients ``A_p_q``, ``B_p_q``, ``AP_p_q``,
    ``BP_p_q`` (PV values are not included). :func:`apply_wcs_exact_keywords` sets them back.
    """
    exact = wcs_exact_parameters(wcs)
    values: dict[str, float] = {"LONPOLE": exact["lonpole"], "LATPOLE": exact["latpole"]}
    for i in range(2):
        values[f"CRPIX{i + 1}"] = exact["crpix"][i]
        values[f"CRVAL{i + 1}"] = exact["crval"][i]
        values[f"CDELT{i + 1}"] = exact["cdelt"][i]
        for j in range(2):
            values[f"PC{i + 1}_{j + 1}"] = exact["pc"][i][j]
    for _, prefix, coeffs in _sip_items(exact):
        for p, q in zip(*np.nonzero(coeffs), strict=True):
            values[f"{prefix}_{p}_{q}"] = float(coeffs[p, q])
    return values


def apply_wcs_exact_keywords(wcs: WCS, values: dict[str, float]) -> None:
    """Set the exact values of :func:`wcs_exact_keywords` on ``wcs`` parsed from the rounded
    header (in place); parameters without a value in ``values`` are kept, and so are SIP
    coefficients that are zero in ``wcs``.
    """
    exact = wcs_exact_parameters(wcs)
    exact["lonpole"] = values.get("LONPOLE", exact["lonpole"])
    exact["latpole"] = values.get("LATPOLE", exact["latpole"])
    for i in range(2):
        exact["crpix"][i] = values.get(f"CRPIX{i + 1}", exact["crpix"][i])
        exact["crval"][i] = values.get(f"CRVAL{i + 1}", exact["crval"][i])
        exact["cdelt"][i] = values.get(f"CDELT{i + 1}", exact["cdelt"][i])
        for j in range(2):
            exact["pc"][i][j] = values.get(f"PC{i + 1}_{j + 1}", exact["pc"][i][j])
    exact["pv"] = []  # PV values are not in the keyword form: keep the parsed ones
    for name, prefix, coeffs in _sip_items(exact):
        for p, q in zip(*np.nonzero(coeffs), strict=True):
            coeffs[p, q] = values.get(f"{prefix}_{p}_{q}", coeffs[p, q])
        exact["sip"][name] = coeffs
    apply_wcs_exact_parameters(wcs, exact)


def wcs_to_record(wcs: WCS) -> dict[str, Any]:
    """A JSON-able description of a celestial WCS from which :func:`wcs_from_record` rebuilds
    it exactly.

    ``header`` holds the ``(keyword, value)`` cards of :func:`wcs_header`; because FITS
    cards print only ~14 significant digits, ``exact`` repeats the numerical parameters
    (:func:`wcs_exact_parameters`) at full double precision. Lookup-table distortions are
    not representable and are refused.
    """
    if (
        wcs.cpdis1 is not None
        or wcs.cpdis2 is not None
        or wcs.det2im1 is not None
        or (wcs.det2im2 is not None)
    ):
        raise ValueError("WCS lookup-table distortions (CPDIS/DET2IM) cannot be stored")
    header = wcs_header(wcs)
    exact = wcs_exact_parameters(wcs)
    return {"header": [[card.keyword, card.value] for card in header.cards], "exact": exact}


def wcs_from_record(record: dict[str, Any]) -> WCS:
    """Rebuild the WCS described by :func:`wcs_to_record` (bit-exact parameters)."""
    header = fits.Header([(str(key), value) for key, value in record["header"]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        wcs = WCS(header, relax=True)
    apply_wcs_exact_parameters(wcs, record["exact"])
    return wcs


#: Names of the SIP coefficient matrices in :func:`wcs_exact_parameters`.
_SIP_NAMES = ("a", "b", "ap", "bp")


def _sip_items(exact: dict[str, Any]) -> Iterator[tuple[str, str, np.ndarray]]:
    """``(name, keyword prefix, float64 copy)`` of each SIP matrix present in ``exact``."""
    sip = exact["sip"]
    if sip is None:
        return
    for name in _SIP_NAMES:
        if sip[name] is not None:
            yield name, name.upper(), np.array(sip[name], dtype=float)


def _as_int(field: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InvalidCoaddError(f"{field} must be an integer, got {value!r}")
    return int(value)


def _as_index(index: Sequence[int]) -> tuple[int, int]:
    try:
        cx, cy = index
    except (TypeError, ValueError):
        raise InvalidCoaddError(f"index must be a pair (cx, cy), got {index!r}") from None
    return (_as_int("index[0]", cx), _as_int("index[1]", cy))


def _float_array(cell: str, field: str, value: Any, dtype: type[np.floating]) -> np.ndarray:
    array = np.asarray(value)
    if array.dtype.kind != "f":
        raise InvalidCoaddError(f"{cell}: {field} must be a float array, got dtype {array.dtype}")
    # Same-kind conversion; a native float32 input is kept as is (bits untouched).
    return np.asarray(array, dtype=dtype)


def _float_plane(
    cell: str, field: str, value: Any, shape: tuple[int, int], dtype: type[np.floating]
) -> np.ndarray:
    array = _float_array(cell, field, value, dtype)
    if array.shape != shape:
        raise InvalidCoaddError(
            f"{cell}: {field} must have the outer-box shape {shape}, got {array.shape}"
        )
    return array


def _mask_plane(cell: str, value: Any, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(value)
    if array.dtype.kind not in "iu":
        raise InvalidCoaddError(f"{cell}: mask must be an integer array, got dtype {array.dtype}")
    if array.shape != shape:
        raise InvalidCoaddError(
            f"{cell}: mask must have the outer-box shape {shape}, got {array.shape}"
        )
    if array.dtype != np.int32 and array.size:
        info = np.iinfo(np.int32)
        if array.min() < info.min or array.max() > info.max:
            raise InvalidCoaddError(f"{cell}: mask values do not fit in int32")
    return np.asarray(array, dtype=np.int32)


def _check_wcs(cell: str, wcs: Any) -> WCS:
    if not isinstance(wcs, WCS) or wcs.naxis != 2 or not wcs.has_celestial:
        raise InvalidCoaddError(f"{cell}: wcs must be a 2-axis celestial astropy.wcs.WCS")
    return wcs
