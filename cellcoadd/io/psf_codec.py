"""Storable PSF models: exact JSON descriptions of GalSim profiles, and sampled grids.

A constant PSF (a ``galsim.GSObject``) made of the profiles listed in
:data:`PROFILE_FIELDS` and of transformations, convolutions and sums of them is described
exactly by a small JSON document (floats are written with ``repr`` precision, so the
profile read back compares equal and draws bit-identically). Decoding uses an explicit
whitelist: nothing from a file is ever evaluated as code.

Two picklable callable PSFs ``(x, y) -> galsim.GSObject`` (pre-pixel, arcsec on the local
tangent plane; see :mod:`cellcoadd.model.exposure`) live here because files must be able
to hold them:

* :class:`VaryingPsf`: a profile whose size and shape vary as polynomials over the
  detector; described exactly in JSON.
* :class:`GridPsf`: any other callable, sampled on a grid of detector positions as
  oversampled pre-pixel stamps, interpolated bilinearly between grid nodes.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import galsim
import numpy as np

#: Profiles stored exactly: GalSim class -> constructor arguments (read from attributes
#: of the same name).
PROFILE_FIELDS: dict[str, tuple[type, tuple[str, ...]]] = {
    "Gaussian": (galsim.Gaussian, ("sigma", "flux")),
    "Moffat": (galsim.Moffat, ("beta", "scale_radius", "trunc", "flux")),
    "Kolmogorov": (galsim.Kolmogorov, ("lam_over_r0", "flux")),
    "Exponential": (galsim.Exponential, ("scale_radius", "flux")),
    "Airy": (galsim.Airy, ("lam_over_diam", "obscuration", "flux")),
    "Box": (galsim.Box, ("width", "height", "flux")),
    "Pixel": (galsim.Pixel, ("scale", "flux")),
    "DeltaFunction": (galsim.DeltaFunction, ("flux",)),
}
# the GSParams arguments GalSim still stores (deprecated ones are dropped)
_GSPARAMS_NAMES = tuple(
    name
    for name in inspect.signature(galsim.GSParams).parameters
    if f"_{name}" in vars(galsim.GSParams())
)
_MAX_DEPTH = 32
#: Largest side (samples) of a sampled PSF stamp; larger means a unit mistake.
MAX_STAMP_SIZE = 1025
Poly = tuple[tuple[int, int, float], ...]


class PsfCodecError(ValueError):
    """A PSF description cannot be encoded or is not a valid description."""


# -- constant profiles ---------------------------------------------------------------
def can_encode(obj: Any) -> bool:
    """Whether ``obj`` (a GSObject or :class:`VaryingPsf`) has an exact JSON description."""
    try:
        encode_psf(obj)
    except PsfCodecError:
        return False
    return True


def encode_psf(obj: Any) -> dict[str, Any]:
    """JSON-able exact description of a GSObject or :class:`VaryingPsf`.

    Raises
    ------
    PsfCodecError
        For a profile type outside the whitelist (e.g. an ``InterpolatedImage``).
    """
    if isinstance(obj, VaryingPsf):
        return {
            "type": "VaryingPsf",
            "base": encode_psf(obj.base),
            "x0": float(obj.x0),
            "y0": float(obj.y0),
            "radius": float(obj.radius),
            "dilation": [list(t) for t in obj.dilation],
            "g1": [list(t) for t in obj.g1],
            "g2": [list(t) for t in obj.g2],
        }
    if not isinstance(obj, galsim.GSObject):
        raise PsfCodecError(f"cannot describe {type(obj).__name__} as a PSF profile")
    out: dict[str, Any]
    name = type(obj).__name__
    if name in PROFILE_FIELDS and type(obj) is PROFILE_FIELDS[name][0]:
        out = {"type": name}
        for attr in PROFILE_FIELDS[name][1]:
            out[attr] = float(getattr(obj, attr))
    elif type(obj) is galsim.Transformation:
        jac = obj.jac
        out = {
            "type": "Transformation",
            "original": encode_psf(obj.original),
            "jac": None if jac is None else [float(v) for v in np.asarray(jac).ravel()],
            "offset": [float(obj.offset.x), float(obj.offset.y)],
            "flux_ratio": float(obj.flux_ratio),
        }
    elif type(obj) is galsim.Convolution:
        out = {
            "type": "Convolution",
            "items": [encode_psf(item) for item in obj.obj_list],
            "real_space": bool(obj.real_space),
        }
    elif type(obj) is galsim.Sum:
        out = {"type": "Sum", "items": [encode_psf(item) for item in obj.obj_list]}
    else:
        raise PsfCodecError(f"no exact description for a galsim.{name}")
    if obj.gsparams != galsim.GSParams():
        out["gsparams"] = {n: getattr(obj.gsparams, n) for n in _GSPARAMS_NAMES}
    return out


def decode_psf(desc: Any, _depth: int = 0) -> Any:
    """Inverse of :func:`encode_psf`, accepting only whitelisted types and fields.

    Raises
    ------
    PsfCodecError
        For anything that is not a valid description.
    """
    if _depth > _MAX_DEPTH:
        raise PsfCodecError("PSF description nested too deeply")
    if not isinstance(desc, dict) or not isinstance(desc.get("type"), str):
        raise PsfCodecError("a PSF description must be an object with a 'type'")
    kind = desc["type"]
    if kind == "VaryingPsf":
        _check_keys(desc, {"type", "base", "x0", "y0", "radius", "dilation", "g1", "g2"})
        return VaryingPsf(
            base=_decode_profile(desc["base"], _depth + 1),
            x0=_number(desc, "x0"),
            y0=_number(desc, "y0"),
            radius=_number(desc, "radius"),
            dilation=_poly(desc["dilation"]),
            g1=_poly(desc["g1"]),
            g2=_poly(desc["g2"]),
        )
    return _decode_profile(desc, _depth)


def _decode_profile(desc: Any, depth: int) -> galsim.GSObject:
    if depth > _MAX_DEPTH:
        raise PsfCodecError("PSF description nested too deeply")
    if not isinstance(desc, dict) or not isinstance(desc.get("type"), str):
        raise PsfCodecError("a profile description must be an object with a 'type'")
    kind = desc["type"]
    gsparams = _gsparams(desc.get("gsparams"))
    try:
        if kind in PROFILE_FIELDS:
            cls, fields = PROFILE_FIELDS[kind]
            _check_keys(desc, {"type", "gsparams", *fields})
            return cls(**{f: _number(desc, f) for f in fields}, gsparams=gsparams)
        if kind == "Transformation":
            _check_keys(desc, {"type", "gsparams", "original", "jac", "offset", "flux_ratio"})
            jac = desc["jac"]
            if jac is not None:
                jac = np.array(_numbers(jac, 4, "jac"), dtype=float).reshape(2, 2)
            return galsim.Transformation(
                _decode_profile(desc["original"], depth + 1),
                jac=jac,
                offset=tuple(_numbers(desc["offset"], 2, "offset")),
                flux_ratio=_number(desc, "flux_ratio"),
                gsparams=gsparams,
            )
        if kind in ("Convolution", "Sum"):
            _check_keys(desc, {"type", "gsparams", "items", "real_space"})
            items = desc["items"]
            if not isinstance(items, list) or not items:
                raise PsfCodecError(f"{kind} needs a non-empty list of items")
            objs = [_decode_profile(item, depth + 1) for item in items]
            if kind == "Sum":
                return galsim.Sum(objs, gsparams=gsparams)
            real_space = desc.get("real_space", False)
            if not isinstance(real_space, bool):
                raise PsfCodecError("real_space must be a boolean")
            return galsim.Convolution(objs, real_space=real_space, gsparams=gsparams)
    except galsim.GalSimError as err:
        raise PsfCodecError(f"invalid {kind} parameters: {err}") from err
    raise PsfCodecError(f"unknown or disallowed profile type {kind!r}")


def _check_keys(desc: dict, allowed: set[str]) -> None:
    extra = set(desc) - allowed
    if extra:
        raise PsfCodecError(f"unexpected fields {sorted(extra)} in a {desc['type']} description")


def _number(desc: dict, key: str) -> float:
    if key not in desc:
        raise PsfCodecError(f"missing field {key!r} in a {desc.get('type')} description")
    return _as_float(desc[key], key)


def _as_float(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise PsfCodecError(f"{what} must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise PsfCodecError(f"{what} must be finite")
    return float(value)


def _numbers(values: Any, n: int, what: str) -> list[float]:
    if not isinstance(values, list) or len(values) != n:
        raise PsfCodecError(f"{what} must be a list of {n} numbers")
    return [_as_float(v, what) for v in values]


def _poly(terms: Any) -> Poly:
    if not isinstance(terms, list):
        raise PsfCodecError("polynomial terms must be a list of [i, j, coefficient]")
    out = []
    for term in terms:
        if not isinstance(term, list) or len(term) != 3:
            raise PsfCodecError("polynomial term must be [i, j, coefficient]")
        i, j, c = term
        if not all(isinstance(p, int) and not isinstance(p, bool) for p in (i, j)):
            raise PsfCodecError("polynomial powers must be integers")
        if not (0 <= i <= 8 and 0 <= j <= 8):
            raise PsfCodecError("polynomial powers must be in 0..8")
        out.append((i, j, _as_float(c, "polynomial coefficient")))
    return tuple(out)


def _gsparams(desc: Any) -> galsim.GSParams | None:
    if desc is None:
        return None
    if not isinstance(desc, dict) or set(desc) - set(_GSPARAMS_NAMES):
        raise PsfCodecError("gsparams must map GSParams argument names to numbers")
    values = {
        k: v if isinstance(v, int) and not isinstance(v, bool) else _as_float(v, k)
        for k, v in desc.items()
    }
    return galsim.GSParams(**values)


# -- callable PSFs -------------------------------------------------------------------
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
            raise ValueError("VaryingPsf radius must be positive")

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
            raise ValueError("GridPsf stamps must have shape (n_y_nodes, n_x_nodes, n, n)")
        if self.stamps.shape[2] != self.stamps.shape[3] or self.stamps.shape[2] % 2 == 0:
            raise ValueError("GridPsf stamps must be odd squares")
        for nodes in (self.x_nodes, self.y_nodes):
            if len(nodes) > 1 and not np.all(np.diff(nodes) > 0):
                raise ValueError("GridPsf nodes must be strictly increasing")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError("GridPsf scale must be positive")
        if not np.all(np.isfinite(self.stamps)) or not np.all(self.stamps.sum(axis=(2, 3)) > 0):
            raise ValueError("GridPsf stamps must be finite with positive sums")

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
                    raise PsfCodecError(
                        f"the PSF callable returned a {type(profile).__name__}, not a GSObject"
                    )
        size = max(p.getGoodImageSize(scale) for row in profiles for p in row)
        size += 1 - size % 2
        if size > MAX_STAMP_SIZE:
            raise PsfCodecError(
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


def _bracket(nodes: Sequence[float], value: float) -> tuple[int, int, float]:
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
