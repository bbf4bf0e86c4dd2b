"""Mirror images in the BFD prior: the parity of the moments, a parity-symmetric prior, and
its normalisation (``TemplatePrior.from_templates(..., mirror=True)``)."""

import galsim
import numpy as np
import pytest

from cellcoadd.shear import bfd

SCALE = 0.27
JAC = np.array([[-SCALE, 0.0], [0.0, SCALE]])  # u West, as on the sky


def _lopsided_galaxy(rng: np.random.Generator) -> galsim.GSObject:
    """An elliptical disc with an off-centre knot: no mirror symmetry about any axis, so a
    template set of them is not parity-symmetric."""
    disc = galsim.Exponential(half_light_radius=rng.uniform(0.4, 0.7), flux=1.0)
    disc = disc.shear(e1=rng.normal(0, 0.2), e2=rng.normal(0, 0.2))
    knot = galsim.Gaussian(sigma=0.15, flux=0.3).shift(*rng.uniform(-0.4, 0.4, 2))
    return galsim.Add(disc, knot)


@pytest.fixture(scope="module")
def lopsided():
    """Six noise-free lopsided templates on 48-pixel stamps with a sheared Moffat PSF, and
    a target's moment covariance made parity-symmetric (no ``E2`` correlation with ``F, R,
    E1``, none between ``X`` and ``Y``), as a population without handedness has."""
    wcs = galsim.JacobianWCS(*JAC.ravel())
    psf = galsim.Moffat(beta=3.5, fwhm=0.95).shear(g1=0.01, g2=0.02)
    psf_img = psf.drawImage(nx=31, ny=31, wcs=wcs).array
    rng = np.random.default_rng(12)
    templates = []
    for _ in range(6):
        img = galsim.Convolve(_lopsided_galaxy(rng), psf).drawImage(
            nx=48, ny=48, wcs=wcs, offset=rng.uniform(-0.5, 0.5, 2), dtype=np.float64
        )
        templates.append(bfd.fourier_data(img.array, psf_img, JAC, noise_variance=1e-4))
    ref = bfd.measure_moments(templates[0])
    cov_even = ref.cov_even.copy()
    cov_even[3, :3] = cov_even[:3, 3] = 0.0
    cov_odd = np.diag(np.diag(ref.cov_odd))
    return templates, cov_even, cov_odd


def test_mirror_signs_are_those_of_the_mirrored_data(lopsided):
    """Every moment and shear derivative of the k-space mirror image (``k_u -> -k_u``)
    equals the original's times MIRROR_SIGNS (``E2``, ``X`` and odd powers of ``g2``
    flip), to rounding; and the mirror is re-centred at the mirrored centre."""
    data = lopsided[0][1]
    mirror = data.mirrored()
    assert np.array_equal(mirror.kx, -data.kx) and np.array_equal(mirror.values, data.values)

    def terms(d: bfd.KData) -> np.ndarray:
        coeff = bfd.moment_coefficients(d.kx, d.ky, d.weight, derivatives=True)
        return np.real(coeff @ d.values)  # (6 moments, 6 terms)

    original = terms(data)
    size = np.abs(original).max(axis=1, keepdims=True)
    np.testing.assert_allclose(terms(mirror) / size, bfd.MIRROR_SIGNS * original / size, atol=1e-12)
    # Not trivially true: the terms that flip are far from zero for this lopsided galaxy.
    flips = bfd.MIRROR_SIGNS < 0
    assert np.all(np.abs(original / size)[flips] > 1e-4)
    m, mm = bfd.measure_moments(data), bfd.measure_moments(mirror)
    assert m.converged and mm.converged
    np.testing.assert_allclose(mm.centre, m.centre * [-1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(mm.even, m.even * [1, 1, 1, -1], rtol=1e-12, atol=1e-12 * m.even[0])
    # The mirror of the galaxy sheared by (g1, g2) is the mirror image sheared by (g1, -g2).
    a_inv = np.array([[1.0 - 0.03, -0.05], [-0.05, 1.0 + 0.03]]) / np.sqrt(1 - 0.03**2 - 0.05**2)
    b_inv = np.array([[1.0 - 0.03, 0.05], [0.05, 1.0 + 0.03]]) / np.sqrt(1 - 0.03**2 - 0.05**2)

    def sheared(d: bfd.KData, a: np.ndarray) -> np.ndarray:
        sx, sy = a[0, 0] * d.kx + a[0, 1] * d.ky, a[1, 0] * d.kx + a[1, 1] * d.ky
        return np.real(bfd.moment_coefficients(sx, sy, d.weight) @ d.values)

    np.testing.assert_allclose(
        sheared(mirror, a_inv) / size[:, 0],
        bfd.MIRROR_SIGNS[:, 0] * sheared(data, b_inv) / size[:, 0],
        atol=1e-12,
    )


def _pqr(prior: bfd.TemplatePrior, targets: np.ndarray):
    res = prior.pqr(targets)
    scale = np.exp(res.log_scale)
    return res.P * scale, res.Q * scale[:, None], res.R * scale[:, None, None]


def _targets(templates: list[bfd.KData], cov_even: np.ndarray) -> np.ndarray:
    """Targets near the templates' moments (within a few sigma, where P is not tiny)."""
    rng = np.random.default_rng(3)
    even = np.array([bfd.measure_moments(t).even for t in templates])
    sigma = np.sqrt(np.diag(cov_even))
    return even + rng.normal(0.0, 1.5, even.shape) * sigma


@pytest.mark.parametrize("shear", [(0.0, 0.0), (0.01, -0.02)], ids=["unsheared", "sheared"])
def test_mirrored_prior_is_parity_symmetric(lopsided, shear):
    """With mirror=True, P, Q, R of a target and of its mirror image (``E2 -> -E2``)
    satisfy ``P(SM | g1, g2) = P(M | g1, -g2)``: P, Q1, R11, R22 equal, Q2, R12 opposite,
    to 1e-10 of their scale. Without it (the same lopsided templates) they differ."""
    templates, cov_even, cov_odd = lopsided
    targets = _targets(templates, cov_even)
    mirrored = targets * [1.0, 1.0, 1.0, -1.0]
    kw = dict(cov_even=cov_even, cov_odd=cov_odd, n_rotations=3, snr_range=None)
    flip_q = np.array([1.0, -1.0])
    flip_r = np.array([[1.0, -1.0], [-1.0, 1.0]])
    for mirror in (True, False):
        # the mirror image of a target sheared by g is seen by the prior sheared by (g1, -g2)
        a = bfd.TemplatePrior.from_templates(templates, shear=shear, mirror=mirror, **kw)
        b = bfd.TemplatePrior.from_templates(
            templates, shear=(shear[0], -shear[1]), mirror=mirror, **kw
        )
        p, q, r = _pqr(a, targets)
        pm, qm, rm = _pqr(b, mirrored)
        assert np.all(p > 0.0)
        q_size = np.abs(q).max(1)[:, None]
        r_size = np.abs(r).max((1, 2))[:, None, None]
        errors = (
            np.max(np.abs(pm / p - 1.0)),
            np.max(np.abs(qm - q * flip_q) / q_size),
            np.max(np.abs(rm - r * flip_r) / r_size),
        )
        if mirror:
            assert max(errors) < 1e-10, errors
        else:
            assert min(errors) > 1e-3, errors  # the test would see a broken mirror


def test_mirrored_prior_equals_the_prior_of_the_mirrored_templates(lopsided):
    """The mirrored copies (sign flips of the copies' moments) are the copies of the
    k-space mirror images of the templates: the prior of ``templates + mirrored templates``
    (half weight each) gives the same P, Q, R, for a diagonal odd covariance (then the
    mirrored templates' position grids are the mirrors of the originals')."""
    templates, cov_even, cov_odd = lopsided
    targets = _targets(templates, cov_even)
    for shear in ((0.0, 0.0), (0.02, 0.01)):
        kw = dict(cov_even=cov_even, cov_odd=cov_odd, n_rotations=4, snr_range=None, shear=shear)
        by_signs = bfd.TemplatePrior.from_templates(templates, mirror=True, **kw)
        in_k = bfd.TemplatePrior.from_templates(
            [*templates, *(t.mirrored() for t in templates)], **kw
        )
        assert len(by_signs.moments) == len(in_k.moments)
        np.testing.assert_allclose(by_signs.weights.sum(), in_k.weights.sum(), rtol=1e-12)
        for x, y in zip(_pqr(by_signs, targets), _pqr(in_k, targets), strict=True):
            size = np.abs(x).reshape(len(targets), -1).max(1)
            diff = np.abs(x - y).reshape(len(targets), -1).max(1)
            assert np.all(diff < 1e-9 * size)


def test_mirror_keeps_the_normalisation(lopsided):
    """Twice the copies at half the weight: the total weight (the prior's integral over the
    moments), the selection probability P_s and each template's original copies are as
    without mirror; the selection derivatives' parity-odd parts are exactly zero."""
    templates, cov_even, cov_odd = lopsided
    fluxes = np.array([bfd.measure_moments(t).even[0] for t in templates])
    sigma = np.sqrt(cov_even[0, 0])
    snr = (np.quantile(fluxes, 0.3) / sigma, np.quantile(fluxes, 0.7) / sigma)
    kw = dict(cov_even=cov_even, cov_odd=cov_odd, n_rotations=3, snr_range=snr)
    plain = bfd.TemplatePrior.from_templates(templates, **kw)
    both = bfd.TemplatePrior.from_templates(templates, mirror=True, **kw)
    assert len(both.moments) == 2 * len(plain.moments)
    assert len(both.centred) == 2 * len(plain.centred)
    np.testing.assert_allclose(both.weights.sum(), plain.weights.sum(), rtol=1e-13)
    np.testing.assert_allclose(both.centred_weights.sum(), 1.0, rtol=1e-13)
    per_template = len(plain.moments) // len(templates)
    first = both.moments.reshape(len(templates), 2, per_template, 6, 6)
    np.testing.assert_array_equal(first[:, 0], plain.moments.reshape(first[:, 0].shape))
    np.testing.assert_array_equal(first[:, 1], first[:, 0] * bfd.MIRROR_SIGNS)
    np.testing.assert_allclose(
        both.weights.reshape(len(templates), 2, -1),
        np.repeat(plain.weights.reshape(len(templates), 1, -1), 2, axis=1) / 2,
        rtol=1e-15,
    )
    ps, qs, rs = plain.selection_pqr()
    ps_m, qs_m, rs_m = both.selection_pqr()
    assert 0.05 < ps < 0.95
    assert ps_m == pytest.approx(ps, rel=1e-13)
    assert abs(qs_m[1]) < 1e-13 * abs(rs[0, 0]) and abs(rs_m[0, 1]) < 1e-13 * abs(rs[0, 0])
    assert rs_m[0, 0] == pytest.approx(rs[0, 0], rel=1e-10)


def test_validation_setting_reaches_the_prior():
    """``ValidationSettings.bfd_mirror`` builds the mirrored prior (twice the copies, the
    same total weight); at S/N 10^4 with the targets as templates each target sees only
    its own template, so Q/P is unchanged (docs/validation.md: 3e-9 in m1 over 200 pairs)."""
    from cellcoadd.pipelines.validation.bfd_validation import bfd_posterior
    from cellcoadd.pipelines.validation.shear_validation import run_pairs
    from cellcoadd.pipelines.validation.stamp_pairs import bfd_noise_sigma, bfd_templates
    from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
    from cellcoadd.sim import SimConfig

    settings = ValidationSettings(
        seed=3, snr=1e4, method="bfd", bfd_template_sample="targets", rotated_partners=False,
        sim=SimConfig(shear=(1e-3, 0.0)),
    )  # fmt: skip
    assert not settings.bfd_mirror
    catalogue = run_pairs(settings, 2, progress=False)
    templates = bfd_templates(settings, bfd_noise_sigma(settings), catalogue.index.tolist())
    off = bfd_posterior(settings, catalogue, templates)
    on = bfd_posterior(settings.model_copy(update={"bfd_mirror": True}), catalogue, templates)
    assert len(on.prior.moments) == 2 * len(off.prior.moments)
    np.testing.assert_allclose(on.prior.weights.sum(), off.prior.weights.sum(), rtol=1e-13)
    for a, b in ((on.plus, off.plus), (on.minus, off.minus)):
        assert np.array_equal(a.selected, b.selected) and a.selected.all()
        np.testing.assert_allclose(a.Q / a.P[:, None], b.Q / b.P[:, None], rtol=1e-6)


def test_command_line_flag_reaches_the_settings():
    """``cellcoadd validate-shear --bfd-mirror`` runs with the mirrored prior (recorded in
    the result's settings); without the flag it stays off."""
    import json

    from click.testing import CliRunner

    from cellcoadd.cli.main import cli

    args = ["validate-shear", "--method", "bfd", "--n-objects", "2", "--bfd-templates", "2"]
    args += ["--snr", "20"]  # independent templates: S/N up to 50
    for flag, expected in (([], False), (["--bfd-mirror"], True)):
        result = CliRunner().invoke(cli, [*args, *flag, "--json", "--quiet"])
        assert result.exit_code == 0, result.output
        assert json.loads(result.stdout)["settings"]["bfd_mirror"] is expected
