"""BFD template prior, per-galaxy ``P, Q, R``, selection term and the posterior mean shear.

The prior (Bernstein et al. 2016, section 2) is a sum over *template copies*: every deep
(noise-free or nearly so) template galaxy, at ``n_rotations`` orientations, on a grid of
positions ``x0`` around its null-centroid point. For a target with even moments ``M`` and,
by construction, odd moments ``0``::

    P(D|g) = sum_t w_t N_6((M, 0) - M_t(g); C)

with ``C = diag(C_even, C_odd)`` the target's moment covariance and ``M_t(g)`` the six
moments of copy ``t`` sheared by ``g``. The sum over positions is the integral over the
unknown true position (``w_t`` includes the area element ``d2x0``): with the odd moments in
the likelihood it gives each template its centroid (Jacobian) factor and the shear
dependence of it. The positions are a square grid of step ``shift_step`` in the whitened
odd-moment space, ``x0 = J_t^-1 L z`` (``L L^T = C_odd``, ``J_t`` the template's
:func:`~cellcoadd.shear.bfd.centroid_jacobian`), ``|z| <= shift_radius``.

With ``mirror`` every copy also enters as its mirror image ``u -> -u`` (the template's
mirror, at the mirrored position), each of the pair at half the weight: the unlensed
population BFD assumes is invariant under rotation *and* parity, and the rotations alone
make a finite template set isotropic but not parity-symmetric. The mirror's moments are
the copy's times :data:`~cellcoadd.shear.bfd.MIRROR_SIGNS` (``E2``, ``X`` and the odd
powers of ``g2`` change sign), so the mirrored copies cost no Fourier sums; for a
parity-symmetric covariance the prior's ``P, Q, R`` of a target and of its mirror image
(``E2 -> -E2``) then differ exactly by the signs of ``Q_2`` and ``R_12``.

``Q = dP/dg`` and ``R = d2P/dg2`` at ``g = 0`` follow analytically from the template
moments' shear derivatives (:func:`~cellcoadd.shear.bfd.moment_coefficients`)::

    Q_j = sum_t w_t G_t a_j,   R_jl = sum_t w_t G_t (a_j a_l - b_jl + c_jl)
    a_j = d.C^-1 dM_t/dg_j,   b_jl = dM_t/dg_j.C^-1 dM_t/dg_l,   c_jl = d.C^-1 d2M_t/dg_j dg_l

(``d = (M, 0) - M_t``, ``G_t`` the Gaussian). The posterior mean over many galaxies is
``g = R_tot^-1 Q_tot`` (paper eqs. for ``Q_tot``, ``R_tot``), its covariance ``R_tot^-1``.

Selection (paper section 4.1, Bernstein et al. 2016 section 2.3): targets are kept when
``snr_min < M_F / sigma_F < snr_max`` (``sigma_F^2 = C_FF`` of the prior). For each kept
galaxy the likelihood becomes ``P(D|g) / P_s(g)``, with ``P_s(g)`` the probability that a
galaxy of the template population passes the cut: ``sum_t w_t [Phi(u_hi) - Phi(u_lo)]``,
``u = (F_bound - F_t(g)) / sigma_F``, over the centred copies. Its expansion ``P_s, Q_s,
R_s`` adds ``-N Q_s / P_s`` to ``Q_tot`` and ``-N (Q_s Q_s^T / P_s^2 - R_s / P_s)`` to
``R_tot`` for ``N`` selected galaxies.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cellcoadd.errors import BfdError
from cellcoadd.shear.bfd._moments import (
    MIRROR_SIGNS,
    KData,
    Moments,
    centroid_jacobian,
    measure_moments,
    moment_coefficients,
)
from cellcoadd.shear.response import Groups, paired_shear_bias

__all__ = [
    "Pqr",
    "TemplatePrior",
    "bias_from_sums",
    "estimate_shear",
    "paired_bias",
    "paired_terms",
]

_PAIRS = ((0, 0), (0, 1), (1, 1))  # (j, l) of the second-derivative terms 3, 4, 5
#: Copies whose chi^2 exceeds the best one's by more than this (a relative weight below
#: exp(-35) ~ 6e-16) are skipped for a block of targets.
_CHI2_CUT = 70.0
_erf = np.vectorize(math.erf, otypes=[np.float64])


def _normal_cdf(u: np.ndarray) -> np.ndarray:
    return np.asarray(0.5 * (1.0 + _erf(u / np.sqrt(2.0))))


def _normal_pdf(u: np.ndarray) -> np.ndarray:
    return np.asarray(np.exp(-0.5 * u * u) / np.sqrt(2.0 * np.pi))


def _inverse_shear(g: tuple[float, float]) -> np.ndarray:
    g1, g2 = g
    gsq = g1 * g1 + g2 * g2
    if gsq >= 1.0:
        raise BfdError(f"|g| must be < 1, got {g}")
    return np.array([[1.0 - g1, -g2], [-g2, 1.0 + g1]]) / np.sqrt(1.0 - gsq)


def _half_plane(data: KData) -> KData:
    """The samples with ``k_u > 0`` (or ``k_u = 0 < k_v``) at twice their value, and
    ``k = 0``: the same real parts of every moment sum, from half the samples.

    The samples of a real image come in pairs ``k, -k`` with conjugate values, and every
    moment coefficient and its shear derivatives satisfy ``f(-k) = conj(f(k))`` (even
    moments: real even polynomials; odd ones: ``i`` times odd ones), as do the position
    phases; so ``Re sum_k f v = Re sum_half 2 f v (+ the k = 0 term)``. ``data`` is
    returned unchanged when its wavenumbers are not symmetric.
    """
    kx, ky = data.kx, data.ky
    half = (kx > 0.0) | ((kx == 0.0) & (ky > 0.0))
    origin = (kx == 0.0) & (ky == 0.0)
    if 2 * int(half.sum()) + int(origin.sum()) != kx.size:
        return data
    order = np.lexsort((ky, kx))
    mirror = np.lexsort((-ky, -kx))
    if not (np.array_equal(kx[order], -kx[mirror]) and np.array_equal(ky[order], -ky[mirror])):
        return data
    keep = half | origin
    values = np.where(half, 2.0, 1.0)[keep] * data.values[keep]
    noise = None if data.noise is None else data.noise[keep]
    return replace(data, kx=kx[keep], ky=ky[keep], values=values, noise=noise)


def _template_copies(
    data: KData,
    qx: np.ndarray,
    qy: np.ndarray,
    shear: tuple[float, float],
    to_x0: np.ndarray,
    zi: np.ndarray,
    grid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Moments (and shear derivatives) of a template's copies sheared by ``shear``: on the
    position grid, shape ``(r * s, 6, 6)``, and centred, shape ``(r, 4, 6)``."""
    a_inv = _inverse_shear(shear)
    sx = a_inv[0, 0] * qx + a_inv[0, 1] * qy
    sy = a_inv[1, 0] * qx + a_inv[1, 1] * qy
    coeff = moment_coefficients(sx, sy, data.weight, derivatives=True)  # (6,6,r,k)
    coeff = coeff * data.values
    shifted = _shifted_moments(coeff, qx, qy, to_x0, zi, grid)
    return shifted, np.real(coeff[:4].sum(-1)).transpose(2, 0, 1)


def _shifted_moments(
    coeff: np.ndarray,
    qx: np.ndarray,
    qy: np.ndarray,
    to_x0: np.ndarray,
    zi: np.ndarray,
    grid: np.ndarray,
) -> np.ndarray:
    """Moments and shear derivatives of a template's copies on its position grid.

    ``coeff`` (6, 6, r, k): the coefficients times the template's samples at the rotated
    wavenumbers ``q = (qx, qy)`` (r, k); the copy of rotation ``r`` at position ``s`` sits
    at ``x0 = to_x0[r] z_s`` with ``z_s = (zi[grid[0, s]], zi[grid[1, s]])``, so its
    moments are ``Re sum_k coeff exp(-i q.x0)``. Since ``q.x0 = p.z`` with
    ``p = to_x0^T q``, the phase factorises into one exponential per grid axis, and the
    sum over ``k`` is a real matrix product.

    Returns
    -------
    ndarray, shape (r * s, 6, 6)
        Copies in the order ``(rotation, position)``.
    """
    px = to_x0[:, 0, 0, None] * qx + to_x0[:, 1, 0, None] * qy  # (r, k)
    py = to_x0[:, 0, 1, None] * qx + to_x0[:, 1, 1, None] * qy
    ex = np.exp(-1j * px[:, None, :] * zi[None, :, None])  # (r, n_grid, k)
    ey = np.exp(-1j * py[:, None, :] * zi[None, :, None])
    phase = ex[:, grid[0]] * ey[:, grid[1]]  # (r, s, k)
    n_rot, n_k = qx.shape
    c = coeff.reshape(36, n_rot, n_k).transpose(1, 0, 2)  # (r, 36, k)
    # Re(c . phase) = Re c . Re phase - Im c . Im phase, as one real product per rotation
    stacked = np.concatenate([c.real, -c.imag], axis=2)  # (r, 36, 2k)
    waves = np.concatenate([phase.real, phase.imag], axis=2)  # (r, s, 2k)
    out = np.matmul(waves, stacked.transpose(0, 2, 1))  # (r, s, 36)
    return out.reshape(-1, 6, 6)


@dataclass(frozen=True, eq=False)
class Pqr:
    """``P``, ``Q``, ``R`` of targets, all scaled by ``exp(-log_scale)`` per target.

    Attributes
    ----------
    P : ndarray, shape (n,)
    Q : ndarray, shape (n, 2)
    R : ndarray, shape (n, 2, 2)
    log_scale : ndarray, shape (n,)
        The true values are ``P exp(log_scale)`` etc. (ratios ``Q/P``, ``R/P`` need none).
    selected : ndarray of bool, shape (n,)
        Converged targets inside the selection (others have ``P = Q = R = 0``).
    """

    P: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    log_scale: np.ndarray
    selected: np.ndarray

    @classmethod
    def concatenate(cls, parts: Sequence[Pqr]) -> Pqr:
        """All targets of several :class:`Pqr` (e.g. one per cell)."""
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                     ("P", "Q", "R", "log_scale", "selected")))  # fmt: skip


@dataclass(frozen=True, eq=False)
class TemplatePrior:
    """Template copies with their moments, shear derivatives and weights.

    Build it with :meth:`from_templates`. ``moments[t, a, d]``: copy ``t``, moment ``a`` in
    ``F, R, E1, E2, X, Y``, term ``d`` in ``value, d/dg1, d/dg2, d2/dg1^2, d2/dg1dg2,
    d2/dg2^2``; ``centred`` is the same for the unshifted copies (selection term).
    """

    moments: np.ndarray
    weights: np.ndarray
    centred: np.ndarray
    centred_weights: np.ndarray
    cov_even: np.ndarray
    cov_odd: np.ndarray
    snr_range: tuple[float, float] | None

    @classmethod
    def from_templates(
        cls,
        templates: Sequence[KData],
        cov_even: np.ndarray,
        cov_odd: np.ndarray,
        n_rotations: int = 8,
        shift_step: float = 0.8,
        shift_radius: float = 5.0,
        snr_range: tuple[float, float] | None = (5.0, 50.0),
        template_weights: Sequence[float] | None = None,
        shear: tuple[float, float] = (0.0, 0.0),
        mirror: bool = False,
    ) -> TemplatePrior:
        """The prior from deep templates, for targets with moment covariance ``cov_*``.

        Parameters
        ----------
        templates : sequence of KData
            Fourier data of deep galaxies (:func:`~cellcoadd.shear.bfd.fourier_data`
            of images with the same weight function; noise / 100 in the paper), drawn with
            random sub-pixel positions. Each is re-centred on its null-centroid point.
        cov_even, cov_odd : ndarray, shapes (4, 4) and (2, 2)
            The targets' moment covariance (e.g. ``Moments.cov_even``); the paper builds
            one prior per S/N range.
        n_rotations : int
            Orientations ``pi i / n_rotations`` of each template (>= 3 for isotropy of the
            ellipticity moments to second order).
        shift_step, shift_radius : float
            Position grid (in units of the centroid noise): step and radius.
        snr_range : (float, float) or None
            Flux S/N selection ``(5, 50)`` as in the paper, or None.
        template_weights : sequence of float, optional
            Relative weights of the templates (default equal).
        shear : (g1, g2)
            Build the prior for templates sheared by ``g`` (moments exact in ``g``; the
            derivatives are then with respect to a further shear). For tests.
        mirror : bool
            Add every copy's mirror image (``u -> -u``), the pair at half the copy's
            weight: a parity-symmetric prior, at twice the copies (the cost of ``P, Q,
            R`` doubles; building the prior costs the same, the mirrors' moments being
            sign flips of the copies'). Off by default: for galaxies without handedness
            (elliptical profiles) the rotations already make the prior parity-symmetric
            to well below its noise (docs/validation.md, "Mirror images in the prior").
        """
        cov_even = np.asarray(cov_even, dtype=np.float64)
        cov_odd = np.asarray(cov_odd, dtype=np.float64)
        if cov_even.shape != (4, 4) or cov_odd.shape != (2, 2):
            raise BfdError("cov_even must be 4x4 and cov_odd 2x2")
        if not templates:
            raise BfdError("no template")
        if n_rotations < 1 or shift_step <= 0.0 or shift_radius < 0.0:
            raise BfdError("need n_rotations >= 1, shift_step > 0 and shift_radius >= 0")
        tw = np.ones(len(templates)) if template_weights is None else np.asarray(template_weights)
        if tw.shape != (len(templates),) or np.any(tw < 0.0) or tw.sum() <= 0.0:
            raise BfdError("template_weights must be one non-negative number per template")
        tw = tw / tw.sum()
        chol_odd = np.linalg.cholesky(cov_odd)
        n = int(np.floor(shift_radius / shift_step))
        zi = np.arange(-n, n + 1) * shift_step
        steps = np.arange(2 * n + 1)
        grid = np.stack(np.meshgrid(steps, steps, indexing="ij")).reshape(2, -1)
        grid = grid[:, np.hypot(*zi[grid]) <= shift_radius + 1e-12]  # (2, positions)
        z = zi[grid].T  # (positions, 2)
        angles = np.pi * np.arange(n_rotations) / n_rotations
        cos, sin = np.cos(angles), np.sin(angles)
        _inverse_shear(shear)  # refuse |g| >= 1 before any work
        n_parity = 2 if mirror else 1
        moments, weights, centred = [], [], []
        for template, weight in zip(templates, tw, strict=True):
            m0 = measure_moments(template)
            if not m0.converged:
                raise BfdError("a template could not be centred (no null-centroid point)")
            data = _half_plane(template.shifted(m0.centre))
            # Rotated wavenumbers q = R k, shape (n_rot, 2, n_k).
            qx = cos[:, None] * data.kx - sin[:, None] * data.ky
            qy = sin[:, None] * data.kx + cos[:, None] * data.ky
            # The position grid comes from the unsheared copies (the same for any shear).
            unsheared = np.real(moment_coefficients(qx, qy, data.weight)[:4] @ data.values)
            jac = centroid_jacobian(unsheared.T)  # (r, 2, 2)
            if np.any(np.linalg.det(jac) <= 0.0):
                raise BfdError("a template has a non-positive centroid jacobian")
            to_x0 = np.linalg.solve(jac, chol_odd[None])  # (r, 2, 2): x0 = J^-1 L z
            copies, centres = _template_copies(data, qx, qy, shear, to_x0, zi, grid)
            moments.append(copies)
            centred.append(centres)
            if mirror:
                # The mirror of the template sheared by g is the mirror image of the
                # template sheared by (g1, -g2): the same copies when g2 = 0.
                if shear[1] != 0.0:
                    copies, centres = _template_copies(
                        data, qx, qy, (shear[0], -shear[1]), to_x0, zi, grid
                    )
                moments.append(copies * MIRROR_SIGNS)
                centred.append(centres * MIRROR_SIGNS[:4])
            area = np.abs(np.linalg.det(to_x0)) * shift_step**2
            copy_weights = np.repeat(area * weight / (n_rotations * n_parity), len(z))
            weights.append(np.tile(copy_weights, n_parity))
        return cls(
            moments=np.concatenate(moments),
            weights=np.concatenate(weights),
            centred=np.concatenate(centred),
            centred_weights=np.repeat(tw / (n_rotations * n_parity), n_rotations * n_parity),
            cov_even=cov_even,
            cov_odd=cov_odd,
            snr_range=snr_range,
        )

    @property
    def flux_bounds(self) -> tuple[float, float]:
        """Selection bounds on ``M_F`` (``snr_range`` times ``sqrt(C_FF)``)."""
        lo, hi = self.snr_range if self.snr_range is not None else (-np.inf, np.inf)
        sigma = float(np.sqrt(self.cov_even[0, 0]))
        return lo * sigma, hi * sigma

    def pqr(
        self,
        targets: Moments | Sequence[Moments] | np.ndarray,
        chunk: int = 4_000_000,
        block: int = 64,
    ) -> Pqr:
        """``P, Q, R`` of targets (their even moments, odd moments taken as zero).

        ``targets``: :class:`Moments` (one or a sequence; non-converged ones are not
        selected) or an array ``(n, 4)`` of even moments. The prior's covariance is used
        for every target. ``chunk`` bounds the number of (target, copy) pairs in memory.
        """
        if isinstance(targets, Moments):
            targets = [targets]
        if isinstance(targets, np.ndarray):
            even = np.atleast_2d(np.asarray(targets, dtype=np.float64))
            ok = np.ones(len(even), dtype=bool)
        else:
            even = np.array([t.even for t in targets], dtype=np.float64).reshape(-1, 4)
            ok = np.array([t.converged for t in targets], dtype=bool)
        if even.shape[1] != 4:
            raise BfdError(f"targets must have 4 even moments, got shape {even.shape}")
        lo, hi = self.flux_bounds
        selected = ok & (even[:, 0] > lo) & (even[:, 0] < hi)
        cov = np.zeros((6, 6))
        cov[:4, :4], cov[4:, 4:] = self.cov_even, self.cov_odd
        chol = np.linalg.cholesky(cov)
        norm = -3.0 * np.log(2.0 * np.pi) - np.log(np.diag(chol)).sum()
        y = np.linalg.solve(chol, self.moments.transpose(1, 0, 2).reshape(6, -1))
        y = y.reshape(6, len(self.moments), 6).transpose(2, 1, 0)  # (term, copy, 6)
        y0, y_sq = y[0], np.einsum("ti,ti->t", y[0], y[0])
        b = np.stack([np.einsum("ti,ti->t", y[1 + j], y[1 + l]) for j, l in _PAIRS])
        y0_dots = np.einsum("ti,dti->dt", y0, y[1:])  # (5, copy)
        y_derivs = np.ascontiguousarray(y[1:].transpose(0, 2, 1))  # (5, 6, copy)
        x_all = np.zeros((len(even), 6))
        x_all[:, :4] = even
        x_all = np.linalg.solve(chol, x_all.T).T
        n = len(even)
        P, Q, R = np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2, 2))
        log_scale = np.zeros(n)
        # Targets in flux order, in small blocks: each block only needs the copies whose
        # Gaussian is within exp(-CHI2_CUT / 2) of the best one for some target of the block.
        index = np.flatnonzero(selected)
        index = index[np.argsort(even[index, 0], kind="stable")]
        step = int(np.clip(chunk // max(1, len(y0)), 1, block))
        for start in range(0, len(index), step):
            rows = index[start : start + step]
            x = x_all[rows]
            chi2 = (x * x).sum(1)[:, None] - 2.0 * x @ y0.T + y_sq[None, :]
            low = chi2.min(axis=1)
            keep = np.flatnonzero(np.any(chi2 - low[:, None] < _CHI2_CUT, axis=0))
            g = np.exp(-0.5 * (chi2[:, keep] - low[:, None])) * self.weights[None, keep]
            # a[d] = (x - y0).C^-1 dM_d, shape (5, block, kept)
            a = np.matmul(x[None], y_derivs[:, :, keep]) - y0_dots[:, None, keep]
            P[rows] = g.sum(1)
            Q[rows] = np.stack([(g * a[0]).sum(1), (g * a[1]).sum(1)], -1)
            for k, (j, l) in enumerate(_PAIRS):
                r_jl = (g * (a[j] * a[l] - b[k][None, keep] + a[2 + k])).sum(1)
                R[rows, j, l] = R[rows, l, j] = r_jl
            log_scale[rows] = norm - 0.5 * low
        return Pqr(P=P, Q=Q, R=R, log_scale=log_scale, selected=selected)

    def selection_pqr(self) -> tuple[float, np.ndarray, np.ndarray]:
        """``P_s, Q_s, R_s``: the selection probability and its shear derivatives."""
        if self.snr_range is None:
            return 1.0, np.zeros(2), np.zeros((2, 2))
        lo, hi = self.flux_bounds
        sigma = float(np.sqrt(self.cov_even[0, 0]))
        flux = self.centred[:, 0]  # (copy, term)
        u_lo, u_hi = (lo - flux[:, 0]) / sigma, (hi - flux[:, 0]) / sigma
        p = _normal_cdf(u_hi) - _normal_cdf(u_lo)
        dp = (_normal_pdf(u_lo) - _normal_pdf(u_hi)) / sigma
        d2p = (u_lo * _normal_pdf(u_lo) - u_hi * _normal_pdf(u_hi)) / sigma**2
        w = self.centred_weights
        ps = float(np.sum(w * p))
        qs = np.array([np.sum(w * dp * flux[:, 1 + j]) for j in range(2)])
        rs = np.zeros((2, 2))
        for k, (j, l) in enumerate(_PAIRS):
            rs[j, l] = rs[l, j] = np.sum(
                w * (d2p * flux[:, 1 + j] * flux[:, 1 + l] + dp * flux[:, 3 + k])
            )
        return ps, qs, rs


def estimate_shear(
    pqr: Pqr | Sequence[Pqr], prior: TemplatePrior | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean shear ``g = R_tot^-1 Q_tot`` and its covariance ``R_tot^-1``.

    Parameters
    ----------
    pqr : Pqr or sequence of Pqr
        Per-target values (only ``selected`` targets count).
    prior : TemplatePrior, optional
        When given with a ``snr_range``, the selection term is added for the ``N``
        selected targets (the prior must be the one that produced ``pqr``).

    Returns
    -------
    g : ndarray, shape (2,)
    cov : ndarray, shape (2, 2)
    """
    values = pqr if isinstance(pqr, Pqr) else Pqr.concatenate(list(pqr))
    sel = values.selected & (values.P > 0.0)
    if not np.any(sel):
        raise BfdError("no selected target with P > 0")
    q = values.Q[sel] / values.P[sel, None]
    r = values.R[sel] / values.P[sel, None, None]
    q_tot = q.sum(0)
    r_tot = np.einsum("ni,nj->ij", q, q) - r.sum(0)
    if prior is not None and prior.snr_range is not None:
        ps, qs, rs = prior.selection_pqr()
        n_sel = int(sel.sum())
        q_tot = q_tot - n_sel * qs / ps
        r_tot = r_tot - n_sel * (np.outer(qs, qs) / ps**2 - rs / ps)
    cov = np.linalg.inv(r_tot)
    return cov @ q_tot, cov


def _per_target(pqr: Pqr) -> np.ndarray:
    """Per-target columns ``selected, Q/P (2), (Q/P)(Q/P)^T - R/P (4)``, zero if unselected."""
    sel = pqr.selected & (pqr.P > 0.0)
    p = np.where(sel, pqr.P, 1.0)
    q = np.where(sel[:, None], pqr.Q / p[:, None], 0.0)
    r = np.where(sel[:, None, None], pqr.R / p[:, None, None], 0.0)
    rr = np.einsum("ni,nj->nij", q, q) - r
    return np.column_stack([sel.astype(np.float64), q, rr.reshape(-1, 4)])


def _shear_from_sums(
    sums: np.ndarray, selection: tuple[float, np.ndarray, np.ndarray]
) -> np.ndarray:
    ps, qs, rs = selection
    n_sel = sums[0]
    q_tot = sums[1:3] - n_sel * qs / ps
    r_tot = sums[3:7].reshape(2, 2) - n_sel * (np.outer(qs, qs) / ps**2 - rs / ps)
    try:
        return np.asarray(np.linalg.solve(r_tot, q_tot))
    except np.linalg.LinAlgError:
        return np.full(2, np.nan)


def paired_terms(plus: Pqr, minus: Pqr) -> np.ndarray:
    """Per-object summable terms of paired targets: row ``k`` holds the ``+g`` member's
    ``selected, Q/P, (Q/P)(Q/P)^T - R/P`` (7 columns), then the ``-g`` member's.

    Sums of rows (all, or a jackknife's subsets) give the mean shears through
    :func:`bias_from_sums`.
    """
    if len(plus.P) != len(minus.P):
        raise BfdError("plus and minus must hold the same targets")
    return np.hstack([_per_target(plus), _per_target(minus)])


def bias_from_sums(
    sums: np.ndarray, selection: tuple[float, np.ndarray, np.ndarray], true_g: float
) -> np.ndarray:
    """``(m1, c1, c2)`` from summed :func:`paired_terms` (``selection``: the prior's
    :meth:`TemplatePrior.selection_pqr`)."""
    g_plus = _shear_from_sums(sums[:7], selection)
    g_minus = _shear_from_sums(sums[7:], selection)
    m1 = (g_plus[0] - g_minus[0]) / (2.0 * true_g) - 1.0
    return np.array([m1, 0.5 * (g_plus[0] + g_minus[0]), 0.5 * (g_plus[1] + g_minus[1])])


def paired_bias(
    plus: Pqr,
    minus: Pqr,
    prior: TemplatePrior,
    true_g: float = 0.02,
    n_blocks: int = 100,
    group: Groups = 1,
) -> dict[str, float]:
    """``m1, c1, c2`` and jackknife errors of BFD on paired ``+g`` / ``-g`` targets.

    Row ``k`` of ``plus`` and ``minus`` is the same object sheared by ``(+true_g, 0)`` and
    ``(-true_g, 0)``; ``g+-`` are the posterior mean shears (:func:`estimate_shear`, with
    the prior's selection term), ``m1 = (g+_1 - g-_1) / (2 true_g) - 1``, ``c_i = (g+_i +
    g-_i) / 2``. Jackknife as :func:`cellcoadd.shear.multiplicative_bias` (a pair's members
    and each ``group`` of consecutive rows removed together).
    """
    terms = paired_terms(plus, minus)
    selection = prior.selection_pqr()

    return paired_shear_bias(
        terms, 7, lambda sums: _shear_from_sums(sums, selection), true_g, n_blocks, group
    )
