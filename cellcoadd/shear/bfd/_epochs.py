"""Multi-epoch BFD: Fourier data of several exposures of one object combined linearly.

BFD moments are linear in the pixels (paper section 4.1; Bernstein et al. 2016): the
moments of ``K`` unaliased exposures of one object, each in sky coordinates about the same
sky origin and divided by its own PSF transform (:func:`~cellcoadd.shear.bfd.
fourier_data`), can be combined at the catalogue level. :func:`combine_epochs` makes their
weighted mean (the scale of one image), :func:`sum_epochs` their sum; either way the
samples are concatenated, so :func:`~cellcoadd.shear.bfd.measure_moments` of the
result re-centres the object jointly and gives the combined covariance (the epochs'
noise being independent).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cellcoadd.errors import BfdError
from cellcoadd.shear.bfd._moments import KData

__all__ = ["combine_epochs", "sum_epochs"]


def combine_epochs(
    epochs: Sequence[KData], weights: Sequence[float] | None = None, normalize: bool = True
) -> KData:
    """Multi-epoch Fourier data: moments are the weighted mean of the epochs' moments.

    BFD moments are linear in the pixels, so the moments of several unaliased exposures
    of one object (each with its own PSF and jacobian, all with the same sky origin) are
    combined by a weighted sum; here the weights are normalised to sum to 1 so that the
    result is on the scale of a single image (and of noise-free templates). The default
    weights are the inverse flux-moment variances; they never depend on the signal.
    ``normalize=False`` keeps the weights as given (:func:`sum_epochs`: all ones).
    """
    if not epochs:
        raise BfdError("combine_epochs needs at least one epoch")
    if any(e.weight != epochs[0].weight for e in epochs):
        raise BfdError("all epochs must use the same weight function")
    if weights is None:
        if any(e.noise is None for e in epochs):
            raise BfdError("default epoch weights need the noise of every epoch")
        wts = np.array([1.0 / np.sum(e.weight.derivatives(e.kx**2 + e.ky**2)[0] ** 2 * e.noise)
                        for e in epochs])  # fmt: skip
    else:
        wts = np.asarray(weights, dtype=np.float64)
    if wts.shape != (len(epochs),) or np.any(wts < 0.0) or wts.sum() <= 0.0:
        raise BfdError(f"need one non-negative weight per epoch, got {wts}")
    if normalize:
        wts = wts / wts.sum()
    has_noise = all(e.noise is not None for e in epochs)
    return KData(
        kx=np.concatenate([e.kx for e in epochs]),
        ky=np.concatenate([e.ky for e in epochs]),
        values=np.concatenate([w * e.values for w, e in zip(wts, epochs, strict=True)]),
        noise=np.concatenate([w * w * e.noise for w, e in zip(wts, epochs, strict=True)])
        if has_noise
        else None,
        weight=epochs[0].weight,
    )


def sum_epochs(epochs: Sequence[KData]) -> KData:
    """Multi-epoch Fourier data whose moments are the *sum* of the epochs' moments.

    BFD moments are linear in the pixels (paper section 4.1; Bernstein et al. 2016), so
    the moments of ``K`` unaliased exposures of one object, each measured in sky
    coordinates about the same sky origin and divided by its own PSF transform, add up;
    the epochs' noise is independent, so their covariances add up too. The samples of all
    epochs are concatenated: :func:`~cellcoadd.shear.bfd.measure_moments` of the
    result gives the summed moments (re-centred jointly) and their summed covariance.
    Templates must be combined the same way (the sum of ``K`` epochs is ``K`` times the
    galaxy's moments).
    """
    return combine_epochs(epochs, weights=[1.0] * len(epochs), normalize=False)
