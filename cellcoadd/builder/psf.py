"""Drawing an exposure's PSF where a cell centre falls, with the image's sub-pixel phase."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import galsim
import numpy as np

from cellcoadd.builder.kernels.psf_render import render_cores as _render
from cellcoadd.errors import PsfError, PsfStampWarning
from cellcoadd.geometry.box import Box
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.model.psf import PSF_FLUX_TOLERANCE
from cellcoadd.model.psf_phase import PHASE_HALF, PHASE_OVERSAMPLING

#: Smallest fraction of a PSF's unit flux its drawn stamp may hold.
MIN_STAMP_FLUX = 0.5

#: Fraction of the PSF's flux outside a cell's PSF stamp above which a build warns.
PSF_FLUX_OUTSIDE_LIMIT = 1e-4


def draw_exposure_psf(exposure: Exposure, x: float, y: float, box: Box) -> np.ndarray:
    """Image of a unit-flux point source at exposure pixel ``(x, y)``, over ``box``.

    The exposure's PSF model draws itself (pixel response included, see
    :mod:`cellcoadd.model.psf`); the returned float64 array has ``box.shape`` with
    ``[0, 0]`` the pixel ``(box.x_start, box.y_start)``, so it is sampled exactly like
    the exposure's image.

    Raises
    ------
    PsfError
        When the PSF model fails or gives non-finite or zero-flux values.
    """
    stamp = np.array(exposure.draw_psf(x, y, box), dtype=np.float64)
    if stamp.shape != box.shape:
        raise PsfError(f"PSF drawn at ({x:.2f}, {y:.2f}) has shape {stamp.shape}, not {box.shape}")
    if not np.all(np.isfinite(stamp)) or stamp.sum() <= 0:
        raise PsfError(f"PSF drawn at ({x:.2f}, {y:.2f}) is non-finite or has no flux")
    # a unit-flux model that leaves much of its flux outside the coadd's PSF stamp is far
    # too large for the pixel scale (e.g. a profile in pixels taken as arcsec)
    total = float(stamp.sum())
    if not MIN_STAMP_FLUX <= total <= 1.0 + 5 * PSF_FLUX_TOLERANCE:
        raise PsfError(
            f"PSF drawn at ({x:.2f}, {y:.2f}) has {total:.4g} of its unit flux in the "
            f"{box.shape[1]} x {box.shape[0]} pixel stamp: its size or flux does not fit "
            "the exposure's pixel scale (a profile in pixels rather than arcsec?)"
        )
    return stamp


#: Side, detector pixels, of the squares of an exposure that share one oversampled PSF
#: core for the phase terms (:meth:`cellcoadd.builder.cell.CellBlock._cores`): ~2 cells of
#: 150 coadd pixels at 0.2"/px on 0.263"/px inputs; the core is drawn at its centre.
PHASE_CORE_STEP = 256

#: Spacing, detector pixels, of the nodes a varying PSF model's cores are interpolated from
#: for the corner stamps: the quadratic through 3 x 3 nodes spans 1024 pixels, over which
#: a PSF model varies smoothly (PSFEx: polynomials over the CCD), and a cell's 5 positions
#: lie within 1/4 of a spacing of its stencil's centre node.
CORE_STENCIL_STEP = 512

#: Nodes per axis of the stencil a varying PSF model's core is interpolated from at a
#: cell's PSF positions: 3, a quadratic in each axis.
CORE_STENCIL = 3


class Stencil(NamedTuple):
    """Nodes of an exposure's grid of PSF cores: node ``(bx, by)`` lies at detector pixel
    ``((bx + 1/2) step, (by + 1/2) step)``; the stencil holds the ``side`` x ``side``
    nodes from ``first``."""

    step: int
    first: tuple[int, int]
    side: int


def draw_exposure_core(exposure: Exposure, x: float, y: float) -> np.ndarray:
    """The exposure's effective PSF at exposure pixel ``(x, y)``, oversampled around the
    source as :mod:`cellcoadd.model.psf_phase` stores it (float32, ``(m, m)``,
    :meth:`~cellcoadd.model.psf.PsfModel.draw_core`).

    Raises
    ------
    PsfError
        When the model fails there or gives non-finite values or no flux.
    """
    ox, oy = exposure.origin
    core = exposure.psf_model.draw_core(
        x + ox, y + oy, exposure.local_jacobian(x, y), PHASE_HALF, PHASE_OVERSAMPLING
    )
    if not np.all(np.isfinite(core)) or not core.sum() > 0:
        raise PsfError(f"PSF core drawn at ({x:.2f}, {y:.2f}) is non-finite or has no flux")
    return core.astype(np.float32)


def core_stencil(exposure: Exposure, x: float, y: float, *, interpolate: bool = True) -> Stencil:
    """The nodes a cell centred at exposure pixel ``(x, y)`` takes its cores from.

    A constant model (:attr:`~cellcoadd.model.psf.PsfModel.constant`), or any without
    ``interpolate`` (the phase terms alone), takes the node of the :data:`PHASE_CORE_STEP`
    square holding ``(x, y)``; a varying one the :data:`CORE_STENCIL` x
    :data:`CORE_STENCIL` nodes of spacing :data:`CORE_STENCIL_STEP` centred on the node
    nearest ``(x, y)``. The stencil depends on the cell and the exposure only, so a cell
    gets the same cores in any block or process.
    """
    ox, oy = exposure.origin
    if exposure.psf_model.constant or not interpolate:
        step = PHASE_CORE_STEP
        first = (math.floor((x + ox) / step), math.floor((y + oy) / step))
        return Stencil(step, first, 1)
    step, half = CORE_STENCIL_STEP, CORE_STENCIL // 2
    first = (math.floor((x + ox) / step) - half, math.floor((y + oy) / step) - half)
    return Stencil(step, first, CORE_STENCIL)


def node_position(exposure: Exposure, step: int, bx: int, by: int) -> tuple[float, float]:
    """Exposure pixel of node ``(bx, by)`` of spacing ``step`` (:class:`Stencil`)."""
    ox, oy = exposure.origin
    return (bx + 0.5) * step - ox, (by + 0.5) * step - oy


def stencil_weights(
    exposure: Exposure, stencil: Stencil, points: Sequence[tuple[float, float]]
) -> np.ndarray:
    """Lagrange weights ``(len(points), side * side)`` of the stencil's nodes (row-major,
    ``y`` outer) at exposure pixels ``points``: the tensor product of the polynomials of
    degree ``side - 1`` through the nodes along each axis (all 1 for one node)."""
    ox, oy = exposure.origin
    step, (fx, fy), side = stencil
    xy = np.asarray(points, dtype=np.float64)
    u = (xy[:, 0] + ox) / step - 0.5 - fx
    v = (xy[:, 1] + oy) / step - 0.5 - fy
    nodes = np.arange(side, dtype=np.float64)
    along_x, along_y = _lagrange(u, nodes), _lagrange(v, nodes)  # (points, side)
    return (along_y[:, :, None] * along_x[:, None, :]).reshape(len(xy), side * side)


def _lagrange(t: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Weights ``(len(t), len(nodes))`` of the interpolating polynomial through ``nodes``
    at each of ``t``."""
    weights = np.ones((len(t), len(nodes)))
    for j, node in enumerate(nodes):
        for m, other in enumerate(nodes):
            if m != j:
                weights[:, j] *= (t - other) / (node - other)
    return weights


def local_map(
    x: np.ndarray, y: np.ndarray, area: np.ndarray, cx: int, cy: int, reach: int = 8
) -> tuple[np.ndarray, float, tuple[float, float]]:
    """The mapping at outer-box pixel ``(cx, cy)``: its Jacobian ``[[dx_exp/dx,
    dx_exp/dy], [dy_exp/dx, dy_exp/dy]]`` (central differences over ``reach`` pixels or
    as far as the box allows, so the mapping's approximation error, <= 1e-3 px, enters
    divided by the baseline), the area ratio there and the exposure phase ``(fx, fy)`` of
    the pixel, in [0, 1)."""
    ny, nx = x.shape
    rx = max(1, min(reach, cx, nx - 1 - cx))
    ry = max(1, min(reach, cy, ny - 1 - cy))
    jacobian = np.array(
        [
            [
                (x[cy, cx + rx] - x[cy, cx - rx]) / (2 * rx),
                (x[cy + ry, cx] - x[cy - ry, cx]) / (2 * ry),
            ],
            [
                (y[cy, cx + rx] - y[cy, cx - rx]) / (2 * rx),
                (y[cy + ry, cx] - y[cy - ry, cx]) / (2 * ry),
            ],
        ]
    )
    px, py = float(x[cy, cx]), float(y[cy, cx])
    return jacobian, float(area[cy, cx]), (px - math.floor(px), py - math.floor(py))


def render_cores(
    coefficients: Sequence[np.ndarray],
    maps: Sequence[tuple[np.ndarray, float, tuple[float, float]]],
    size: int,
) -> np.ndarray:
    """Unit-flux sources' images on coadd PSF stamps, each from an oversampled core.

    The same arithmetic as :func:`cellcoadd.model.psf_phase.render_input` (the core
    sampled at the source's exposure phase, normalised to unit sum, tapered to zero over
    its last 2 exposure pixels, warped with the image's normalised Lanczos-3 weights and
    scaled by the area ratio; equal to it to ~1e-15), with each position's own local map
    and area ratio, computed only on the stamp pixels the core reaches
    (:func:`~cellcoadd.builder.kernels.psf_render.render_cores`).

    Parameters
    ----------
    coefficients : sequence of ndarray, shape (m, m)
        Each core's cubic B-spline coefficients (:func:`~cellcoadd.model.psf_phase.prefiltered`).
    maps : sequence of (ndarray, float, (float, float))
        Each position's map (:func:`local_map`): the Jacobian (exposure pixels per coadd
        pixel), the area ratio (coadd pixel area over exposure pixel area) and the
        source's sub-pixel position in the exposure, pixels in [0, 1).
    size : int
        Side of the (odd) stamps, each centred on its source's coadd pixel.

    Returns
    -------
    ndarray, shape (len(maps), size, size), float64
    """
    out = np.zeros((len(maps), size, size))
    _render(
        np.stack([np.asarray(c, dtype=np.float64) for c in coefficients]),
        np.array([phase for _, _, phase in maps], dtype=np.float64),
        np.stack([np.asarray(j, dtype=np.float64) for j, _, _ in maps]),
        np.array([area for _, area, _ in maps], dtype=np.float64),
        PHASE_HALF,
        PHASE_OVERSAMPLING,
        _TAPER,
        out,
    )
    return out


#: Exposure pixels over which a rendered core is tapered to zero (as
#: :mod:`cellcoadd.model.psf_phase` does).
_TAPER = 2.0


def input_map(
    x: np.ndarray, y: np.ndarray, area: np.ndarray, inner: tuple[slice, slice], weight: float
) -> np.ndarray:
    """An input's ``psf_maps`` row (:data:`~cellcoadd.model.psf_phase.MAP_FIELDS`).

    Parameters
    ----------
    x, y, area : ndarray, shape of the cell's outer box
        Exposure positions of the coadd pixels and their area ratio (the selection's
        mapping).
    inner : (slice, slice)
        Rows and columns of the inner box in the outer box.
    weight : float
        The input's weight.

    Returns
    -------
    ndarray, shape (8,), float64
        The phase of the cell-centre pixel ``(nx // 2, ny // 2)``; the affine map from
        coadd to exposure pixels fitted (least squares, every 15th pixel) over the inner
        box with its constant at that pixel, so the centre's phase is exact; its area
        ratio; ``weight``.
    """
    ny, nx = x.shape
    cy, cx = ny // 2, nx // 2
    rows, cols = inner
    jj, ii = np.mgrid[rows.start : rows.stop : 15, cols.start : cols.stop : 15]
    design = np.stack([(ii - cx).ravel(), (jj - cy).ravel()], axis=1).astype(np.float64)
    target = np.stack([(x[jj, ii] - x[cy, cx]).ravel(), (y[jj, ii] - y[cy, cx]).ravel()], axis=1)
    affine = np.linalg.lstsq(design, target, rcond=None)[0].T  # [[xx, xy], [yx, yy]]
    px, py = float(x[cy, cx]), float(y[cy, cx])
    return np.array(
        [px - math.floor(px), py - math.floor(py), *affine.ravel(), float(area[cy, cx]), weight]
    )


def psf_moments(stamp: np.ndarray, jacobian: np.ndarray) -> dict[str, float]:
    """Adaptive second moments of a PSF stamp on the coadd's pixel grid, in arcsec.

    Parameters
    ----------
    stamp : ndarray
        The PSF as sampled on the coadd grid: for an input record, the exposure's PSF
        warped into the cell's PSF stamp (the contribution the coadd PSF averages), so
        the moments are those of the coadd's pixels, not of the exposure's axes.
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/pixel) of the coadd grid at the
        stamp (``u`` West, ``v`` North: the tract's pixel axes ``x``, ``y``).

    Returns
    -------
    dict
        ``psf_T``, ``psf_e1``, ``psf_e2``, ``psf_fwhm``; all NaN when the moments fail.

    Notes
    -----
    GalSim HSM adaptive (elliptical-Gaussian-weighted) moments ``M`` (pixel^2), which are
    the unweighted second moments for a Gaussian, taken to the sky by the Jacobian,
    ``Ms = J M J^T`` (arcsec^2), then

    * ``psf_T = Ms_uu + Ms_vv`` (arcsec^2): ``T = Ixx + Iyy``, ``2 sigma^2`` for a round
      Gaussian of standard deviation ``sigma``;
    * ``psf_e1 = (Ms_uu - Ms_vv) / T``, ``psf_e2 = 2 Ms_uv / T``: *distortions*
      (``|e| = (a^2 - b^2) / (a^2 + b^2)`` for axes ``a >= b``), not reduced shears
      (``|g| = (a - b) / (a + b)``), in the frame ``u`` West, ``v`` North (which is the
      coadd's ``x``, ``y`` pixel frame; ``e2`` changes sign in an East-North frame);
    * ``psf_fwhm = 2 sqrt(2 ln 2) det(Ms)^(1/4)`` (arcsec): the FWHM of the round Gaussian
      of the same determinant.
    """
    nan = {"psf_fwhm": np.nan, "psf_e1": np.nan, "psf_e2": np.nan, "psf_T": np.nan}
    try:
        shape = galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp), strict=True)
    except galsim.GalSimError:
        return nan
    e1, e2 = shape.observed_shape.e1, shape.observed_shape.e2
    norm = 1.0 - e1 * e1 - e2 * e2
    if not norm > 0.0:
        return nan
    # unit-determinant shape matrix of the distortion (e1, e2), times sigma^2 = det(M)^(1/2)
    pixel_moments = (
        shape.moments_sigma**2 * np.array([[1.0 + e1, e2], [e2, 1.0 - e1]]) / np.sqrt(norm)
    )
    sky = jacobian @ pixel_moments @ jacobian.T
    size = float(sky[0, 0] + sky[1, 1])
    det = float(np.linalg.det(sky))
    if not (size > 0.0 and det > 0.0):
        return nan
    return {
        "psf_fwhm": float(2.0 * np.sqrt(2.0 * np.log(2.0)) * det**0.25),
        "psf_e1": float((sky[0, 0] - sky[1, 1]) / size),
        "psf_e2": float(2.0 * sky[0, 1] / size),
        "psf_T": size,
    }


class PsfLoss(NamedTuple):
    """A cell whose PSF stamp leaves out flux: the fraction, the cell, its stamp side."""

    flux_outside: float
    cell: tuple[int, int]
    tract: int
    size: int


def psf_loss(coadd: CellCoadd, limit: float = PSF_FLUX_OUTSIDE_LIMIT) -> list[PsfLoss]:
    """``[PsfLoss]`` when ``coadd``'s PSF stamp leaves out more than ``limit`` of the PSF's
    flux (:attr:`CellCoadd.psf_flux_outside`), else ``[]``."""
    outside = coadd.psf_flux_outside
    if not outside > limit:
        return []
    return [PsfLoss(outside, coadd.index, coadd.tract, coadd.psf.shape[0])]


def warn_truncated_psfs(coadds: Iterable[CellCoadd], limit: float = PSF_FLUX_OUTSIDE_LIMIT) -> None:
    """Warn (:class:`~cellcoadd.errors.PsfStampWarning`, once for all ``coadds``) when
    cells' PSF stamps leave out more than ``limit`` of the PSF's flux
    (:attr:`CellCoadd.psf_flux_outside`), naming the worst cell."""
    warn_psf_losses([loss for c in coadds for loss in psf_loss(c, limit)], limit, stacklevel=4)


def warn_psf_losses(
    losses: Sequence[PsfLoss], limit: float = PSF_FLUX_OUTSIDE_LIMIT, *, stacklevel: int = 3
) -> None:
    """The warning of :func:`warn_truncated_psfs` for the ``losses`` found in its cells
    (none: no warning)."""
    if not losses:
        return
    worst = max(losses, key=lambda loss: loss.flux_outside)
    warnings.warn(
        PsfStampWarning(
            f"{len(losses)} cell(s) lose more than {limit:g} of the PSF's flux outside the "
            f"{worst.size}-pixel PSF stamp, up to {worst.flux_outside:.2e} in cell "
            f"{worst.cell} of tract {worst.tract}; the stamps are renormalised to unit sum, "
            "which changes the PSF's size: a larger BuildConfig.psf_size keeps more "
            "(psf_flux_outside is recorded per input)"
        ),
        stacklevel=stacklevel,
    )
