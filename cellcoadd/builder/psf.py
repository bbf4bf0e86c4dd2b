"""Drawing an exposure's PSF where a cell centre falls, with the image's sub-pixel phase."""

from __future__ import annotations

import galsim
import numpy as np

from cellcoadd.errors import PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.model.exposure import Exposure


def draw_exposure_psf(exposure: Exposure, x: float, y: float, box: Box) -> np.ndarray:
    """Image of a unit-flux point source at exposure pixel ``(x, y)``, over ``box``.

    The PSF is drawn through the local Jacobian of the exposure WCS at ``(x, y)``; a
    profile PSF is convolved with the pixel (GalSim ``method="auto"``), an image PSF is
    interpolated as is (``method="no_pixel"``). The returned float64 array has
    ``box.shape`` with ``[0, 0]`` the pixel ``(box.x_start, box.y_start)``, so it is
    sampled exactly like the exposure's image.

    Raises
    ------
    PsfError
        When the PSF model fails or gives non-finite or zero-flux values.
    """
    try:
        profile = exposure.psf_profile(x, y)
        jac = exposure.local_jacobian(x, y)
        wcs = galsim.JacobianWCS(jac[0, 0], jac[0, 1], jac[1, 0], jac[1, 1])
        bounds = galsim.BoundsI(box.x_start, box.x_stop - 1, box.y_start, box.y_stop - 1)
        image = galsim.ImageD(bounds, wcs=wcs)
        method = "no_pixel" if exposure.psf_includes_pixel else "auto"
        profile.drawImage(image=image, center=galsim.PositionD(x, y), method=method)
    except PsfError:
        raise
    except Exception as err:  # any failure of a user PSF model becomes a rejection
        raise PsfError(f"PSF could not be drawn at ({x:.2f}, {y:.2f}): {err}") from err
    stamp = image.array.astype(np.float64, copy=True)
    if not np.all(np.isfinite(stamp)) or stamp.sum() <= 0:
        raise PsfError(f"PSF drawn at ({x:.2f}, {y:.2f}) is non-finite or has no flux")
    return stamp


def psf_moments(stamp: np.ndarray, jacobian: np.ndarray) -> dict[str, float]:
    """Adaptive moments of a PSF stamp: FWHM (arcsec, Gaussian equivalent), e1, e2, T.

    ``T = 2 sigma^2`` in arcsec^2; ``e1, e2`` are distortions. NaN when moments fail.
    """
    pixel = float(np.sqrt(abs(np.linalg.det(jacobian))))
    try:
        shape = galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp), strict=True)
    except galsim.GalSimError:
        return {"psf_fwhm": np.nan, "psf_e1": np.nan, "psf_e2": np.nan, "psf_T": np.nan}
    sigma = shape.moments_sigma * pixel
    return {
        "psf_fwhm": float(2.0 * np.sqrt(2.0 * np.log(2.0)) * sigma),
        "psf_e1": float(shape.observed_shape.e1),
        "psf_e2": float(shape.observed_shape.e2),
        "psf_T": float(2.0 * sigma**2),
    }
