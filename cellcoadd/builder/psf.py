"""Drawing an exposure's PSF where a cell centre falls, with the image's sub-pixel phase."""

from __future__ import annotations

import galsim
import numpy as np

from cellcoadd.errors import PsfError
from cellcoadd.geometry.box import Box
from cellcoadd.model.exposure import Exposure


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
