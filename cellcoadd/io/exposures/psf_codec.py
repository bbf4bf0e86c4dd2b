"""Storable PSF models: exact JSON descriptions of GalSim profiles, and sampled grids.

A constant PSF (a ``galsim.GSObject``) made of the profiles listed in
:data:`PROFILE_FIELDS` and of transformations, convolutions and sums of them is described
exactly by a small JSON document (floats are written with ``repr`` precision, so the
profile read back compares equal and draws bit-identically). Decoding uses an explicit
whitelist: nothing from a file is ever evaluated as code.

A :class:`~cellcoadd.model.psf_profiles.VaryingPsf` is described exactly too; a
:class:`~cellcoadd.model.psf_profiles.GridPsf` is stored as arrays by
:mod:`cellcoadd.io.exposures.exposure_psf`.
"""

from __future__ import annotations

import inspect
import math
from typing import Any

import galsim
import numpy as np

from cellcoadd.errors import PsfCodecError
from cellcoadd.model.psf_profiles import Poly, VaryingPsf

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
