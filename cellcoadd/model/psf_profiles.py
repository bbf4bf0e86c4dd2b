"""Callable PSF profiles that vary over a detector, in a form files can hold.

Both are picklable callables ``(x, y) -> galsim.GSObject`` (0-based detector pixels;
pre-pixel profiles in arcsec on the local tangent plane, see
:mod:`cellcoadd.model.exposure`):

* :class:`VaryingPsf`: a profile whose size and shape vary as polynomials over the
  detector; :mod:`cellcoadd.io.exposures.psf_codec` stores it exactly in JSON.
* :class:`GridPsf`: any other callable, sampled on a grid of detector positions as
  oversampled pre-pixel stamps, interpolated bilinearly between grid nodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import galsim
import numpy as np

from cellcoadd.errors import CellCoaddValueError, PsfError

#: Largest side (samples) of a sampled PSF stamp; larger means a unit mistake.
MAX_STAMP_SIZE = 1025
Poly = tuple[tuple[int, int, float], ...]


def _evaluate(terms: Poly, xn: float, yn: float) -> float:
    return float(sum(c * xn**i * yn**j for i, j, c in terms))


@dataclass(frozen=True)
class VaryingPsf:
    """A PSF whose size and shape vary smoothly over a detector.

    At detector pixel ``(x, y)`` (0-based) with ``xn = (x - x0) / radius`` and
    ``yn = (y - y0) / radius`` the PSF is
    ``base.dilate(exp(D)).shear(g1=G1, g2=G2)`` where ``D``, ``G1``, ``G2`` are the
    polynomials ``sum c xn**i yn**j`` over their ``(i, j, c)`` terms. ``base`` is a pre-pixel
    profile in arcsec (see :mod:`cellcoadd.model.exposure`).

    Parameters
    ----------
    base : galsim.GSObject
        The PSF where every polynomial vanishes.
    x0, y0 : float
        Reference position, detector pixels (may lie off the detector, e.g. the boresight).
    radius : float
        Normalisation length of the polynomials, pixels.
    dilation, g1, g2 : tuple of (int, int, float)
        Polynomial terms of ln(size), and of the two reduced-shear components.
    """

    base: galsim.GSObject
    x0: float
    y0: float
    radius: float
    dilation: Poly = ()
    g1: Poly = ()
    g2: Poly = ()

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise CellCoaddValueError("VaryingPsf radius must be positive", value=self.radius)

    def parameters(self, x: float, y: float) -> tuple[float, float, float]:
        """``(dilation factor, g1, g2)`` at detector pixel ``(x, y)``."""
        xn = (x - self.x0) / self.radius
        yn = (y - self.y0) / self.radius
        return (
            math.exp(_evaluate(self.dilation, xn, yn)),
            _evaluate(self.g1, xn, yn),
            _evaluate(self.g2, xn, yn),
        )

    def __call__(self, x: float, y: float) -> galsim.GSObject:
        dilation, g1, g2 = self.parameters(x, y)
        profile = self.base
        if dilation != 1.0:
            profile = profile.dilate(dilation)
        if g1 != 0.0 or g2 != 0.0:
            profile = profile.shear(g1=g1, g2=g2)
        return profile


@dataclass(frozen=True, eq=False)
class GridPsf:
    """A PSF sampled on a regular grid of detector positions.

    Each node holds the pre-pixel PSF drawn without the pixel response on a square stamp
    of ``scale`` arcsec per sample (oversampled relative to the detector); the PSF at
    ``(x, y)`` is the bilinear interpolation of the four surrounding stamps (clamped
    outside the grid), returned as a ``galsim.InterpolatedImage`` in arcsec.

    Parameters
    ----------
    x_nodes, y_nodes : ndarray
        Increasing node coordinates, detector pixels.
    stamps : ndarray, shape (len(y_nodes), len(x_nodes), n, n)
        The node stamps, n odd.
    scale : float
        Sample spacing of the stamps, arcsec.
    """

    x_nodes: np.ndarray
    y_nodes: np.ndarray
    stamps: np.ndarray
    scale: float

    def __post_init__(self) -> None:
        nyg, nxg = len(self.y_nodes), len(self.x_nodes)
        if self.stamps.ndim != 4 or self.stamps.shape[:2] != (nyg, nxg):
            raise CellCoaddValueError(
                "GridPsf stamps must have shape (n_y_nodes, n_x_nodes, n, n)",
                value=self.stamps.shape,
            )
        if self.stamps.shape[2] != self.stamps.shape[3] or self.stamps.shape[2] % 2 == 0:
            raise CellCoaddValueError("GridPsf stamps must be odd squares", value=self.stamps.shape)
        for nodes in (self.x_nodes, self.y_nodes):
            if len(nodes) > 1 and not np.all(np.diff(nodes) > 0):
                raise CellCoaddValueError("GridPsf nodes must be strictly increasing")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise CellCoaddValueError("GridPsf scale must be positive", value=self.scale)
        if not np.all(np.isfinite(self.stamps)) or not np.all(self.stamps.sum(axis=(2, 3)) > 0):
            raise CellCoaddValueError("GridPsf stamps must be finite with positive sums")

    @classmethod
    def sample(
        cls,
        psf: Callable[[float, float], galsim.GSObject],
        shape: tuple[int, int],
        pixel_scale: float,
        n_nodes: int = 5,
        oversample: int = 4,
    ) -> GridPsf:
        """Sample ``psf`` on ``n_nodes`` x ``n_nodes`` positions spanning a detector.

        ``shape`` is the detector ``(ny, nx)``; ``pixel_scale`` (arcsec) its typical pixel
        size, divided by ``oversample`` to give the stamp sampling.
        """
        ny, nx = shape
        x_nodes = grid_nodes(nx, n_nodes)
        y_nodes = grid_nodes(ny, n_nodes)
        scale = pixel_scale / oversample
        profiles = [[psf(float(x), float(y)) for x in x_nodes] for y in y_nodes]
        for row in profiles:
            for profile in row:
                if not isinstance(profile, galsim.GSObject):
                    raise PsfError(
                        f"the PSF callable returned a {type(profile).__name__}, not a GSObject"
                    )
        size = max(p.getGoodImageSize(scale) for row in profiles for p in row)
        size += 1 - size % 2
        if size > MAX_STAMP_SIZE:
            raise PsfError(
                f"the PSF needs {size} x {size} samples of {scale:.3g} arcsec, more than "
                f"{MAX_STAMP_SIZE}: is its size in arcsec?"
            )
        stamps = np.array(
            [
                [p.drawImage(nx=size, ny=size, scale=scale, method="no_pixel").array for p in row]
                for row in profiles
            ],
            dtype=np.float64,
        )
        return cls(x_nodes=x_nodes, y_nodes=y_nodes, stamps=stamps, scale=scale)

    def stamp(self, x: float, y: float) -> np.ndarray:
        """Bilinearly interpolated node stamp at detector pixel ``(x, y)``."""
        (i0, i1, wy), (j0, j1, wx) = _bracket(self.y_nodes, y), _bracket(self.x_nodes, x)
        s = self.stamps
        return (1 - wy) * ((1 - wx) * s[i0, j0] + wx * s[i0, j1]) + wy * (
            (1 - wx) * s[i1, j0] + wx * s[i1, j1]
        )

    def __call__(self, x: float, y: float) -> galsim.GSObject:
        image = galsim.Image(np.ascontiguousarray(self.stamp(x, y)), scale=self.scale)
        return galsim.InterpolatedImage(image, x_interpolant="quintic")


def grid_nodes(n_pixels: int, n_nodes: int) -> np.ndarray:
    """``n_nodes`` evenly spaced positions from the first to the last pixel centre."""
    if n_nodes == 1:
        return np.array([(n_pixels - 1) / 2.0])
    return np.linspace(0.0, n_pixels - 1.0, n_nodes)


def _bracket(nodes: Sequence[float] | np.ndarray, value: float) -> tuple[int, int, float]:
    """Indices of the nodes around ``value`` and the weight of the upper one (clamped)."""
    n = len(nodes)
    if n == 1 or value <= nodes[0]:
        return 0, 0, 0.0
    if value >= nodes[-1]:
        return n - 1, n - 1, 0.0
    upper = int(np.searchsorted(nodes, value, side="right"))
    lower = upper - 1
    weight = (value - nodes[lower]) / (nodes[upper] - nodes[lower])
    return lower, upper, float(weight)
