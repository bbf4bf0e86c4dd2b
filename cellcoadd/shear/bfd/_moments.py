"""BFD moments (Bernstein & Armstrong 2014; Bernstein et al. 2016) of PSF-deconvolved images.

This module turns a pixel image into *Fourier data* (:class:`KData`) and measures the BFD
moments and their noise covariance from it; ``_prior.py`` builds the template prior and
the per-galaxy ``P, Q, R``. Public names are imported from :mod:`cellcoadd.shear.bfd`.

Conventions and units
---------------------
* ``image`` (and each noise realization) is indexed ``[y, x]``, pixel centres at integer
  0-based coordinates; the moments are measured about ``centre`` (default the pixel
  ``(nx // 2, ny // 2)``), then about the point where the odd moments vanish.
* ``psf`` is an odd stamp centred on its central pixel that *includes the pixel response*
  (as a star looks); it is normalised so its transform is 1 at ``k = 0``. Because the image
  contains the same pixel response, ``I~ / T~`` is the transform of the galaxy itself.
* ``jacobian = [[du/dx, du/dy], [dv/dx, dv/dy]]`` in arcsec/pixel, GalSim sky coordinates
  (``u`` West, ``v`` North). Wavenumbers ``k = (k_u, k_v)`` are in **rad/arcsec** in those
  sky coordinates (``k_pix = J^T k``), so the weight's ``sigma`` is in **arcsec** (as in
  the public ``bfd`` code and Bernstein et al. 2016; the paper's ``sigma_k = 1`` is
  1 arcsec). Shear ``g1 > 0`` stretches along ``u``, ``g2 > 0`` along ``u = v`` (GalSim).
* The transform is ``I~(k) = sum_pixels I_p exp(-i k.(x_p - centre))`` and each moment is
  the Riemann sum of the paper's integral, ``M = sum_k d2k f(k) I~(k) / T~(k)`` with
  ``d2k = (2 pi)^2 / (nx ny |det J|)`` (rad/arcsec)^2. With image pixels in flux units,
  ``M_F`` is in flux arcsec^-2 (a point source of flux ``F`` has
  ``M_F = 2 pi F N / ((N + 1) sigma^2)``), ``M_R, M_E1, M_E2`` in flux arcsec^-4 and the
  odd (centroid) moments ``M_X, M_Y`` in flux arcsec^-3.
* Moments, in order: ``M_F = sum W``, ``M_R = sum W k^2``, ``M_E1 = sum W (k_u^2 - k_v^2)``,
  ``M_E2 = sum W 2 k_u k_v`` (even) and ``M_X = sum W i k_u``, ``M_Y = sum W i k_v`` (odd),
  each times ``d2k I~/T~``; ``W`` is the k-sigma weight :class:`KSigmaWeight`.
* Noise: ``C_ab = sum_k f_a(k) conj(f_b(k)) |d2k / T~(k)|^2 P_n(k)`` with ``P_n(k)`` the noise
  power spectrum (the mean ``|FFT|^2`` of the noise realizations, cut in tiles of the
  image's shape), so the correlations the coadd's resampling puts in the noise are
  accounted for. Even and odd moments are uncorrelated (``P_n(k) = P_n(-k)``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cellcoadd.errors import BfdError

__all__ = [
    "DEFAULT_OVERSAMPLE",
    "EVEN_NAMES",
    "MIRROR_SIGNS",
    "ODD_NAMES",
    "KData",
    "KSigmaWeight",
    "Moments",
    "bfd_moments",
    "centroid_jacobian",
    "fourier_data",
    "measure_moments",
    "moment_coefficients",
    "noise_power",
]

#: Names of the even moments (the shear-sensitive set of the paper's eq. for M_obs).
EVEN_NAMES: tuple[str, ...] = ("F", "R", "E1", "E2")
#: Names of the odd (centroid) moments, nulled by choosing the centre.
ODD_NAMES: tuple[str, ...] = ("X", "Y")

#: Signs ``MIRROR_SIGNS[a, d]`` of moment ``a`` (``F, R, E1, E2, X, Y``), term ``d``
#: (``value, d/dg1, d/dg2, d2/dg1^2, d2/dg1dg2, d2/dg2^2``) under the mirror ``u -> -u``
#: (:meth:`KData.mirrored`): the coefficients are even in ``k_u`` except ``E2 ~ k_u k_v``
#: and ``X ~ i k_u``, and the mirror of the object sheared by ``(g1, g2)`` is the mirror
#: image sheared by ``(g1, -g2)``, which flips the odd powers of ``g2``.
MIRROR_SIGNS: np.ndarray = np.outer(
    [1.0, 1.0, 1.0, -1.0, -1.0, 1.0], [1.0, 1.0, -1.0, 1.0, -1.0, 1.0]
)
MIRROR_SIGNS.flags.writeable = False

#: Default k-space oversampling (zero-padding factor) of :func:`fourier_data` and
#: :func:`bfd_moments`: the smallest whose high-S/N shear check agrees with the converged
#: (8-fold) one, to 7e-6 in m1 against 1e-4 for 3-fold and 0.03 for none
#: (docs/validation.md, "k sampling"); it costs ~16 times the unpadded transform.
DEFAULT_OVERSAMPLE = 4


@dataclass(frozen=True)
class KSigmaWeight:
    """The k-sigma weight ``W(k^2) = (1 - k^2 sigma^2 / (2N))^N`` for ``k < sqrt(2N)/sigma``.

    Parameters
    ----------
    sigma : float
        Scale in arcsec (``k`` in rad/arcsec); near ``k = 0`` the weight is a Gaussian
        ``exp(-k^2 sigma^2 / 2)``. The paper uses 1 arcsec.
    n : int
        Power ``N`` (the paper: 4). ``N >= 3`` makes ``W`` twice differentiable at the
        cut-off, which the second shear derivatives need.
    """

    sigma: float = 1.0
    n: int = 4

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma) and self.sigma > 0.0):
            raise BfdError(f"KSigmaWeight.sigma must be positive (arcsec), got {self.sigma}")
        if int(self.n) != self.n or self.n < 3:
            raise BfdError(f"KSigmaWeight.n must be an integer >= 3, got {self.n}")

    @property
    def kmax(self) -> float:
        """Cut-off wavenumber ``sqrt(2N) / sigma`` (rad/arcsec)."""
        return float(np.sqrt(2.0 * self.n) / self.sigma)

    def derivatives(self, ksq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``W``, ``dW/d(k^2)`` and ``d^2W/d(k^2)^2`` at ``ksq`` ((rad/arcsec)^2)."""
        a = self.sigma**2 / (2.0 * self.n)
        u = np.clip(1.0 - np.asarray(ksq, dtype=np.float64) * a, 0.0, None)
        n = self.n
        return u**n, -n * a * u ** (n - 1), n * (n - 1) * a * a * u ** (n - 2)


@dataclass(frozen=True, eq=False)
class KData:
    """PSF-deconvolved Fourier samples of one object (or several epochs of it).

    Attributes
    ----------
    kx, ky : ndarray, shape (n,)
        Wavenumbers ``k_u, k_v`` (rad/arcsec) inside the weight's support.
    values : ndarray of complex, shape (n,)
        ``d2k I~(k) / T~(k)`` (flux arcsec^-2): moments are ``sum f(k) values``.
    noise : ndarray, shape (n,) or None
        ``E|noise part of values|^2`` per sample (same units squared), or None.
    weight : KSigmaWeight
        The weight the samples were cut for.
    """

    kx: np.ndarray
    ky: np.ndarray
    values: np.ndarray
    noise: np.ndarray | None
    weight: KSigmaWeight

    def shifted(self, offset: np.ndarray) -> KData:
        """The same object seen from an origin moved by ``offset = (du, dv)`` arcsec."""
        du, dv = np.asarray(offset, dtype=np.float64)
        return replace(self, values=self.values * np.exp(1j * (self.kx * du + self.ky * dv)))

    def mirrored(self) -> KData:
        """The mirror image ``I(u, v) -> I(-u, v)`` (about the ``v`` axis of the origin).

        Its transform at ``(k_u, k_v)`` is the original's at ``(-k_u, k_v)``: the same
        samples at negated ``k_u``. Its moments and their shear derivatives are the
        original's times :data:`MIRROR_SIGNS`.
        """
        return replace(self, kx=-self.kx)


@dataclass(frozen=True, eq=False)
class Moments:
    """BFD moments of one object about the point where its odd moments vanish.

    Attributes
    ----------
    even : ndarray, shape (4,)
        ``M_F, M_R, M_E1, M_E2`` (units in the module docstring).
    odd : ndarray, shape (2,)
        ``M_X, M_Y`` at ``centre`` (~0 when ``converged``).
    cov_even, cov_odd : ndarray, shapes (4, 4) and (2, 2), or None
        Noise covariances (None without noise information).
    centre : ndarray, shape (2,)
        Offset ``(du, dv)`` (arcsec) of the measurement origin from the stamp centre.
    converged : bool
        Whether the centring converged (False: do not use the object).
    """

    even: np.ndarray
    odd: np.ndarray
    cov_even: np.ndarray | None
    cov_odd: np.ndarray | None
    centre: np.ndarray
    converged: bool

    @property
    def snr(self) -> float:
        """Flux signal-to-noise ``M_F / sqrt(C_FF)`` (nan without a covariance)."""
        if self.cov_even is None:
            return float("nan")
        return float(self.even[0] / np.sqrt(self.cov_even[0, 0]))


def moment_coefficients(
    kx: np.ndarray, ky: np.ndarray, weight: KSigmaWeight, derivatives: bool = False
) -> np.ndarray:
    """Coefficients ``f_a(k)`` of the six moments and, optionally, their shear derivatives.

    Shearing an object by ``g`` changes its moments as ``M_a(g) = sum_k f_a(A^-1 k) I~(k)``
    (``A`` the GalSim shear matrix, ``det A = 1``); ``A^-1 = 1 - G + |g|^2/2 + O(g^3)`` with
    ``G = [[g1, g2], [g2, -g1]]`` gives the exact first and second derivatives at ``g = 0``.

    Parameters
    ----------
    kx, ky : ndarray, shape (n,)
        Wavenumbers (rad/arcsec).
    weight : KSigmaWeight
    derivatives : bool
        Also return ``d/dg1, d/dg2, d2/dg1^2, d2/dg1dg2, d2/dg2^2``.

    Returns
    -------
    ndarray of complex
        Shape ``(6, n)`` (moments ``F, R, E1, E2, X, Y``), or ``(6, 6, n)`` with the second
        axis ``value, d1, d2, d11, d12, d22`` when ``derivatives``.
    """
    kx = np.asarray(kx, dtype=np.float64)
    ky = np.asarray(ky, dtype=np.float64)
    ksq, e1, e2 = kx * kx + ky * ky, kx * kx - ky * ky, 2.0 * kx * ky
    w, dw, d2w = weight.derivatives(ksq)
    zero, one = np.zeros_like(kx), np.ones_like(kx)
    # Polynomials p_a(q) and their derivatives (value, 1, 2, 11, 12, 22) at g = 0.
    s = [ksq, -2.0 * e1, -2.0 * e2, 4.0 * ksq, zero, 4.0 * ksq]  # q^2
    polys = np.array(
        [
            [one, zero, zero, zero, zero, zero],
            s,
            [e1, -2.0 * ksq, zero, 4.0 * e1, 2.0 * e2, zero],
            [e2, zero, -2.0 * ksq, zero, 2.0 * e1, 4.0 * e2],
            [kx, -kx, -ky, kx, zero, kx],
            [ky, ky, -kx, ky, zero, ky],
        ],
        dtype=np.complex128,
    )
    polys[4:] *= 1j
    if not derivatives:
        return w * polys[:, 0]
    out = np.empty_like(polys)
    out[:, 0] = w * polys[:, 0]
    for j in (1, 2):
        out[:, j] = dw * s[j] * polys[:, 0] + w * polys[:, j]
    for idx, (j, l) in zip((3, 4, 5), ((1, 1), (1, 2), (2, 2)), strict=True):
        out[:, idx] = (
            d2w * s[j] * s[l] * polys[:, 0]
            + dw * (s[idx] * polys[:, 0] + s[j] * polys[:, l] + s[l] * polys[:, j])
            + w * polys[:, idx]
        )
    return out


def _sky_wavenumbers(shape: tuple[int, int], jacobian: np.ndarray) -> np.ndarray:
    """``(2, ny, nx)`` sky wavenumbers ``k = J^-T k_pix`` of the FFT grid (rad/arcsec)."""
    ny, nx = shape
    kpx = 2.0 * np.pi * np.fft.fftfreq(nx)
    kpy = 2.0 * np.pi * np.fft.fftfreq(ny)
    kpix = np.stack(np.broadcast_arrays(kpx[None, :], kpy[:, None]))
    return np.einsum("ij,jyx->iyx", np.linalg.inv(jacobian).T, kpix)


def _psf_transform(psf: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """DFT of the PSF stamp (origin at its centre) on the FFT grid of an image of ``shape``."""
    ny, nx = shape
    n = psf.shape[0]
    offsets = np.arange(n) - n // 2
    ex = np.exp(-2j * np.pi * np.outer(np.fft.fftfreq(nx), offsets))  # (nx, n)
    ey = np.exp(-2j * np.pi * np.outer(np.fft.fftfreq(ny), offsets))  # (ny, n)
    return np.asarray(ey @ psf @ ex.T)


def noise_power(
    noise_images: np.ndarray | Sequence[np.ndarray],
    shape: tuple[int, int],
    fft_shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Noise power ``E|FFT(noise)|^2`` on the FFT grid of an image of ``shape``.

    ``fft_shape`` (at least ``shape``): each tile is zero-padded to it before the FFT,
    giving the power of a zero-padded image (:func:`fourier_data` with ``oversample``).

    Every realization (at least ``shape``) is cut into non-overlapping tiles of ``shape``
    whose ``|FFT|^2`` are averaged: larger realizations (a whole cell) give a more
    precise spectrum. The realizations must have zero mean (no mean is subtracted: that
    would remove the ``k = 0`` power, which the flux moment weights most).
    """
    ny, nx = shape
    tiles = []
    for plane in noise_images:
        plane = np.asarray(plane, dtype=np.float64)
        if plane.ndim != 2 or plane.shape[0] < ny or plane.shape[1] < nx:
            raise BfdError(
                f"noise realizations must be 2-D and at least the image shape {shape}, "
                f"got {plane.shape}"
            )
        for y0 in range(0, plane.shape[0] - ny + 1, ny):
            for x0 in range(0, plane.shape[1] - nx + 1, nx):
                tiles.append(plane[y0 : y0 + ny, x0 : x0 + nx])
    if not tiles:
        raise BfdError("no noise realization was given")
    stack = np.array(tiles)
    if not np.all(np.isfinite(stack)):
        raise BfdError("noise realizations contain non-finite pixels")
    return np.asarray(np.mean(np.abs(np.fft.fft2(stack, s=fft_shape)) ** 2, axis=0))


def fourier_data(
    image: np.ndarray,
    psf: np.ndarray,
    jacobian: np.ndarray,
    noise_images: np.ndarray | Sequence[np.ndarray] | None = None,
    noise_variance: float | None = None,
    weight: KSigmaWeight | None = None,
    centre: tuple[float, float] | None = None,
    min_psf_transform: float = 1.0e-3,
    oversample: int = DEFAULT_OVERSAMPLE,
) -> KData:
    """Deconvolved Fourier samples of ``image`` inside the weight's support.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        Stamp or cell image (flux units), background subtracted, the object near ``centre``.
    psf : ndarray, shape (n, n), n odd
        PSF stamp including the pixel response, centred on its central pixel.
    jacobian : ndarray, shape (2, 2)
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]`` (arcsec/pixel).
    noise_images : ndarray (K, ny', nx') or sequence, optional
        Noise realizations coadded like the image (``cell.noise``), at least as large as
        the image: their power spectrum gives the moment covariance.
    noise_variance : float, optional
        White-noise pixel variance, used when ``noise_images`` is None.
    weight : KSigmaWeight, optional
        Default ``KSigmaWeight(sigma=1.0, n=4)`` (the paper).
    centre : (x, y), optional
        Pixel position of the origin (default ``(nx // 2, ny // 2)``).
    min_psf_transform : float
        Refuse a PSF whose transform falls below this inside the weight's support.
    oversample : int
        Sample the transform ``oversample`` times more finely in each direction, by
        zero-padding the image (the object must be inside it, as it is anyway); default
        :data:`DEFAULT_OVERSAMPLE`. ``1`` is the plain FFT of the stamp, whose shear
        derivatives are off by up to tens of per cent for small galaxies (see Notes).

    Notes
    -----
    The moments are Riemann sums over the FFT grid, of spacing ``2 pi / (n * scale)``;
    so are the analytic shear derivatives of a template's moments
    (:func:`moment_coefficients`), which equal the derivatives of the sheared object's
    sums only in the continuum limit. On a small stamp (48 pixels of 0.27 arcsec: 5.8
    grid steps out to ``kmax`` of the paper's weight) the two differ by up to tens of per
    cent in ``d M_E / d g`` for galaxies of ~0.1 arcsec half-light radius; ``oversample=4``
    brings them to ~1e-4. Zero-padded samples are correlated: the per-sample noise is
    scaled by ``oversample**2``, which gives the moment covariance for weights that are
    smooth on the scale of the coarse grid (the k-sigma weight is).
    """
    weight = KSigmaWeight() if weight is None else weight
    img = np.asarray(image, dtype=np.float64)
    jac = np.asarray(jacobian, dtype=np.float64)
    psf_arr = np.asarray(psf, dtype=np.float64)
    if img.ndim != 2 or not np.all(np.isfinite(img)):
        raise BfdError(f"image must be a finite 2-D array, got shape {img.shape}")
    if jac.shape != (2, 2) or not np.all(np.isfinite(jac)) or np.linalg.det(jac) == 0.0:
        raise BfdError(f"jacobian must be a finite non-singular 2x2 array, got {jac!r}")
    if psf_arr.ndim != 2 or psf_arr.shape[0] != psf_arr.shape[1] or psf_arr.shape[0] % 2 == 0:
        raise BfdError(f"psf must be an odd square stamp, got shape {psf_arr.shape}")
    if not np.isfinite(psf_arr.sum()) or psf_arr.sum() <= 0.0:
        raise BfdError("psf must be finite with a positive sum")
    if int(oversample) != oversample or oversample < 1:
        raise BfdError(f"oversample must be an integer >= 1, got {oversample}")
    ny0, nx0 = img.shape
    cx, cy = (nx0 // 2, ny0 // 2) if centre is None else centre
    ny, nx = ny0 * int(oversample), nx0 * int(oversample)
    k = _sky_wavenumbers((ny, nx), jac)
    ksq = k[0] ** 2 + k[1] ** 2
    support = ksq < weight.kmax**2
    # Every k of the support must have its -k on the grid (no Nyquist row or column), and
    # the support should stay clear of the pixel Nyquist frequency.
    fx, fy = np.abs(np.fft.fftfreq(nx)), np.abs(np.fft.fftfreq(ny))
    edge = (fx[None, :] >= 0.5 - 1.0 / nx) | (fy[:, None] >= 0.5 - 1.0 / ny)
    if np.any(support & edge):
        raise BfdError(
            f"the weight's support (kmax = {weight.kmax:.3g} rad/arcsec) reaches the pixel "
            "Nyquist frequency: use a larger weight sigma"
        )
    psf_t = _psf_transform(psf_arr / psf_arr.sum(), (ny, nx))[support]
    if np.min(np.abs(psf_t)) < min_psf_transform:
        raise BfdError(
            f"the PSF transform falls to {np.min(np.abs(psf_t)):.2g} (< {min_psf_transform}) "
            f"inside the weight's support (kmax = {weight.kmax:.3g} rad/arcsec): use a "
            "larger weight sigma"
        )
    d2k = (2.0 * np.pi) ** 2 / (nx * ny * abs(np.linalg.det(jac)))
    kx, ky = k[0][support], k[1][support]
    # FFT origin at pixel (0, 0); move it to (cx, cy).
    kpx = 2.0 * np.pi * np.fft.fftfreq(nx)
    kpy = 2.0 * np.pi * np.fft.fftfreq(ny)
    phase = np.exp(1j * (kpx[None, :] * cx + kpy[:, None] * cy))[support]
    values = np.fft.fft2(img, s=(ny, nx))[support] * phase * d2k / psf_t
    noise: np.ndarray | None = None
    correlation = float(oversample) ** 2  # zero-padded samples are correlated
    if noise_images is not None:
        power = noise_power(noise_images, (ny0, nx0), (ny, nx))[support]
        noise = correlation * power * (d2k / np.abs(psf_t)) ** 2
    elif noise_variance is not None:
        if not (np.isfinite(noise_variance) and noise_variance > 0.0):
            raise BfdError(f"noise_variance must be positive, got {noise_variance}")
        noise = correlation * noise_variance * nx0 * ny0 * (d2k / np.abs(psf_t)) ** 2
    return KData(kx=kx, ky=ky, values=values, noise=noise, weight=weight)


def _moments_at(data: KData, offset: np.ndarray, coeff: np.ndarray | None = None) -> np.ndarray:
    if coeff is None:
        coeff = moment_coefficients(data.kx, data.ky, data.weight)
    return np.real(coeff @ data.shifted(offset).values)


def _covariances(data: KData) -> tuple[np.ndarray | None, np.ndarray | None]:
    if data.noise is None:
        return None, None
    coeff = moment_coefficients(data.kx, data.ky, data.weight)
    cov = np.real((coeff * data.noise) @ coeff.conj().T)
    return cov[:4, :4], cov[4:, 4:]


def centroid_jacobian(even: np.ndarray) -> np.ndarray:
    """``d(M_X, M_Y) / d(position)`` of an object: ``[[R + E1, E2], [E2, R - E1]] / 2``.

    ``even`` may have a leading batch shape ``(..., >=4)``; units arcsec^-1 x moment.
    """
    f, r, e1, e2 = np.moveaxis(np.asarray(even)[..., :4], -1, 0)
    return 0.5 * np.stack([np.stack([r + e1, e2], -1), np.stack([e2, r - e1], -1)], -2)


def measure_moments(
    data: KData, recentre: bool = True, max_iter: int = 20, tol: float = 1.0e-6
) -> Moments:
    """Moments of ``data``, about the point where ``M_X = M_Y = 0`` when ``recentre``.

    The centre is found by Newton iterations on the odd moments (their derivative with
    respect to the origin is :func:`centroid_jacobian`); ``tol`` is in arcsec. If the
    iteration fails (non-positive-definite jacobian, a step beyond the weight's scale or
    no convergence) the moments at the last origin are returned with ``converged=False``.
    """
    offset = np.zeros(2)
    coeff = moment_coefficients(data.kx, data.ky, data.weight)
    converged = True
    if recentre:
        converged = False
        for _ in range(max_iter):
            m = _moments_at(data, offset, coeff)
            jac = centroid_jacobian(m)
            if not (jac[0, 0] > 0.0 and np.linalg.det(jac) > 0.0):
                break
            step = np.linalg.solve(jac, m[4:])
            if not np.all(np.isfinite(step)) or np.hypot(*step) > 3.0 * data.weight.sigma:
                break
            offset = offset + step
            if np.hypot(*step) < tol:
                converged = True
                break
    m = _moments_at(data, offset, coeff)
    cov_even, cov_odd = _covariances(data)
    return Moments(
        even=m[:4], odd=m[4:], cov_even=cov_even, cov_odd=cov_odd, centre=offset,
        converged=converged,
    )  # fmt: skip


def bfd_moments(
    image: np.ndarray,
    psf: np.ndarray,
    jacobian: np.ndarray,
    noise_images: np.ndarray | Sequence[np.ndarray] | None = None,
    noise_variance: float | None = None,
    weight: KSigmaWeight | None = None,
    centre: tuple[float, float] | None = None,
    recentre: bool = True,
    oversample: int = DEFAULT_OVERSAMPLE,
) -> Moments:
    """BFD moments (with covariance) of the object near ``centre`` of ``image``.

    Shorthand for ``measure_moments(fourier_data(...), recentre)``; see
    :func:`fourier_data` for the arguments and the module docstring for the conventions.
    ``Moments.centre`` is the offset (arcsec, ``u, v``) of the null-centroid point from
    the pixel ``centre``.
    """
    data = fourier_data(
        image, psf, jacobian, noise_images=noise_images, noise_variance=noise_variance,
        weight=weight, centre=centre, oversample=oversample,
    )  # fmt: skip
    return measure_moments(data, recentre=recentre)
