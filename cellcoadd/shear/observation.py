"""Handing a cell coadd to shear codes: plain-dict observations and ngmix ``Observation``.

:func:`to_observation` gathers what a metacalibration-style code needs from one
:class:`~cellcoadd.model.cell_coadd.CellCoadd` (image, weight, one noise realization,
masks, masked fraction, PSF stamp and the local WCS jacobian) as numpy arrays and floats,
with no dependency on any shear package. :func:`to_ngmix` wraps the same content into an
``ngmix.Observation`` when ngmix is installed (it is optional).

Conventions
-----------
* Arrays cover the cell's *outer* box and are indexed ``[row, col] = [y, x]`` with pixel
  centres at integer 0-based coordinates (see :mod:`cellcoadd.geometry.box`).
* The jacobian is that of the cell WCS at the cell-centre pixel ``(x, y) = (nx // 2,
  ny // 2)``, the position of the PSF stamp's centre, in arcsec/pixel with GalSim sky
  coordinates (``u`` West, ``v`` North). With ``J = [[du/dx, du/dy], [dv/dx, dv/dy]]``
  (:func:`cellcoadd.geometry.wcs_utils.local_jacobian`) and ``row = y``, ``col = x``:
  ``dudcol = J[0, 0]``, ``dudrow = J[0, 1]``, ``dvdcol = J[1, 0]``, ``dvdrow = J[1, 1]``;
  ``row0, col0`` is the reference pixel (ngmix's ``row``/``col`` arguments).
* ``weight`` is constant, ``1 / var``, where ``var`` is the pixel variance of the coadd
  noise realizations measured over the cell's inner region (the mean over the ``K``
  realizations of each one's variance there). This is the actual per-pixel variance of
  the resampled coadd: the stored ``variance`` plane resamples the input variances with
  the kernel weights and so ignores the averaging the interpolation does (it is ~25%
  higher for 0.27 arcsec inputs on a 0.2 arcsec grid). The pixel correlations themselves
  (~0.4 between neighbours) are carried by ``noise``; a weight map cannot express them, so
  S/N and detection thresholds from it need :mod:`cellcoadd.shear.noise_correlation`.
* ``noise`` is one realization coadded exactly like the image. ngmix's metacal uses it
  only with ``use_noise_image=True`` (``ngmix.metacal.get_all_metacal`` or metadetect's
  ``config["metacal"]``); otherwise it corrects with white noise drawn from the weight.
* ``bmask`` and ``ormask`` are both the cell mask: the coadd mask is already the OR of the
  used inputs' masks under the resampling kernel, which is what ``ormask`` means to
  metadetect, and bad input pixels got no weight rather than masking the coadd pixel.
* The PSF ``weight`` is a constant array of ones: the stamp is noise free, and only its
  relative weights matter to a PSF fit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcoadd.errors import CellCoaddRangeError, EmptyCellError, MissingDependencyError, ShearError
from cellcoadd.geometry.wcs_utils import local_jacobian
from cellcoadd.model.cell_coadd import CellCoadd

#: Keys of the ``jacobian`` entry of :func:`to_observation`.
JACOBIAN_KEYS: tuple[str, ...] = ("row0", "col0", "dudrow", "dudcol", "dvdrow", "dvdcol")

_NGMIX_MISSING = (
    "ngmix is an optional dependency of cellcoadd and is not installed. It is not on the "
    "package index cellcoadd is installed from, so 'pip install ngmix' may fail: get it "
    "from conda-forge ('conda install -c conda-forge ngmix') or from its source, "
    "https://github.com/esheldon/ngmix ('pip install .' in a checkout; it needs numpy, "
    "scipy and numba). Or use cellcoadd.shear.to_observation, which returns plain numpy "
    "arrays (docs/shear.md, 'Feeding a cell to ngmix and metadetect')"
)


def _noise_variance(cell: CellCoadd) -> float:
    """Mean over the realizations of their pixel variance in the inner region (image units^2)."""
    inner_noise = np.asarray(cell.inner.noise, dtype=np.float64)
    variances = []
    for plane in inner_noise:
        finite = plane[np.isfinite(plane)]
        if finite.size > 1:
            variances.append(float(np.var(finite)))
    variance = float(np.mean(variances)) if variances else float("nan")
    if not np.isfinite(variance) or variance <= 0.0:
        raise ShearError(
            f"cell {cell.index} of tract {cell.tract}: its noise realizations give no "
            f"positive variance (got {variance})",
            cell=cell.index,
            value=variance,
        )
    return variance


def to_observation(cell: CellCoadd, noise_index: int = 0) -> dict[str, Any]:
    """The content of an ngmix-style observation of ``cell``, as numpy arrays.

    Parameters
    ----------
    cell : CellCoadd
        A non-empty cell coadd with at least one noise realization.
    noise_index : int
        Which of the cell's noise realizations to hand over as ``noise`` (for
        metacalibration's correlated-noise correction).

    Returns
    -------
    dict
        ``image`` (float64 copy of the cell image), ``weight`` (constant ``1 / var``),
        ``noise`` (float64 copy of ``cell.noise[noise_index]``), ``bmask`` and ``ormask``
        (int32 copies of the cell mask), ``mfrac`` (float64), ``psf`` (``{"image",
        "weight"}``), ``jacobian`` (``row0, col0, dudrow, dudcol, dvdrow, dvdcol``; floats,
        arcsec/pixel) and ``meta`` (``tract``, ``cell``, ``noise_index``,
        ``noise_variance``, ``n_used``). Arrays have the outer-box shape, except the PSF
        stamp. See the module docstring for the conventions.

    Raises
    ------
    EmptyCellError
        If no input contributed to the cell.
    ValueError
        If the cell has no noise realization ``noise_index``, or its noise has no
        positive variance.
    """
    name = f"cell {cell.index} of tract {cell.tract}"
    if cell.is_empty:
        raise EmptyCellError(
            f"{name} is empty (no input covered it; {len(cell.inputs)} rejected): "
            "there is nothing to measure",
            cell=cell.index,
        )
    if not 0 <= noise_index < cell.n_noise:
        raise CellCoaddRangeError(
            f"{name} has {cell.n_noise} noise realizations, so noise_index must be in "
            f"[0, {cell.n_noise}), got {noise_index}"
            + ("; build it with BuildConfig(n_noise >= 1)" if cell.n_noise == 0 else ""),
            value=noise_index,
            low=0,
            high=cell.n_noise,
            cell=cell.index,
        )
    variance = _noise_variance(cell)
    ny, nx = cell.shape
    row0, col0 = ny // 2, nx // 2
    jac = local_jacobian(cell.wcs, col0, row0)
    psf = np.array(cell.psf, dtype=np.float64)
    return {
        "image": np.array(cell.image, dtype=np.float64),
        "weight": np.full((ny, nx), 1.0 / variance),
        "noise": np.array(cell.noise[noise_index], dtype=np.float64),
        "bmask": np.array(cell.mask, dtype=np.int32),
        "ormask": np.array(cell.mask, dtype=np.int32),
        "mfrac": np.array(cell.mfrac, dtype=np.float64),
        "psf": {"image": psf, "weight": np.ones_like(psf)},
        "jacobian": {
            "row0": float(row0),
            "col0": float(col0),
            "dudrow": float(jac[0, 1]),
            "dudcol": float(jac[0, 0]),
            "dvdrow": float(jac[1, 1]),
            "dvdcol": float(jac[1, 0]),
        },
        "meta": {
            "tract": cell.tract,
            "cell": tuple(cell.index),
            "noise_index": int(noise_index),
            "noise_variance": variance,
            "n_used": cell.n_used,
        },
    }


def observation_jacobian(observation: dict[str, Any]) -> np.ndarray:
    """``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/pixel) of a :func:`to_observation` dict.

    This is the form :func:`cellcoadd.shear.measure_metacal` takes.
    """
    jac = observation["jacobian"]
    return np.array([[jac["dudcol"], jac["dudrow"]], [jac["dvdcol"], jac["dvdrow"]]])


def to_ngmix(cell: CellCoadd, noise_index: int = 0) -> Any:
    """An ``ngmix.Observation`` of ``cell`` (ngmix is optional).

    The observation holds the image, weight, noise realization, ``bmask``, ``ormask``,
    ``mfrac`` and an ``ngmix.Jacobian`` centred on the cell-centre pixel; its ``psf`` is
    an ``ngmix.Observation`` of the PSF stamp with the same jacobian derivatives, centred
    on the stamp's central pixel. ``meta`` is that of :func:`to_observation`.

    Raises
    ------
    ImportError
        If ngmix is not installed (with instructions).
    EmptyCellError, ValueError
        As :func:`to_observation`.
    """
    try:
        import ngmix
    except ImportError as err:
        raise MissingDependencyError(_NGMIX_MISSING, package="ngmix") from err
    observation = to_observation(cell, noise_index)
    jac = observation["jacobian"]
    derivatives = {key: jac[key] for key in ("dudrow", "dudcol", "dvdrow", "dvdcol")}
    psf_image = observation["psf"]["image"]
    psf_centre = (psf_image.shape[0] - 1) / 2.0
    psf_obs = ngmix.Observation(
        psf_image,
        weight=observation["psf"]["weight"],
        jacobian=ngmix.Jacobian(row=psf_centre, col=psf_centre, **derivatives),
    )
    return ngmix.Observation(
        observation["image"],
        weight=observation["weight"],
        bmask=observation["bmask"],
        ormask=observation["ormask"],
        noise=observation["noise"],
        mfrac=observation["mfrac"],
        jacobian=ngmix.Jacobian(row=jac["row0"], col=jac["col0"], **derivatives),
        psf=psf_obs,
        meta=dict(observation["meta"]),
    )


__all__ = [
    "JACOBIAN_KEYS",
    "EmptyCellError",
    "observation_jacobian",
    "to_ngmix",
    "to_observation",
]
