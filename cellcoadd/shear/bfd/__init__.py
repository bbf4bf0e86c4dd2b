"""Bayesian Fourier Domain (BFD) shear on cells: the paper's second method (section 4.1).

BFD (Bernstein & Armstrong 2014; Bernstein et al. 2016) compresses each galaxy into linear
Fourier-space moments of its PSF-deconvolved image, ``M = (M_F, M_R, M_E1, M_E2)``
weighted by the k-sigma weight (``N = 4``, ``sigma = 1`` arcsec in the paper), compares
them with a prior of deep *templates* sheared analytically, and sums the per-galaxy
Taylor coefficients ``P, Q, R`` of the likelihood in the shear into the posterior mean
``g = R_tot^-1 Q_tot``.

On a cell coadd the moment covariance comes from the noise realizations, which are coadded
exactly like the image: their power spectrum (:func:`noise_power`) is the coadd's
correlated-noise power. Multi-epoch BFD combines the per-epoch moments linearly
(:func:`combine_epochs`, a weighted mean, or :func:`sum_epochs`, their sum).

Typical use::

    from cellcoadd.shear import bfd
    targets = [bfd.bfd_moments(stamp, cell.psf, jac, noise_images=cell.noise) for stamp in ...]
    deep = [bfd.fourier_data(img, psf, jac) for img in deep_images]
    prior = bfd.TemplatePrior.from_templates(deep, targets[0].cov_even, targets[0].cov_odd)
    g, cov = bfd.estimate_shear(prior.pqr(targets), prior)

Conventions (PSF includes the pixel; jacobian in arcsec/pixel, GalSim ``u`` West /
``v`` North; ``k`` in rad/arcsec; units of the moments) are documented with the
implementation: the Fourier data and moments in ``_moments.py``, the combination of epochs
in ``_epochs.py``, the template prior, selection and shear estimate in ``_prior.py``; see
also ``docs/shear.md``. Those modules are private: import from ``cellcoadd.shear.bfd``.
"""

from __future__ import annotations

from cellcoadd.errors import BfdError
from cellcoadd.shear.bfd import _epochs, _moments, _prior
from cellcoadd.shear.bfd._epochs import *  # noqa: F403
from cellcoadd.shear.bfd._moments import *  # noqa: F403
from cellcoadd.shear.bfd._prior import *  # noqa: F403

__all__: list[str] = ["BfdError"]
__all__ += _moments.__all__
__all__ += _epochs.__all__
__all__ += _prior.__all__
