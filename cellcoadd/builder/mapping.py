"""The map from coadd (cell) pixels to exposure pixels, with a verified error bound.

The exact chain is ``coadd pixel -> (ra, dec) -> exposure pixel`` through the two astropy
WCSs (``all_pix2world`` / ``all_world2pix``, origin 0, so SIP distortion is included).
Evaluating it at every pixel of every cell for every exposure is slow, so
:func:`map_box` evaluates it on a coarse grid, interpolates with piecewise cubics and
checks the interpolant against the exact chain at points that were not used for it
(the midpoints between grid nodes). The grid is refined until the checked error is
within the tolerance, with exact evaluation at every pixel as the last resort.
:func:`footprint_box` gives the exposure pixels the resampling kernel reads for mapped
pixels: what an exposure must hold for a cell to be edge-free.

Conventions: 0-based pixel coordinates with pixel centres at integers (see
:mod:`cellcoadd.geometry.box`); errors are Euclidean distances in exposure pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np
from astropy.wcs import WCS
from astropy.wcs.wcs import NoConvergence

from cellcoadd.builder.kernels.descriptor import WARP_KERNEL, KernelDescriptor
from cellcoadd.builder.kernels.node_interpolation import interpolate_nodes
from cellcoadd.builder.kernels.unit_area import snap_unit_area
from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError, GeometryError, MappingError
from cellcoadd.geometry.box import Box

# Inverse-SIP iterations stop at this step (exposure px): far below any tolerance used here
# and small enough that finite differences over half a pixel stay accurate to ~1e-9.
_WORLD2PIX_TOLERANCE = 1e-10
_WORLD2PIX_MAXITER = 50
# Half-width (coadd px) of the central differences giving the Jacobian.
_DIFFERENCE_STEP = 0.5
# The error of a piecewise cubic between check points can exceed the value at the nearest
# check point by up to ~7% (end intervals); accepting only half the tolerance leaves margin.
_UNIT_AREA_TOLERANCE = 1e-8
_ACCEPT_FRACTION = 0.5
_MIN_GRID_STEP = 4


class _Interpolated:
    """A :class:`PixelMapping` field whose value may still be a :class:`_Deferred`
    interpolation, carried out (once) when the field is first read."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.slot = name, "_" + name

    def __get__(self, mapping: PixelMapping | None, owner: type | None = None) -> np.ndarray:
        if mapping is None:
            raise AttributeError(self.name)  # a required field: no class-level default
        value = mapping.__dict__[self.slot]
        if isinstance(value, _Deferred):
            value = value.evaluate()
            if self.name == "area_ratio":
                _snap_unit_area(value)
            value.setflags(write=False)
            mapping.__dict__[self.slot] = value
        return value

    def __set__(self, mapping: PixelMapping, value: np.ndarray | _Deferred) -> None:
        mapping.__dict__[self.slot] = value  # only reached from __init__: it is frozen

    @staticmethod
    def is_deferred(mapping: PixelMapping, name: str) -> bool:
        return isinstance(mapping.__dict__["_" + name], _Deferred)


@dataclass(frozen=True, eq=False)
class PixelMapping:
    """Exposure pixel positions of the coadd pixel centres of ``box``.

    Attributes
    ----------
    box : Box
        The coadd pixels mapped, in the coadd WCS's pixel coordinates.
    x, y : ndarray, shape box.shape, float64
        Exposure pixel coordinates (0-based) of each coadd pixel centre; NaN where the
        pixel does not map into the exposure's projection.
    area_ratio : ndarray, shape box.shape, float64
        ``|det d(x_exp, y_exp) / d(x_coadd, y_coadd)|``: the area of a coadd pixel in
        exposure pixels. Multiplying a surface brightness per exposure pixel by it gives
        the value per coadd pixel (flux conservation).
    max_error : float
        Largest distance (exposure px) between the returned positions and the exact WCS
        chain at the check points; 0 when every pixel was evaluated exactly.
    grid_step : int
        Nominal spacing (coadd px) of the interpolation grid; 0 for exact evaluation.

    Notes
    -----
    From :func:`map_box`, ``x``, ``y`` and ``area_ratio`` are interpolated from the grid
    on first access (then kept, read-only): most exposures considered for a cell are
    rejected on their positions alone and never need the area ratio.
    """

    box: Box
    if TYPE_CHECKING:
        # What the _Interpolated fields below look like from outside: they read as arrays,
        # accept a _Deferred at construction, and are required (their __get__ refuses class
        # access, so dataclasses see no default; mypy would take the descriptor for one).
        x: np.ndarray
        y: np.ndarray
        area_ratio: np.ndarray
        max_error: float
        grid_step: int

        def __init__(
            self,
            box: Box,
            x: np.ndarray | _Deferred,
            y: np.ndarray | _Deferred,
            area_ratio: np.ndarray | _Deferred,
            max_error: float,
            grid_step: int,
        ) -> None: ...
    else:
        x: np.ndarray = _Interpolated()
        y: np.ndarray = _Interpolated()
        area_ratio: np.ndarray = _Interpolated()
        max_error: float
        grid_step: int

    def restricted(self, box: Box) -> PixelMapping:
        """The mapping of the pixels of ``box`` (inside :attr:`box`), bit for bit the
        values the whole mapping holds there, without evaluating the rest.

        An interpolated mapping stays deferred: only ``box``'s pixels are interpolated, from
        the same grid values with the same weights, so any sub-box gives the same numbers.
        """
        if not self.box.contains_box(box):
            raise GeometryError(
                f"{box} is not inside the mapped box {self.box}", value=box, allowed=self.box
            )
        rows = slice(box.y_start - self.box.y_start, box.y_stop - self.box.y_start)
        cols = slice(box.x_start - self.box.x_start, box.x_stop - self.box.x_start)

        def part(name: str) -> np.ndarray | _Deferred:
            value = self.__dict__["_" + name]
            if isinstance(value, _Deferred):
                return _Deferred(value.nodes, value.rows.sliced(rows), value.cols.sliced(cols))
            return value[rows, cols]

        return PixelMapping(
            box, part("x"), part("y"), part("area_ratio"), self.max_error, self.grid_step
        )

    @property
    def is_complete(self) -> bool:
        """Whether every pixel of the box has a finite exposure position."""
        if _Interpolated.is_deferred(self, "x") and _Interpolated.is_deferred(self, "y"):
            return True  # interpolated from an accepted grid, whose values are all finite
        return bool(np.isfinite(self.x).all() and np.isfinite(self.y).all())


class PixelPositions(Protocol):
    """Exposure pixel positions ``x`` and ``y`` of some coadd pixels: a
    :class:`PixelMapping` or a subset of its pixels."""

    @property
    def x(self) -> np.ndarray: ...

    @property
    def y(self) -> np.ndarray: ...


def footprint_box(mapping: PixelPositions, kernel: KernelDescriptor = WARP_KERNEL) -> Box:
    """Exposure pixels touched by the resampling kernel taps of all mapped pixels.

    Taps run from ``floor(x) + kernel.first_offset`` to ``floor(x) + kernel.last_offset``
    (Lanczos-3: ``floor(x) - 2 .. floor(x) + 3``), so the box is
    ``[min floor(x) - half_width + 1, max floor(x) + half_width + 1)`` and likewise in y.
    An exposure can be resampled without edge effects iff its valid box contains this.

    Parameters
    ----------
    mapping : PixelMapping
        Or any object with exposure pixel coordinate arrays ``x`` and ``y`` (e.g. a
        subset of a mapping's pixels).
    kernel : KernelDescriptor
        The resampling kernel (default: the builder's).

    Raises
    ------
    MappingError
        If there are no pixels or some do not map into the exposure (non-finite).
    """
    x = np.asarray(mapping.x, dtype=np.float64)
    y = np.asarray(mapping.y, dtype=np.float64)
    if x.size == 0:
        raise MappingError("an empty mapping has no footprint")
    # floor is monotonic: the floor of the extremes is the extreme of the floors; a NaN
    # propagates to the extremes, an infinity stays one
    x_min, x_max, y_min, y_max = x.min(), x.max(), y.min(), y.max()
    if not np.isfinite([x_min, x_max, y_min, y_max]).all():
        raise MappingError("some pixels do not map into the exposure")
    x_start, x_stop = kernel.tap_range(x_min, x_max)
    y_start, y_stop = kernel.tap_range(y_min, y_max)
    return Box(x_start=x_start, x_stop=x_stop, y_start=y_start, y_stop=y_stop)


def _snap_unit_area(area_ratio: np.ndarray) -> None:
    # WCS round trips leave ~1e-9 relative noise on a ratio that is exactly 1 for equal
    # pixel scales; far below float32 precision, but it would spoil exact copies
    if area_ratio.flags.c_contiguous and area_ratio.dtype == np.float64:
        snap_unit_area(area_ratio, _UNIT_AREA_TOLERANCE)  # one pass (a block's millions)
    else:
        area_ratio[np.abs(area_ratio - 1.0) < _UNIT_AREA_TOLERANCE] = 1.0


def map_points(
    coadd_wcs: WCS, x: np.ndarray, y: np.ndarray, exposure_wcs: WCS
) -> tuple[np.ndarray, np.ndarray]:
    """Exact exposure pixel coordinates of coadd pixel coordinates ``(x, y)``.

    Parameters
    ----------
    coadd_wcs, exposure_wcs : astropy.wcs.WCS
        Celestial WCSs; pixel coordinates are 0-based.
    x, y : array_like
        Coadd pixel coordinates (broadcast together).

    Returns
    -------
    x_exp, y_exp : ndarray, float64
        Exposure pixel coordinates, NaN where the inverse exposure WCS has no solution or
        its iteration diverges or fails to converge (points far outside a SIP exposure).
    """
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    shape = x.shape
    ra, dec = coadd_wcs.all_pix2world(x.ravel(), y.ravel(), 0)
    try:
        x_exp, y_exp = exposure_wcs.all_world2pix(
            ra, dec, 0, tolerance=_WORLD2PIX_TOLERANCE, maxiter=_WORLD2PIX_MAXITER
        )
    except NoConvergence as failure:
        solution = np.array(failure.best_solution, dtype=np.float64)
        for bad in (failure.divergent, failure.slow_conv):
            if bad is not None:
                solution[np.asarray(bad)] = np.nan
        x_exp, y_exp = solution[:, 0], solution[:, 1]
    x_exp = np.asarray(x_exp, dtype=np.float64).reshape(shape)
    y_exp = np.asarray(y_exp, dtype=np.float64).reshape(shape)
    return x_exp, y_exp


def _map_with_area(
    coadd_wcs: WCS, x: np.ndarray, y: np.ndarray, exposure_wcs: WCS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact positions and area ratios (central differences) at coadd points ``(x, y)``."""
    h = _DIFFERENCE_STEP
    offsets_x = np.array([0.0, h, -h, 0.0, 0.0])
    offsets_y = np.array([0.0, 0.0, 0.0, h, -h])
    x_all = x[np.newaxis] + offsets_x.reshape((5,) + (1,) * x.ndim)
    y_all = y[np.newaxis] + offsets_y.reshape((5,) + (1,) * y.ndim)
    x_exp, y_exp = map_points(coadd_wcs, x_all, y_all, exposure_wcs)
    dx_dx = (x_exp[1] - x_exp[2]) / (2 * h)
    dy_dx = (y_exp[1] - y_exp[2]) / (2 * h)
    dx_dy = (x_exp[3] - x_exp[4]) / (2 * h)
    dy_dy = (y_exp[3] - y_exp[4]) / (2 * h)
    area_ratio = np.abs(dx_dx * dy_dy - dx_dy * dy_dx)
    return x_exp[0], y_exp[0], area_ratio


class _CubicBasis(NamedTuple):
    """Piecewise-cubic interpolation weights from uniform nodes to a set of positions.

    Position ``i`` is ``sum(weights[i, m] * f(nodes[first[i] + m]) for m in range(4))``.
    """

    first: np.ndarray  # int64 (n,): first of the four nodes used by each position
    weights: np.ndarray  # float64 (n, 4)

    def sliced(self, positions: slice) -> _CubicBasis:
        """The weights of a run of the positions."""
        return _CubicBasis(self.first[positions], self.weights[positions])


def _cubic_basis(nodes: np.ndarray, positions: np.ndarray) -> _CubicBasis:
    """Lagrange weights of ``positions`` on uniformly spaced ``nodes`` (at least 4).

    Each position uses the four nodes around its interval (shifted inwards at the ends),
    so the interpolation is exact for cubics and its error scales as ``spacing^4``.
    """
    n_nodes = nodes.size
    spacing = nodes[1] - nodes[0]
    u = (positions - nodes[0]) / spacing
    interval = np.clip(np.floor(u).astype(np.int64), 0, n_nodes - 2)
    first = np.clip(interval - 1, 0, n_nodes - 4)
    local = u - first
    weights = np.ones((positions.size, 4))
    for m in range(4):
        for other in range(4):
            if other != m:
                weights[:, m] *= (local - other) / (m - other)
    for array in (first, weights):
        array.setflags(write=False)  # shared by every mapping using the grid
    return _CubicBasis(first, weights)


def _axis_nodes(start: int, stop: int, step: int) -> np.ndarray:
    """Uniform nodes from the first to the last pixel centre of ``[start, stop)``."""
    n_nodes = max(4, math.ceil((stop - 1 - start) / step) + 1)
    return np.linspace(start, stop - 1, n_nodes)


def _exact_mapping(coadd_wcs: WCS, box: Box, exposure_wcs: WCS) -> PixelMapping:
    y_coadd, x_coadd = np.mgrid[box.y_start : box.y_stop, box.x_start : box.x_stop]
    x_exp, y_exp, area_ratio = _map_with_area(
        coadd_wcs, x_coadd.astype(np.float64), y_coadd.astype(np.float64), exposure_wcs
    )
    return _frozen_mapping(box, x_exp, y_exp, area_ratio, 0.0, 0)


def _nodes_of(values: np.ndarray) -> np.ndarray:
    """The values at the grid nodes, ``values[::2, ::2]`` of the dense grid (its odd indices
    are the check points between nodes), as a contiguous array of their own."""
    return np.ascontiguousarray(values[::2, ::2])


def _from_nodes(nodes: np.ndarray, rows: _CubicBasis, cols: _CubicBasis) -> np.ndarray:
    """Interpolate from the values at the grid nodes to the positions of ``rows`` x ``cols``."""
    return interpolate_nodes(nodes, rows.first, rows.weights, cols.first, cols.weights)


def _interpolate(values: np.ndarray, rows: _CubicBasis, cols: _CubicBasis) -> np.ndarray:
    """:func:`_from_nodes` of the nodes of the dense grid ``values``."""
    return _from_nodes(_nodes_of(values), rows, cols)


@dataclass(frozen=True, eq=False)
class _Deferred:
    """A pixel-level quantity interpolated from its values at the grid nodes when first
    needed. Only the nodes are kept (not the check points, nor the arrays of positions
    offset for the area ratio they were computed with): a quarter of the dense grid,
    which is what every exposure mapped over a patch holds until the patch is built."""

    nodes: np.ndarray
    rows: _CubicBasis
    cols: _CubicBasis

    def evaluate(self) -> np.ndarray:
        return _from_nodes(self.nodes, self.rows, self.cols)


def _frozen_mapping(
    box: Box,
    x: np.ndarray | _Deferred,
    y: np.ndarray | _Deferred,
    area_ratio: np.ndarray | _Deferred,
    max_error: float,
    grid_step: int,
) -> PixelMapping:
    if isinstance(area_ratio, np.ndarray):
        _snap_unit_area(area_ratio)
    for values in (x, y, area_ratio):
        if isinstance(values, np.ndarray):
            values.setflags(write=False)
    return PixelMapping(box, x, y, area_ratio, float(max_error), int(grid_step))


class _AxisGrid:
    """Grid nodes along one axis of a box and the cubic bases that interpolate from them."""

    def __init__(self, start: int, stop: int, step: int) -> None:
        self.start, self.stop = start, stop
        self.nodes = _axis_nodes(start, stop, step)
        # Nodes and the midpoints between them; the midpoints (odd indices) are check points.
        self.dense = np.linspace(self.nodes[0], self.nodes[-1], 2 * self.nodes.size - 1)
        self.dense_basis = _cubic_basis(self.nodes, self.dense)

    @cached_property
    def pixel_basis(self) -> _CubicBasis:
        """Basis interpolating to every pixel centre (needed once a grid is accepted)."""
        return _cubic_basis(self.nodes, np.arange(self.start, self.stop, dtype=np.float64))


def _axis_grid(start: int, stop: int, step: int, cache: dict) -> _AxisGrid:
    key = (start, stop, step)
    if key not in cache:
        cache[key] = _AxisGrid(start, stop, step)
    return cache[key]


def _try_grid(
    coadd_wcs: WCS,
    box: Box,
    exposure_wcs: WCS,
    step: int,
    tolerance: float,
    area_tolerance: float,
    grids: dict,
) -> tuple[PixelMapping | None, bool]:
    """Interpolated mapping on a grid of ``step`` px, or None if it fails verification.

    The flag says whether the exact chain was finite on the whole grid; when it is not,
    part of the box is off the exposure and no grid can help. ``grids`` keeps the axis
    grids (the same for both axes of a square box, and for every exposure of a cell).
    """
    along_x = _axis_grid(box.x_start, box.x_stop, step, grids)
    along_y = _axis_grid(box.y_start, box.y_stop, step, grids)
    grid_x, grid_y = np.meshgrid(along_x.dense, along_y.dense)
    exact_x, exact_y, exact_area = _map_with_area(coadd_wcs, grid_x, grid_y, exposure_wcs)
    finite = np.isfinite(exact_x).all() and np.isfinite(exact_y).all()
    if not (finite and np.isfinite(exact_area).all() and (exact_area > 0).all()):
        return None, False

    basis_x, basis_y = along_x.dense_basis, along_y.dense_basis
    error = np.hypot(
        _interpolate(exact_x, basis_y, basis_x) - exact_x,
        _interpolate(exact_y, basis_y, basis_x) - exact_y,
    )
    max_error = float(error.max())
    area_error = float(np.abs(_interpolate(exact_area, basis_y, basis_x) / exact_area - 1).max())
    if max_error > _ACCEPT_FRACTION * tolerance or area_error > area_tolerance:
        return None, True

    pixel_basis_x, pixel_basis_y = along_x.pixel_basis, along_y.pixel_basis
    mapping = _frozen_mapping(
        box,
        _Deferred(_nodes_of(exact_x), pixel_basis_y, pixel_basis_x),
        _Deferred(_nodes_of(exact_y), pixel_basis_y, pixel_basis_x),
        _Deferred(_nodes_of(exact_area), pixel_basis_y, pixel_basis_x),
        max_error,
        step,
    )
    return mapping, True


def map_box(
    coadd_wcs: WCS,
    box: Box,
    exposure_wcs: WCS,
    tolerance: float = 1e-3,
    grid_step: int = 32,
    area_tolerance: float = 1e-6,
    *,
    grid_cache: dict | None = None,
) -> PixelMapping:
    """Map every coadd pixel centre of ``box`` into exposure pixel coordinates.

    Parameters
    ----------
    coadd_wcs : astropy.wcs.WCS
        WCS of the coadd frame ``box`` lives in (0-based pixels).
    box : Box
        Coadd pixels to map (half-open).
    exposure_wcs : astropy.wcs.WCS
        The exposure's WCS; SIP distortion is honoured.
    tolerance : float
        Largest allowed position error (exposure px) at the check points. A grid is
        accepted only when its checked error is at most half of this, which bounds the
        error between check points as well.
    grid_step : int
        Initial grid spacing (coadd px); halved on failure down to 4 px, after which
        every pixel is evaluated exactly.
    area_tolerance : float
        Largest allowed relative error of ``area_ratio`` at the check points.
    grid_cache : dict, optional
        Keeps the interpolation grids for later calls on boxes with the same extent (e.g.
        every exposure considered for one cell); any dict, filled here.

    Returns
    -------
    PixelMapping
        With ``max_error <= tolerance``. Pixels outside the exposure's projection (or
        where its inverse does not converge) get NaN: check ``is_complete``.
    """
    mapping = grid_mapping(
        coadd_wcs, box, exposure_wcs, tolerance, grid_step, area_tolerance, grid_cache=grid_cache
    )
    return mapping if mapping is not None else _exact_mapping(coadd_wcs, box, exposure_wcs)


def grid_mapping(
    coadd_wcs: WCS,
    box: Box,
    exposure_wcs: WCS,
    tolerance: float = 1e-3,
    grid_step: int = 32,
    area_tolerance: float = 1e-6,
    *,
    grid_cache: dict | None = None,
) -> PixelMapping | None:
    """:func:`map_box` from an interpolation grid only: None where :func:`map_box` would
    evaluate every pixel exactly (no verified grid; part of the box off the exposure's
    projection), which for a large box is slow and memory-hungry."""
    if not tolerance > 0 or not area_tolerance > 0:
        raise CellCoaddValueError(
            "tolerance and area_tolerance must be positive", value=(tolerance, area_tolerance)
        )
    if grid_step < 1:
        raise CellCoaddRangeError(
            f"grid_step must be positive, got {grid_step}", value=grid_step, low=1
        )
    if box.is_empty:
        empty = np.zeros(box.shape)
        return _frozen_mapping(box, empty, empty.copy(), empty.copy(), 0.0, 0)
    step = grid_step
    grids = grid_cache if grid_cache is not None else {}
    # A cubic needs four nodes per axis; tiny boxes are cheaper to evaluate exactly anyway.
    if min(box.nx, box.ny) >= 4:
        while step >= _MIN_GRID_STEP:
            mapping, finite = _try_grid(
                coadd_wcs, box, exposure_wcs, step, tolerance, area_tolerance, grids
            )
            if mapping is not None:
                return mapping
            if not finite:
                break
            step //= 2
    return None
