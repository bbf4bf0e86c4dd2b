"""The in-memory coadd of one cell: pixel planes, PSF, inputs, identity and WCS.

Array conventions
-----------------
Every plane covers the cell's *outer* box: ``plane[j, i]`` is tract pixel
``(outer_bbox.x_start + i, outer_bbox.y_start + j)``, and ``wcs`` maps array pixel
``(0, 0)`` (0-based, pixel centres at integers) to that tract pixel's sky position.

* ``image``: surface brightness in the patch's unit (``PatchMetadata.units``: nJy, or
  counts at ``PatchMetadata.zero_point``) per coadd pixel, float32.
* ``mask``: int32 bit mask, bits named by the patch's :class:`~cellcoadd.model.maskbits.MaskBits`.
* ``variance``: per-pixel variance of ``image`` (the unit squared), float32.
* ``noise``: ``K`` noise realizations coadded exactly like the image, float32, ``(K, ny, nx)``.
* ``mfrac``: fraction of the coadd weight that came from masked input pixels, float32.
* ``psf``: odd square float64 stamp of the coadd PSF at the cell centre (pixel response
  included), centred on its central pixel, summing to 1.
* ``psf_corners``: optional (None when the build did not ask for it, and in files before
  format 1.4), float64 ``(4, n, n)``: the coadd PSF at the 4 corner pixels of the inner
  box, like ``psf`` (:data:`~cellcoadd.model.planes.CORNER_ORDER`);
  :meth:`CellCoadd.psf_at` interpolates the PSF between them and the centre.
* ``psf_phase``, ``psf_maps``: optional (None when the build did not ask for them, and in
  files before format 1.5), ``(n_used, m, m)`` float32 and ``(n_used, 8)`` float64: each
  used input's effective PSF oversampled around the cell centre, and its phase, affine
  map, area ratio and weight (:mod:`cellcoadd.model.psf_phase`), in the order of the used
  input records; :meth:`CellCoadd.psf_at` renders with them the PSF of a star at any
  pixel, at the phase where each input meets it.

A cell with no used input is *empty*: every float plane is NaN, the mask has ``NO_DATA``
set everywhere (checked by :class:`~cellcoadd.model.patch_coadd.PatchCoadd`) and its
rejected inputs are still listed. :meth:`CellCoadd.empty` builds one.

:meth:`CellCoadd.to_nddata` gives an ``astropy.nddata.CCDData`` (unit, WCS, boolean mask,
``VarianceUncertainty``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np
from astropy.wcs import WCS

from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError, InvalidCoaddError
from cellcoadd.geometry.box import Box
from cellcoadd.model.cell_common import CellCommon
from cellcoadd.model.inputs import InputRecord
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.planes import CORNER_ORDER, grid_plane_names, plane_names
from cellcoadd.model.psf_phase import MAP_FIELDS, PHASE_SIDE, PhaseRenderer
from cellcoadd.model.units import mask_plane_cards
from cellcoadd.model.wcs_codec import wcs_to_record

#: Tolerance on ``|sum(psf) - 1|`` for a non-empty cell.
PSF_SUM_TOLERANCE = 1e-6


class CellPlanes(NamedTuple):
    """Views of a cell's planes cut to a sub-box (the inner box, for :attr:`CellCoadd.inner`).

    One field per plane on the cell grid (:func:`~cellcoadd.model.planes.grid_plane_names`).
    """

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
    psf_corners : ndarray, shape ``(4, n, n)``, optional
        PSF stamps at the inner box's corner pixels, in the order of
        :data:`~cellcoadd.model.planes.CORNER_ORDER` (float, converted to float64); each
        sums to 1 unless the cell is empty. None (the default): not built.
    psf_phase, psf_maps : ndarray, optional
        Each used input's phase term, shapes ``(n_used, m, m)`` and ``(n_used, 8)``
        (:mod:`cellcoadd.model.psf_phase`; converted to float32 and float64); both or
        neither. None (the default): not built.
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
    common : CellCommon, optional
        What the cell shares with its patch (unit, zero point, band, mask-bit names, patch
        and sky map). Set on every cell of a :class:`~cellcoadd.model.patch_coadd.PatchCoadd`
        and on a cell read alone; None for a cell made on its own. Not part of
        :meth:`equals` (it describes the patch, not the cell's contents).

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
        common: CellCommon | None = None,
        psf_corners: np.ndarray | None = None,
        psf_phase: np.ndarray | None = None,
        psf_maps: np.ndarray | None = None,
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
        self.psf_corners: np.ndarray | None = None
        if psf_corners is not None:
            corners = _float_array(name, "psf_corners", psf_corners, np.float64)
            if corners.shape != (len(CORNER_ORDER), *self.psf.shape):
                raise InvalidCoaddError(
                    f"{name}: psf_corners must have shape (4, n, n) with the psf's n = "
                    f"{self.psf.shape[0]}, got {corners.shape}"
                )
            self.psf_corners = corners
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
        self.psf_phase: np.ndarray | None = None
        self.psf_maps: np.ndarray | None = None
        # psf_at's renders of the phase terms at the stored stamps (made on first use)
        self._phase_renderer: tuple[tuple[object, ...], PhaseRenderer] | None = None
        if (psf_phase is None) != (psf_maps is None):
            raise InvalidCoaddError(f"{name}: psf_phase and psf_maps go together")
        if psf_phase is not None and psf_maps is not None:
            self.psf_phase = _float_array(name, "psf_phase", psf_phase, np.float32)
            self.psf_maps = _float_array(name, "psf_maps", psf_maps, np.float64)
            n_used = self.n_used
            if self.psf_phase.shape != (n_used, PHASE_SIDE, PHASE_SIDE) or (
                self.psf_maps.shape != (n_used, len(MAP_FIELDS))
            ):
                raise InvalidCoaddError(
                    f"{name}: psf_phase and psf_maps must have shapes ({n_used}, {PHASE_SIDE}, "
                    f"{PHASE_SIDE}) and ({n_used}, {len(MAP_FIELDS)}) for its {n_used} used "
                    f"inputs, got {self.psf_phase.shape} and {self.psf_maps.shape}"
                )
        self.wcs = _check_wcs(name, wcs)
        self.common: CellCommon | None = None
        if common is not None:
            self.attach(common)
        if self.is_empty:
            if not np.isnan(self.image).all():
                raise InvalidCoaddError(
                    f"{name}: an empty cell (no used input) must have a NaN image"
                )
        else:
            total = float(np.sum(self.psf))
            if not abs(total - 1.0) <= PSF_SUM_TOLERANCE:
                raise InvalidCoaddError(f"{name}: psf must sum to 1 (got {total!r})")
            if self.psf_corners is not None:
                sums = np.sum(self.psf_corners, axis=(1, 2))
                if not np.all(np.abs(sums - 1.0) <= PSF_SUM_TOLERANCE):
                    raise InvalidCoaddError(
                        f"{name}: each psf_corners stamp must sum to 1 (got {sums.tolist()})"
                    )

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
        common: CellCommon | None = None,
        psf_corners: bool = False,
        psf_phase: bool = False,
    ) -> CellCoadd:
        """A cell with no used input: NaN planes and PSF, ``NO_DATA`` everywhere in the mask.

        ``inputs`` lists the rejected inputs (none may be used); ``mask_bits`` default to
        ``common``'s; ``psf_corners``: give it NaN corner stamps too (a build that draws
        them), else None; ``psf_phase``: give it empty phase terms (a build that stores
        them), else None.
        """
        if mask_bits is None and common is not None:
            mask_bits = common.mask_bits
        bits = mask_bits if mask_bits is not None else MaskBits()
        shape = outer_bbox.shape
        return cls(
            image=np.full(shape, np.nan, dtype=np.float32),
            mask=np.full(shape, bits.value("NO_DATA"), dtype=np.int32),
            variance=np.full(shape, np.nan, dtype=np.float32),
            noise=np.full((n_noise, *shape), np.nan, dtype=np.float32),
            mfrac=np.full(shape, np.nan, dtype=np.float32),
            psf=np.full((psf_size, psf_size), np.nan, dtype=np.float64),
            psf_corners=(
                np.full((len(CORNER_ORDER), psf_size, psf_size), np.nan) if psf_corners else None
            ),
            psf_phase=np.zeros((0, PHASE_SIDE, PHASE_SIDE), np.float32) if psf_phase else None,
            psf_maps=np.zeros((0, len(MAP_FIELDS))) if psf_phase else None,
            inputs=inputs,
            tract=tract,
            index=index,
            inner_bbox=inner_bbox,
            outer_bbox=outer_bbox,
            wcs=wcs,
            common=common,
        )

    def attach(self, common: CellCommon) -> None:
        """Give the cell its patch's common components (its tract must match)."""
        if not isinstance(common, CellCommon):
            raise InvalidCoaddError(
                f"cell {self.index}: common must be a CellCommon, got {type(common).__name__}"
            )
        if common.tract != self.tract:
            raise InvalidCoaddError(
                f"cell {self.index} is in tract {self.tract}, its common components say "
                f"{common.tract}"
            )
        self.common = common

    @property
    def n_used(self) -> int:
        """Number of inputs that contributed."""
        return sum(record.is_used for record in self.inputs)

    @property
    def n_noise(self) -> int:
        """Number ``K`` of noise realizations."""
        return int(self.noise.shape[0])

    @property
    def plane_names(self) -> tuple[str, ...]:
        """Names of the planes this cell holds, in storage order: every plane of
        :data:`~cellcoadd.model.planes.PLANES` but the optional ones it lacks (None)."""
        return tuple(name for name in plane_names() if getattr(self, name) is not None)

    @property
    def psf_centre(self) -> tuple[int, int]:
        """Array pixel ``(x, y)`` of the cell centre, where :attr:`psf` is centred:
        ``(nx // 2, ny // 2)`` of the outer box."""
        ny, nx = self.shape
        return nx // 2, ny // 2

    @property
    def psf_corner_positions(self) -> np.ndarray:
        """Array pixels ``(x, y)`` (shape (4, 2), integers) where the stamps of
        :attr:`psf_corners` are centred: the inner box's corner pixels, in the order of
        :data:`~cellcoadd.model.planes.CORNER_ORDER`."""
        rows, cols = self.inner_bbox.slices_in(self.outer_bbox)
        xs, ys = (cols.start, cols.stop - 1), (rows.start, rows.stop - 1)
        return np.array([(xs[i], ys[j]) for i, j in CORNER_ORDER], dtype=np.int64)

    def psf_at(self, x: float, y: float, *, extrapolate: bool = False) -> np.ndarray:
        """The coadd PSF of a point source at array pixel ``(x, y)``.

        Parameters
        ----------
        x, y : float
            Position in the cell's array pixel coordinates, pixels: ``plane[j, i]`` is
            pixel ``(x, y) = (i, j)``, 0-based over the outer box, pixel centres at
            integers (tract pixel ``(x + outer_bbox.x_start, y + outer_bbox.y_start)``, and
            :attr:`wcs` maps ``(x, y)`` to the sky).
        extrapolate : bool
            Allow positions outside the inner box (anywhere in the outer box), where the
            interpolation extrapolates; by default those are refused.

        Returns
        -------
        ndarray, shape ``psf.shape``, float64
            The PSF image (pixel response included), centred on the stamp's central pixel
            like :attr:`psf`, normalised to unit sum (NaN for an empty cell). At a pixel
            centre it is the coadded image of a star there; at a sub-pixel position it is
            the image a star would have on the stamp's central pixel with the phases at
            which the inputs meet ``(x, y)`` (the sub-pixel shift itself is not applied).

        Raises
        ------
        CellCoaddValueError
            When the cell has neither :attr:`psf_corners` nor :attr:`psf_phase` (built
            without ``BuildConfig(psf_corners=True)`` or ``psf_phase=True``, or read from a
            file before format 1.4).
        CellCoaddRangeError
            When ``(x, y)`` lies outside the inner box (pixel edges included) and
            ``extrapolate`` is false, or outside the outer box.

        Notes
        -----
        Two parts. *Where* the PSF models vary across the cell: the centre stamp alone,
        or with :attr:`psf_corners` the stamps combined with the weights of
        :func:`psf_interpolation_weights` (bilinear between the corners plus a quadratic
        "bubble" through the centre, exact for a PSF varying as ``a + b x + c y + d x y +
        e (x^2 + y^2)``). *How each input is resampled there*: with :attr:`psf_phase`, each
        used input's stored core rendered at its phase at ``(x, y)`` minus the same
        rendered at the stamps' positions (:func:`~cellcoadd.model.psf_phase.phase_correction`),
        so the interpolated stamps lose their own phases' pattern and take that of
        ``(x, y)``; without it that pattern, ~1e-3 to 1e-2 in size and shape on
        undersampled inputs, is not followed. Accuracy and cost: ``docs/shear.md``.
        """
        if self.psf_corners is None and self.psf_phase is None:
            raise CellCoaddValueError(
                f"cell {self.index} of tract {self.tract} has neither psf_corners nor "
                "psf_phase (built without BuildConfig(psf_corners=True) or psf_phase=True, "
                "or read from a file before format 1.4): psf_at needs them; cell.psf is "
                "the PSF at the centre",
                cell=self.index,
            )
        if extrapolate:
            ny, nx = self.shape
            low, high = (-0.5, -0.5), (nx - 0.5, ny - 0.5)
            where = "outer"
        else:
            rows, cols = self.inner_bbox.slices_in(self.outer_bbox)
            low, high = (cols.start - 0.5, rows.start - 0.5), (cols.stop - 0.5, rows.stop - 0.5)
            where = "inner"
        for axis, value, lo, hi in (("x", x, low[0], high[0]), ("y", y, low[1], high[1])):
            if not lo <= value <= hi:
                raise CellCoaddRangeError(
                    f"cell {self.index} of tract {self.tract}: {axis} = {value} is outside the "
                    f"{where} box [{lo}, {hi}] (array pixels)"
                    + ("" if extrapolate else "; extrapolate=True allows the outer box"),
                    value=value,
                    low=lo,
                    high=hi,
                    cell=self.index,
                )
        xc, yc = self.psf_centre
        if self.psf_corners is None:
            weights = np.ones(1)
            positions = [(float(xc), float(yc))]
            stamp = self.psf.copy()
        else:
            weights = psf_interpolation_weights(
                float(x), float(y), self.psf_centre, self.psf_corner_positions
            )
            positions = [(float(xc), float(yc))]
            positions += [(float(px), float(py)) for px, py in self.psf_corner_positions]
            stamp = weights[0] * self.psf + np.tensordot(weights[1:], self.psf_corners, axes=1)
        if self.psf_phase is not None and self.psf_maps is not None and not self.is_empty:
            renderer = self._phase_renderer
            # the stamps' positions and the arrays rendered: a changed plane is rendered anew
            references = [(px - xc, py - yc) for px, py in positions]
            key = (tuple(references), self.psf_phase, self.psf_maps)
            if renderer is None or not (
                renderer[0][0] == key[0] and renderer[0][1] is key[1] and renderer[0][2] is key[2]
            ):
                renderer = (
                    key,
                    PhaseRenderer(self.psf_phase, self.psf_maps, references, self.psf.shape[0]),
                )
                self._phase_renderer = renderer  # kept: each further position costs less
            stamp = stamp + renderer[1].correction((float(x) - xc, float(y) - yc), weights)
        return stamp / stamp.sum()

    @property
    def psf_flux_outside(self) -> float:
        """Fraction of the coadd PSF's flux that falls outside the ``psf`` stamp.

        The weighted mean of the used inputs' ``psf_flux_outside`` (with their coadd
        weights, as the coadd PSF is their weighted mean): the stamp holds ``1 - f`` of
        the flux and was renormalised to unit sum. NaN for an empty cell or inputs
        recorded without it (files before format 1.3).
        """
        used = [r for r in self.inputs if r.is_used]
        if not used:
            return float("nan")
        weights = np.array([r.weight for r in used])
        values = np.array([r.psf_flux_outside for r in used])
        return float(np.sum(weights * values) / np.sum(weights))

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
        # the last two axes are the pixels' (per-realization planes lead with K)
        return CellPlanes(
            **{name: getattr(self, name)[..., rows, cols] for name in grid_plane_names()}
        )

    def to_nddata(
        self,
        unit: Any = None,
        *,
        mask_bits: MaskBits | None = None,
        bad_bits: Iterable[str] | None = None,
        inner: bool = False,
        zero_point: float | None = None,
    ) -> Any:
        """The cell as an ``astropy.nddata.CCDData`` (an ``NDData``) for astropy tools.

        Parameters
        ----------
        unit : str or astropy.units.Unit, optional
            Unit of the image; by default the cell's own (:attr:`common`, which every cell
            of a patch and every cell read from a file has). A cell without common
            components needs it.
        mask_bits : MaskBits, optional
            Names of the mask bits (default: the cell's own, else :class:`MaskBits`); they
            go into ``meta`` as ``MP_<NAME> = bit`` and name ``bad_bits``.
        bad_bits : iterable of str, optional
            Bits that make a pixel masked; default: any bit.
        inner : bool
            Cut to the inner box (default: the outer box, like the planes).
        zero_point : float, optional
            AB zero point of counts, written to ``meta["MAGZERO"]`` (not for nJy); by
            default the cell's own.

        Returns
        -------
        astropy.nddata.CCDData
            ``data``: a copy of the image (float32); ``unit``; ``wcs``: :attr:`wcs` (or
            its shift to the inner box), so ``nddata.wcs`` maps ``data[j, i]`` to the sky
            like the cell; ``uncertainty``: ``VarianceUncertainty`` of the variance plane
            (unit squared); ``mask``: boolean, **True where a pixel is flagged** (astropy's
            convention: it has any of ``bad_bits``); the integer bit mask stays in
            :attr:`mask`. ``meta`` (an ``astropy.io.fits.Header``): ``TRACT``, ``CELL_X``,
            ``CELL_Y``, ``MP_<NAME> = bit`` (upper-case ASCII names), for counts
            ``MAGZERO``, and from the common components ``PATCH_X``, ``PATCH_Y``,
            ``FILTER`` (JSON-escaped to ASCII) and ``SKYMAP``. Noise realizations, ``mfrac``
            and the PSF are not included.

        Raises
        ------
        InvalidCoaddError
            No ``unit`` given and the cell has no common components.
        """
        import astropy.units as u
        from astropy.io import fits
        from astropy.nddata import CCDData, VarianceUncertainty

        from cellcoadd.geometry.wcs_utils import shifted_wcs

        common = self.common
        if unit is None:
            if common is None:
                raise InvalidCoaddError(
                    f"cell {self.index} has no unit of its own (it was not read from a file "
                    "or taken from a patch): pass unit="
                )
            unit = common.units
        unit = u.Unit(unit)
        if zero_point is None and common is not None and unit == common.unit:
            zero_point = common.zero_point
        if mask_bits is None and common is not None:
            mask_bits = common.mask_bits
        bits = mask_bits if mask_bits is not None else MaskBits()
        if inner:
            planes = self.inner
            image, variance, mask = planes.image, planes.variance, planes.mask
            outer = self.outer_bbox
            wcs = shifted_wcs(
                self.wcs,
                self.inner_bbox.x_start - outer.x_start,
                self.inner_bbox.y_start - outer.y_start,
            )
        else:
            image, variance, mask = self.image, self.variance, self.mask
            wcs = self.wcs.deepcopy()
        flagged = mask != 0 if bad_bits is None else (mask & bits.mask_of(bad_bits)) != 0
        # a FITS header, so CCDData.write keeps the long (HIERARCH) MP_* keywords
        meta = fits.Header()
        meta["TRACT"], meta["CELL_X"], meta["CELL_Y"] = self.tract, *self.index
        if zero_point is not None and unit != u.nJy:
            meta["MAGZERO"] = (float(zero_point), "[mag] AB zero point of the pixel values")
        for key, bit, comment in mask_plane_cards(bits.bits):
            meta[f"HIERARCH {key}" if len(key) > 8 else key] = (bit, comment)
        if common is not None:
            meta["PATCH_X"], meta["PATCH_Y"] = common.patch
            meta["FILTER"] = json.dumps(common.band, ensure_ascii=True)[1:-1]
            if common.skymap:
                meta["SKYMAP"] = common.skymap
        return CCDData(
            np.array(image),
            unit=unit,
            wcs=wcs,
            mask=flagged,
            uncertainty=VarianceUncertainty(np.array(variance), unit=unit**2),
            meta=meta,
        )

    def equals(self, other: object) -> bool:
        """Whether ``other`` is the same cell bit for bit.

        Arrays must have equal dtypes, shapes and bytes (so NaN payloads and -0.0 count),
        inputs must be :meth:`~cellcoadd.model.inputs.InputRecord.identical`, and identity,
        boxes and WCS (:func:`~cellcoadd.model.wcs_codec.wcs_to_record`) equal.
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
        for name in plane_names():
            mine, theirs = getattr(self, name), getattr(other, name)
            if mine is None or theirs is None:  # an optional plane
                if mine is not theirs:
                    return False
            elif not arrays_identical(mine, theirs):
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


def psf_interpolation_weights(
    x: float, y: float, centre: tuple[float, float], corners: np.ndarray
) -> np.ndarray:
    """Weights of the centre and corner PSFs for the PSF at ``(x, y)``
    (:meth:`CellCoadd.psf_at`).

    Parameters
    ----------
    x, y : float
        The position (any pixel coordinates, the same as the others').
    centre : (float, float)
        ``(xc, yc)``, the position of the centre stamp, strictly inside the corners' box.
    corners : ndarray, shape (4, 2)
        ``(x, y)`` of the corner stamps in the order of
        :data:`~cellcoadd.model.planes.CORNER_ORDER`: ``(x0, y0), (x1, y0), (x0, y1),
        (x1, y1)``.

    Returns
    -------
    ndarray, shape (5,)
        Weights of the centre, then of the 4 corners; they sum to 1.

    Notes
    -----
    With ``u = (x - x0) / (x1 - x0)``, ``v`` likewise, the bilinear weights of the corners
    are ``B = ((1-u)(1-v), u(1-v), (1-u)v, uv)``. The bubble
    ``b = (qx + qy) / 2``, ``qx = (x - x0)(x1 - x) / ((xc - x0)(x1 - xc))`` (``qy``
    likewise), is 1 at the centre and 0 at the corners; the weights are ``b`` for the
    centre and ``B(x, y) - b B(xc, yc)`` for the corners. At the centre they give the
    centre stamp alone, at a corner that corner's; they interpolate exactly any
    ``a + b x + c y + d x y + e (x^2 + y^2)`` when the corners' box is square (the cells'
    inner box), as a PSF's size varies over a focal plane to second order. Corner weights
    may be negative (then the interpolated stamp is still normalised to unit sum).
    """
    (x0, y0), (x1, y1) = corners[0], corners[3]
    xc, yc = centre

    def bilinear(px: float, py: float) -> np.ndarray:
        u, v = (px - x0) / (x1 - x0), (py - y0) / (y1 - y0)
        return np.array([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v])

    qx = (x - x0) * (x1 - x) / ((xc - x0) * (x1 - xc))
    qy = (y - y0) * (y1 - y) / ((yc - y0) * (y1 - yc))
    bubble = 0.5 * (qx + qy)
    return np.concatenate(([bubble], bilinear(x, y) - bubble * bilinear(xc, yc)))


def arrays_identical(first: np.ndarray, second: np.ndarray) -> bool:
    """Whether two arrays have the same dtype, shape and bytes (NaN payloads, -0.0 included)."""
    return (
        first.dtype == second.dtype
        and first.shape == second.shape
        and first.tobytes() == second.tobytes()
    )


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
