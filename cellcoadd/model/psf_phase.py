"""The coadd PSF at any position of a cell: each input's resampling phase, rendered again.

Why
---
A star at coadd pixel ``(x, y)`` falls at exposure position ``p_i = M_i(x, y)`` of each
input ``i``; its coadded image is ``sum_i w_i warp_i(E_i sampled at phase frac(p_i)) /
sum_i w_i`` where ``E_i`` is the input's effective PSF (pixel included) and ``warp_i`` the
image's normalised Lanczos-3 resampling. For a PSF that is not band-limited at the
exposure's sampling (any real one, badly so at DECam's 0.263"), the warped stamp depends
on the phase: ~1e-3 to 1e-2 in size and shape, a pattern that changes every coadd pixel
(the phase moves by ~0.76 exposure pixels per coadd pixel at 0.2"), which no spatial
interpolation of a few coadd PSF stamps can follow.

What is stored
--------------
Per cell and used input, in the order of the cell's used input records:

* ``psf_phase`` ``(n_used, m, m)`` float32: the input's effective PSF near the cell (the
  builder draws it once per exposure and 256-pixel square, at the square's centre, for
  the cells there: the model's change over half a square scales the phase term by
  ~1e-2 at most), sampled every ``1 / PHASE_OVERSAMPLING`` exposure
  pixels over ``[-PHASE_HALF, PHASE_HALF]`` exposure pixels in each axis around the
  source (``m = 2 PHASE_HALF PHASE_OVERSAMPLING + 1``; ``[j, i]`` is the offset
  ``((i - c) / N, (j - c) / N)``, ``c = (m - 1) / 2``), per unit exposure-pixel area
  (values at whole-pixel offsets are the pixels of a star drawn there);
* ``psf_maps`` ``(n_used, 8)`` float64: :data:`MAP_FIELDS`: the fractional part of the
  exposure position of the cell-centre pixel, the affine map from coadd to exposure
  pixels across the inner box (least squares over the cell's mapping), the pixel-area
  ratio and the input's weight.

How it is used
--------------
:func:`phase_correction` renders each input's term at the phases of a requested position
and of the stored stamps (:attr:`CellCoadd.psf` and its corners), warping with the same
kernel, and returns the weighted difference. Added to the stamps' spatial interpolation it
gives the coadd PSF of a star at that position; only the phase-dependent *difference*
comes from this compact model (the wings, well sampled, change with the phase by far less),
so its truncation and interpolation errors enter at second order. Each render is of a
unit-flux source (the core's pixels at that phase summed to 1), as a PSF model draws one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Samples per exposure pixel of the stored effective PSF.
PHASE_OVERSAMPLING = 4
#: Half side of the stored effective PSF, exposure pixels (its core: beyond it the PSF is
#: well sampled and its warp changes with the phase far below 1e-4).
PHASE_HALF = 8
#: Side of a stored effective PSF, samples.
PHASE_SIDE = 2 * PHASE_HALF * PHASE_OVERSAMPLING + 1
#: Columns of ``psf_maps``: phase ``(fx, fy)`` of the cell-centre pixel in exposure pixels;
#: ``a_xx = dx_exp/dx``, ``a_xy = dx_exp/dy``, ``a_yx``, ``a_yy``; the area ratio (coadd
#: pixel area over exposure pixel area); the weight.
MAP_FIELDS = ("fx", "fy", "a_xx", "a_xy", "a_yx", "a_yy", "area", "weight")
#: Exposure pixels over which the rendered core is tapered to zero at its edge.
_TAPER = 2.0


def _lanczos3(t: np.ndarray) -> np.ndarray:
    """``sinc(t) sinc(t / 3)`` for ``|t| < 3``, else 0."""
    return np.where(np.abs(t) < 3.0, np.sinc(t) * np.sinc(t / 3.0), 0.0)


def _axis_weights(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First tap ``floor(u) - 2`` and the 6 normalised Lanczos-3 weights along one axis
    (as the image's warp: :mod:`cellcoadd.builder.kernels.warp`)."""
    base = np.floor(u)
    frac = u - base
    near = np.abs(frac - np.round(frac)) < 1e-9
    frac = np.where(near, np.round(frac), frac)
    base = base + np.where(frac >= 1.0, 1.0, 0.0)
    frac = np.where(frac >= 1.0, 0.0, frac)
    offsets = np.arange(-2, 4, dtype=np.float64)
    weights = _lanczos3(frac[:, None] - offsets[None, :])
    weights /= weights.sum(axis=1, keepdims=True)
    return base.astype(np.int64) - 2, weights


def prefiltered(core: np.ndarray) -> np.ndarray:
    """``core`` as the cubic B-spline coefficients :func:`render_input` interpolates
    (computed once per core, e.g. for many positions of one cell)."""
    from scipy import ndimage

    return np.asarray(ndimage.spline_filter(np.asarray(core, dtype=np.float64), order=3))


def render_input(
    core: np.ndarray,
    row: np.ndarray,
    phase: tuple[float, float],
    size: int,
    *,
    is_prefiltered: bool = False,
) -> np.ndarray:
    """One input's PSF on the coadd grid for a source at exposure phase ``phase``.

    Parameters
    ----------
    core : ndarray, shape (m, m)
        The input's stored effective PSF (``psf_phase``).
    row : ndarray, shape (8,)
        Its ``psf_maps`` row (:data:`MAP_FIELDS`).
    phase : (float, float)
        Sub-pixel position ``(fx, fy)`` of the source in the exposure, pixels in [0, 1).
    size : int
        Side of the coadd stamp (odd), centred on the source's coadd pixel.
    is_prefiltered : bool
        ``core`` is already :func:`prefiltered`.

    Returns
    -------
    ndarray, shape (size, size)
        The source's warped image times the area ratio (unit flux, unweighted), zero
        beyond the core.
    """
    from scipy import ndimage  # only where a PSF is rendered: importing the model stays cheap

    n = PHASE_OVERSAMPLING
    half = PHASE_HALF
    fx, fy = phase
    # the exposure pixels around the source (pixel 0 holds it at offset (fx, fy))
    k = np.arange(-half, half + 1, dtype=np.float64)
    centre = (core.shape[0] - 1) / 2.0
    ix = (k[None, :] - fx) * n + centre
    iy = (k[:, None] - fy) * n + centre
    grid_y, grid_x = np.broadcast_arrays(iy, ix)
    coefficients = core if is_prefiltered else prefiltered(core)
    pixels = ndimage.map_coordinates(
        coefficients, [grid_y, grid_x], order=3, mode="constant", cval=0.0, prefilter=False
    )
    # a point source of unit flux at every phase, as a PSF model draws it (a model
    # sampled on its own grid, e.g. PSFEx, sums to 1 only within ~0.5% at other phases)
    total = pixels.sum()
    if total > 0:
        pixels /= total
    # a smooth edge: the truncated core must not ring differently at each phase
    distance = np.maximum(np.abs(k[None, :] - fx), np.abs(k[:, None] - fy))
    taper = np.clip((half - distance) / _TAPER, 0.0, 1.0)
    pixels *= 0.5 - 0.5 * np.cos(np.pi * taper)
    # the coadd stamp's pixels in the exposure, relative to pixel 0
    a = row[2:6].reshape(2, 2)
    offsets = np.arange(size, dtype=np.float64) - size // 2
    dx, dy = (v.ravel() for v in np.meshgrid(offsets, offsets))
    ux = fx + a[0, 0] * dx + a[0, 1] * dy
    uy = fy + a[1, 0] * dx + a[1, 1] * dy
    x0, wx = _axis_weights(ux)
    y0, wy = _axis_weights(uy)
    taps = np.arange(6)
    cols = x0[:, None] + taps[None, :] + half  # index into pixels
    rows = y0[:, None] + taps[None, :] + half
    side = 2 * half + 1
    col_ok = (cols >= 0) & (cols < side)
    row_ok = (rows >= 0) & (rows < side)
    safe_rows, safe_cols = np.clip(rows, 0, side - 1), np.clip(cols, 0, side - 1)
    gathered = pixels[safe_rows[:, :, None], safe_cols[:, None, :]]
    gathered = gathered * (row_ok[:, :, None] & col_ok[:, None, :])
    out = np.einsum("pi,pij,pj->p", wy, gathered, wx)
    return (out * row[6]).reshape(size, size)


def input_phase(row: np.ndarray, dx: float, dy: float) -> tuple[float, float]:
    """Exposure phase ``(fx, fy)`` in [0, 1) of the position ``(dx, dy)`` coadd pixels from
    the cell-centre pixel, through the input's affine map (its ``psf_maps`` row)."""
    px = row[0] + row[2] * dx + row[3] * dy
    py = row[1] + row[4] * dx + row[5] * dy
    return float(px - np.floor(px)), float(py - np.floor(py))


class PhaseRenderer:
    """The phase terms of one cell, ready to render at many positions.

    Keeps each input's :func:`prefiltered` core and its renders at the stored stamps'
    positions (``references``, offsets from the cell-centre pixel), which every position
    subtracts: a position then costs one render per input.
    """

    def __init__(
        self,
        cores: np.ndarray,
        maps: np.ndarray,
        references: Sequence[tuple[float, float]],
        size: int,
    ) -> None:
        self.maps = np.asarray(maps, dtype=np.float64)
        self.size = size
        self.cores = [prefiltered(core) for core in cores]
        self.references = np.array(
            [
                [
                    render_input(core, row, input_phase(row, rx, ry), size, is_prefiltered=True)
                    for rx, ry in references
                ]
                for core, row in zip(self.cores, self.maps, strict=True)
            ]
        ).reshape(len(self.cores), len(references), size, size)

    def correction(self, offset: tuple[float, float], reference_weights: np.ndarray) -> np.ndarray:
        """:func:`phase_correction` at ``offset`` with the references interpolated with
        ``reference_weights``."""
        total = np.zeros((self.size, self.size))
        weights = self.maps[:, 7] if len(self.maps) else np.zeros(0)
        if not len(self.maps) or not weights.sum() > 0:
            return total
        for core, row, w, refs in zip(self.cores, self.maps, weights, self.references, strict=True):
            term = render_input(
                core, row, input_phase(row, *offset), self.size, is_prefiltered=True
            )
            term -= np.tensordot(reference_weights, refs, axes=1)
            total += w * term
        return total / weights.sum()


def phase_correction(
    cores: np.ndarray,
    maps: np.ndarray,
    offset: tuple[float, float],
    references: Sequence[tuple[float, float]],
    reference_weights: np.ndarray,
    size: int,
) -> np.ndarray:
    """What resampling changes between the stored stamps and a source at ``offset``.

    Parameters
    ----------
    cores, maps : ndarray
        The cell's ``psf_phase`` and ``psf_maps``.
    offset : (float, float)
        The source's position, coadd pixels from the cell-centre pixel.
    references : sequence of (float, float)
        Positions of the stored stamps (same frame), and ``reference_weights`` the weights
        with which they are interpolated at ``offset``.
    size : int
        Stamp side.

    Returns
    -------
    ndarray, shape (size, size)
        ``sum_i w_i [R_i(offset) - sum_k b_k R_i(reference_k)] / sum_i w_i``, ``R_i`` of
        :func:`render_input` at the input's phase of each position (zero without inputs).
    """
    renderer = PhaseRenderer(cores, maps, references, size)
    return renderer.correction(offset, np.asarray(reference_weights, dtype=np.float64))


__all__ = [
    "MAP_FIELDS",
    "PhaseRenderer",
    "PHASE_HALF",
    "PHASE_OVERSAMPLING",
    "PHASE_SIDE",
    "input_phase",
    "phase_correction",
    "prefiltered",
    "render_input",
]
