"""A WCS whose pickle is exact, and the exact numerical parameters of a WCS.

astropy pickles a WCS as a FITS file written by ``to_fits(relax=True)``: its header cards
print floating-point values with 14 significant digits, so CRVAL, CD/PC, CRPIX and the SIP
coefficients come back from another process rounded (~5e-12 deg for CRVAL, ~3e-8 px on a
30,000 px tract). :class:`ExactWCS` is an astropy ``WCS`` that pickles itself losslessly:
wcslib's header at 17 significant digits (enough for any double) plus the numerical
parameters at full precision (:func:`wcs_exact_parameters`, set again after parsing), so
what a worker receives is the same WCS bit for bit. It is also ~10 times faster than
astropy's pickle (no FITS file is written or read). astropy's own operations (``copy``,
``deepcopy``, ``sub``, ``celestial``, slicing) return instances of the class they are
called on, so their results pickle exactly too.

The parameters themselves (:func:`wcs_exact_parameters`, :func:`apply_wcs_exact_parameters`)
are also what the file formats store beside the 14-digit header cards
(:mod:`cellcoadd.model.wcs_codec`).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from astropy import wcs as astropy_wcs  # its C base class WCSBase, used by name below
from astropy.wcs import (
    WCS,
    WCSHDO_P17,
    FITSFixedWarning,
    Sip,
    WCSHDO_all,
    Wcsprm,
)

#: wcslib ``to_header`` flags: every extension (``WCSHDO_all``), 17 significant digits
#: (``WCSHDO_P17``), which print any double exactly.
_EXACT_HEADER_FLAGS = WCSHDO_all | WCSHDO_P17
#: Names of the SIP coefficient matrices in :func:`wcs_exact_parameters`.
SIP_NAMES = ("a", "b", "ap", "bp")


def wcs_exact_parameters(wcs: WCS) -> dict[str, Any]:
    """The numerical parameters of a WCS at full double precision (JSON-able).

    Keys: ``crpix``, ``crval``, ``cdelt`` (lists of one float per axis), ``pc`` (the
    matrix as nested lists; wcslib's matrix is ``cdelt`` times it, row by row, so a CD
    matrix comes out as ``pc`` with ``cdelt = 1``), ``lonpole``, ``latpole``, ``pv``
    (``[i, m, value]`` triples) and ``sip`` (None, or the ``a``, ``b``, ``ap``, ``bp``
    coefficient matrices as nested lists, each possibly None).
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
                SIP_NAMES, (wcs.sip.a, wcs.sip.b, wcs.sip.ap, wcs.sip.bp), strict=True
            )
        }
    return exact


def apply_wcs_exact_parameters(wcs: WCS, exact: dict[str, Any]) -> None:
    """Set the parameters of :func:`wcs_exact_parameters` on ``wcs`` (in place), bit-exact.

    An empty ``pv`` list leaves the PV values of ``wcs`` as they are. SIP coefficients,
    when present, replace the SIP of ``wcs`` (with ``crpix`` as its reference pixel).
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
                for name in SIP_NAMES
            ),
            np.asarray(exact["crpix"], dtype=float),
        )
    params.set()


class ExactWCS(WCS):
    """An astropy ``WCS`` that survives pickling bit for bit.

    Used like any ``WCS``; made by :func:`~cellcoadd.geometry.wcs_utils.canonical_wcs`
    (which converts any WCS). ``copy``, ``deepcopy``, ``sub``, ``celestial``, ``slice`` and
    ``wcs[...]`` slicing keep the class. A WCS with lookup-table distortions (CPDIS, DET2IM)
    is pickled as astropy does, as a FITS file, its core parameters then set exactly.
    """

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild, (type(self), exact_state(self)))


def exact_state(wcs: WCS) -> dict[str, Any]:
    """What :class:`ExactWCS` pickles of ``wcs`` (any astropy WCS): see :func:`from_exact_state`.

    ``header``: wcslib's header of the core WCS at 17 digits (SIP excluded, as astropy
    keeps it apart); ``exact``: :func:`wcs_exact_parameters`; ``attributes``: the Python
    attributes (axis lengths, pixel bounds, options), as astropy's pickle keeps them;
    ``fits``: astropy's pickled FITS file instead of ``header`` when there are lookup
    tables.
    """
    exact = wcs_exact_parameters(wcs)
    if any(t is not None for t in (wcs.cpdis1, wcs.cpdis2, wcs.det2im1, wcs.det2im2)):
        _, (_, attributes, fits_data) = WCS.__reduce__(wcs)
        return {"fits": fits_data, "attributes": attributes, "exact": exact}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        header = wcs.wcs.to_header(_EXACT_HEADER_FLAGS)
    # astropy's pickle leaves out its lazily filled caches the same way
    attributes = {k: v for k, v in wcs.__dict__.items() if not k.endswith("_cache")}
    return {"header": header, "key": wcs.wcs.alt, "attributes": attributes, "exact": exact}


def from_exact_state(state: dict[str, Any], cls: type[ExactWCS] = ExactWCS) -> ExactWCS:
    """The WCS described by :func:`exact_state`, as an instance of ``cls``."""
    if "fits" in state:
        from astropy.wcs.wcs import __WCS_unpickle__

        wcs = __WCS_unpickle__(cls, dict(state["attributes"]), state["fits"])
    else:
        attributes = state["attributes"]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            params = Wcsprm(
                header=state["header"].encode("ascii"),
                key=state["key"],
                relax=True,
                preserve_units=bool(attributes.get("_preserve_units", False)),
            )
        wcs = cls.__new__(cls)
        # what astropy's WCS.__init__ and copies do, without parsing a FITS header again
        # the C base class, which astropy's own copies initialise (not a module name here:
        # the API reference would document it as ours)
        astropy_wcs.WCSBase.__init__(wcs, None, (None, None), params, (None, None))
        wcs.__dict__.update(attributes)
    apply_wcs_exact_parameters(wcs, state["exact"])
    return wcs


def _rebuild(cls: type[ExactWCS], state: dict[str, Any]) -> ExactWCS:
    """Unpickle an :class:`ExactWCS` (module level, so that pickle can name it)."""
    return from_exact_state(state, cls)
