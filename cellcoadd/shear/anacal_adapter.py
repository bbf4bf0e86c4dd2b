"""FPFS shapes and their shear responses on a cell through AnaCal's Python API (optional).

`AnaCal <https://github.com/mr-superonion/AnaCal>`_ (``pip install 'cellcoadd[anacal]'``,
``anacal>=0.8``) measures FPFS shapelet ellipticities ``e1, e2`` together with their
analytic shear responses ``de_i/dg_j``, so the mean shear is ``<e> / <de/dg>`` with no
image manipulation. :func:`measure_fpfs` feeds it one cell (or a stamp of one) through
:func:`anacal.fpfs.process_image`:

* the image, forced at the given centre (AnaCal's detector is not run);
* the PSF stamp zero-padded (or cropped) to AnaCal's ``npix x npix`` stamp with its
  centre pixel on ``(npix // 2, npix // 2)``, where AnaCal puts the FFT origin;
* the cell's noise realization, which AnaCal measures turned by 90 degrees and adds to
  the image's measurement to cancel the noise bias of the non-linear shape (it must have
  the image's noise properties, correlations included: a coadd noise realization has);
* the *measured* pixel variance of that realization (``to_observation``'s
  ``meta["noise_variance"]``), not the stored variance plane, which ignores the averaging
  of the resampling and is higher (x1.3 on the validation stamps, 0.27 to 0.2 arcsec).
  It sets only the errors and ``s2n``.

AnaCal takes a scalar pixel scale: :func:`measure_fpfs` passes ``sqrt(|det J|)`` of the
cell jacobian, which is exact only where the jacobian is diagonal with equal entries up
to sign (a cell of a tangent-plane tract near its centre: see the jacobian note of
docs/shear.md). A parity flip (``det J < 0``, e.g. ``u`` West along ``+x``) turns ``g2``
around; the sky-frame ``e2`` and cross responses are returned.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcoadd.errors import CellCoaddRangeError, MissingDependencyError, ShearError
from cellcoadd.shear.response import Groups, paired_shear_bias

#: One AnaCal measurement: ``flags`` (0: good, :data:`ANACAL_FAILED`), the ellipticities,
#: their shear responses, the flux moment ``m00`` and AnaCal's ``flux`` and ``s2n``.
ANACAL_DTYPE = np.dtype(
    [
        ("flags", "i4"),
        ("e1", "f8"),
        ("e2", "f8"),
        ("de1_dg1", "f8"),
        ("de1_dg2", "f8"),
        ("de2_dg1", "f8"),
        ("de2_dg2", "f8"),
        ("m00", "f8"),
        ("flux", "f8"),
        ("s2n", "f8"),
    ]
)
ANACAL_FAILED = 1

#: AnaCal's stamp size, pixels (even; the PSF stamp is padded to it).
DEFAULT_NPIX = 48
#: Scale of the FPFS shapelet kernel, arcsec (smaller kernels raise the scatter of
#: ``e+ - e-`` about the analytic response on the paper's stamps: 0.5 arcsec triples it).
DEFAULT_SIGMA_ARCSEC = 0.8
#: FPFS weighting constant of ``m00`` in ``e = M22 / (M00 + c0)``, image units.
DEFAULT_C0 = 30.0

_ANACAL_MISSING = (
    "AnaCal is an optional dependency of cellcoadd and is not installed: "
    "pip install 'cellcoadd[anacal]' (or 'anacal>=0.8')"
)


def require_anacal() -> Any:
    """The ``anacal`` module; ImportError naming the ``cellcoadd[anacal]`` extra if absent."""
    try:
        import anacal
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(_ANACAL_MISSING, package="anacal") from exc
    return anacal


def empty_anacal_record(flags: int = ANACAL_FAILED) -> np.ndarray:
    """A length-1 :data:`ANACAL_DTYPE` row with ``flags`` and NaN values."""
    record = np.zeros(1, dtype=ANACAL_DTYPE)
    for name in ANACAL_DTYPE.names or ():
        if name != "flags":
            record[name] = np.nan
    record["flags"] = flags
    return record


def padded_psf(psf: np.ndarray, npix: int) -> np.ndarray:
    """``psf`` (odd stamp centred on its middle pixel) on an ``npix x npix`` grid.

    The middle pixel lands on ``(npix // 2, npix // 2)``; the stamp is zero-padded, or
    cropped symmetrically when larger than ``npix``.
    """
    psf = np.asarray(psf, dtype=np.float64)
    ny, nx = psf.shape
    if ny % 2 == 0 or nx % 2 == 0:
        raise ShearError(f"the PSF stamp must have odd sides, got {psf.shape}", value=psf.shape)
    out = np.zeros((npix, npix))
    half = npix // 2
    # source rows cy - half .. cy - half + npix - 1 go to rows 0 .. npix - 1
    src = []
    dst = []
    for n in (ny, nx):
        start = n // 2 - half
        lo, hi = max(start, 0), min(start + npix, n)
        src.append(slice(lo, hi))
        dst.append(slice(lo - start, hi - start))
    out[dst[0], dst[1]] = psf[src[0], src[1]]
    return out


def measure_fpfs(
    image: np.ndarray,
    psf: np.ndarray,
    noise: np.ndarray,
    jacobian: np.ndarray,
    noise_variance: float,
    centre: tuple[float, float],
    *,
    npix: int = DEFAULT_NPIX,
    sigma_arcsec: float = DEFAULT_SIGMA_ARCSEC,
    c0: float = DEFAULT_C0,
) -> np.ndarray:
    """FPFS shape and shear responses of the object at ``centre`` of a cell image.

    Parameters
    ----------
    image, noise : ndarray
        The cell image and one noise realization coadded like it (same shape).
    psf : ndarray
        Odd PSF stamp centred on its middle pixel (the cell's ``psf``); it is
        zero-padded to ``npix`` (see :func:`padded_psf`).
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel at the object. AnaCal takes a
        scalar scale, ``sqrt(|det J|)``: exact only for a diagonal jacobian with equal
        entries up to sign (docs/shear.md, jacobian note).
    noise_variance : float
        Measured pixel variance of the noise realization (not the stored variance plane).
    centre : (float, float)
        ``(x, y)`` pixel of the object; AnaCal measures an ``npix`` stamp around it.
    npix : int
        AnaCal's stamp size (even).
    sigma_arcsec : float
        FPFS shapelet kernel scale, arcsec.
    c0 : float
        FPFS weighting constant, image units.

    Returns
    -------
    ndarray
        A length-1 :data:`ANACAL_DTYPE` row, ``e2`` and the cross responses in the sky
        frame (sign flipped for a parity-flipped jacobian).
    """
    anacal = require_anacal()
    image = np.ascontiguousarray(image, dtype=np.float64)
    noise = np.ascontiguousarray(noise, dtype=np.float64)
    if image.shape != noise.shape:
        raise ShearError(
            f"image {image.shape} and noise {noise.shape} differ in shape",
            value=(image.shape, noise.shape),
        )
    jac = np.asarray(jacobian, dtype=np.float64)
    det = float(np.linalg.det(jac))
    if det == 0.0 or not np.isfinite(det):
        raise ShearError(f"singular jacobian {jac.tolist()}", value=jac.tolist())
    if not noise_variance > 0.0:
        raise CellCoaddRangeError(
            f"noise_variance must be > 0, got {noise_variance}", value=noise_variance, low=0.0
        )
    scale = float(np.sqrt(abs(det)))
    config = anacal.fpfs.FpfsConfig(npix=npix, sigma_shapelets1=sigma_arcsec, c0=c0)
    detection = np.array([(float(centre[1]), float(centre[0]))], dtype=[("y", "f8"), ("x", "f8")])
    catalogue = anacal.fpfs.process_image(
        fpfs_config=config,
        pixel_scale=scale,
        noise_variance=float(noise_variance),
        mag_zero=float(anacal.task.THRESHOLD_REF_MAG_ZERO),
        gal_array=image,
        psf_array=padded_psf(psf, npix),
        noise_array=noise,
        detection=detection,
    )
    row = catalogue[0]
    parity = 1.0 if det > 0.0 else -1.0
    out = np.zeros(1, dtype=ANACAL_DTYPE)
    out["e1"] = row["fpfs1_e1"]
    out["e2"] = parity * row["fpfs1_e2"]
    out["de1_dg1"] = row["fpfs1_de1_dg1"]
    out["de1_dg2"] = parity * row["fpfs1_de1_dg2"]
    out["de2_dg1"] = parity * row["fpfs1_de2_dg1"]
    out["de2_dg2"] = row["fpfs1_de2_dg2"]
    out["m00"] = row["fpfs1_m00"]
    out["flux"] = row["flux_fpfs1"]
    out["s2n"] = row["s2n_fpfs1"]
    values = [out[name][0] for name in ("e1", "e2", "de1_dg1", "de2_dg2")]
    out["flags"] = 0 if np.all(np.isfinite(values)) else ANACAL_FAILED
    return out


def paired_bias(
    plus: np.ndarray, minus: np.ndarray, true_g: float = 0.02, n_blocks: int = 100,
    group: Groups = 1,
) -> dict[str, float]:  # fmt: skip
    """``m1, c1, c2`` and jackknife errors from :data:`ANACAL_DTYPE` rows of paired objects.

    Row ``k`` of ``plus`` and ``minus`` is the same object sheared by ``(+true_g, 0)`` and
    ``(-true_g, 0)``; pairs with a flagged member are dropped. Each member's mean shear is
    ``g_i = sum e_i / sum de_i/dg_i``; ``m1 = (g+_1 - g-_1) / (2 true_g) - 1`` and
    ``c_i = (g+_i + g-_i) / 2``, with the errors of
    :func:`~cellcoadd.shear.response.multiplicative_bias` (pairs and each run of ``group``
    rows removed together).
    """
    if len(plus) != len(minus):
        raise ShearError(
            "plus and minus must hold the same objects (same length)", value=(len(plus), len(minus))
        )
    good = (plus["flags"] == 0) & (minus["flags"] == 0)
    columns = ("e1", "e2", "de1_dg1", "de2_dg2")
    terms = np.stack(
        [np.where(good, member[name], 0.0) for member in (plus, minus) for name in columns],
        axis=1,
    )

    return paired_shear_bias(
        terms, len(columns), lambda sums: sums[0:2] / sums[2:4], true_g, n_blocks, group
    )


__all__ = [
    "ANACAL_DTYPE",
    "ANACAL_FAILED",
    "DEFAULT_C0",
    "DEFAULT_NPIX",
    "DEFAULT_SIGMA_ARCSEC",
    "empty_anacal_record",
    "measure_fpfs",
    "padded_psf",
    "paired_bias",
    "require_anacal",
]
