"""Multi-epoch shear: metacal on every epoch with one joint shape, BFD summing the epochs'
moments (the paper's Table 1 "multi-epoch" rows), and validate-shear --mode multi-epoch."""

from __future__ import annotations

import json

import galsim
import numpy as np
import pytest
from click.testing import CliRunner

from cellcoadd.cli.shear import validate_shear as validate_shear_command
from cellcoadd.errors import ConfigError, MetacalError
from cellcoadd.pipelines import (
    EpochGeometry,
    ValidationSettings,
    format_bias_table,
    validate_shear,
)
from cellcoadd.pipelines.validation.epoch_measurements import bfd_epoch_sum
from cellcoadd.pipelines.validation.shear_validation import measure_pairs
from cellcoadd.shear import (
    MetacalEpoch,
    bfd,
    common_reconvolution_psf,
    measure_metacal,
    measure_metacal_multi_epoch,
    reconvolution_psf,
)
from cellcoadd.shear.joint_shapes import EpochPixels, joint_admom, joint_wmom
from cellcoadd.shear.shapes import measure_wmom
from cellcoadd.sim import SimConfig, simulate_object

HIGH_SNR = 1.0e4
SETTINGS = ValidationSettings(mode="multi-epoch", snr=HIGH_SNR, seed=3)


def _epochs(n: int = 3, sigma: float = 1.0) -> list[MetacalEpoch]:
    """The first ``n`` epochs of a simulated object, with noise and noise realizations."""
    obj = simulate_object(SimConfig(), 3, 0, add_noise=False)
    geometry = EpochGeometry.of(obj, 35)
    rng = np.random.default_rng(11)
    return [
        MetacalEpoch(
            e.image + sigma * rng.standard_normal(e.shape),
            psf,
            sigma * rng.standard_normal(e.shape),
            jac,
            sigma,
            centre,
        )  # fmt: skip
        for e, psf, jac, centre in zip(
            obj.exposures[:n], geometry.psfs, geometry.jacobians, geometry.centres, strict=False
        )
    ]


@pytest.mark.parametrize("shape", ["wmom", "admom"])
def test_joint_measurement_of_one_epoch_is_the_single_epoch_measurement(shape):
    epoch = _epochs(1)[0]
    single = measure_metacal(
        epoch.image, epoch.psf_image, epoch.noise_image, epoch.jacobian, epoch.noise_sigma,
        guess_centroid=epoch.centre, shape=shape,
    )  # fmt: skip
    joint = measure_metacal_multi_epoch([epoch], shape=shape)
    for name, record in single.items():
        assert joint[name]["flags"][0] == record["flags"][0] == 0
        if shape == "wmom":  # the same sums: equal to rounding
            for field in ("g1", "g2", "T", "T_psf", "flux", "s2n", "x", "y"):
                assert joint[name][field][0] == pytest.approx(record[field][0], rel=1e-12)
        else:  # our joint iteration against GalSim's HSM: both converge to ~1e-6
            for field in ("g1", "g2"):
                assert joint[name][field][0] == pytest.approx(record[field][0], abs=1e-5)
            for field in ("T", "T_psf", "flux", "s2n"):
                assert joint[name][field][0] == pytest.approx(record[field][0], rel=1e-5)


def test_every_type_uses_each_epochs_noshear_noise_covariance():
    # the fixed joint wmom weight and one covariance per epoch for every type: each
    # type's S/N moves with its flux alone (see test_metacal's single-image test)
    joint = measure_metacal_multi_epoch(_epochs(3), shape="wmom")
    flux_errors = [record["flux"][0] / record["s2n"][0] for record in joint.values()]
    assert all(record["flags"][0] == 0 for record in joint.values())
    np.testing.assert_allclose(flux_errors, flux_errors[0], rtol=1e-12)


def test_common_reconvolution_psf_is_the_largest_of_the_epochs():
    epochs = _epochs(3)
    psfs, jacs = [e.psf_image for e in epochs], [e.jacobian for e in epochs]
    common = common_reconvolution_psf(psfs, jacs)
    own = [reconvolution_psf(p, j).sigma for p, j in zip(psfs, jacs, strict=True)]
    assert common.sigma == max(own) and len(set(own)) == 3  # epochs differ
    with pytest.raises(MetacalError, match="round"):
        common_reconvolution_psf(psfs, jacs, kind="dilate")
    with pytest.raises(MetacalError, match="round"):
        measure_metacal_multi_epoch(epochs, psf="dilate")


def _gaussian(jacobian: np.ndarray, centre: tuple[float, float], cov: np.ndarray) -> np.ndarray:
    """An elliptical Gaussian of sky covariance ``cov`` centred on pixel ``centre``."""
    wcs = galsim.JacobianWCS(*jacobian.ravel())
    sigma = np.linalg.det(cov) ** 0.25
    e1 = (cov[0, 0] - cov[1, 1]) / (cov[0, 0] + cov[1, 1])
    profile = galsim.Gaussian(sigma=sigma, flux=100.0).shear(
        galsim.Shear(e1=e1, e2=2 * cov[0, 1] / (cov[0, 0] + cov[1, 1]))
    )
    image = galsim.Image(48, 48, xmin=0, ymin=0, wcs=wcs)
    offset = galsim.PositionD(*centre) - image.true_center
    return profile.drawImage(image=image, offset=offset, method="no_pixel").array


def test_joint_shapes_combine_epochs_in_sky_coordinates():
    cov = np.array([[0.30, 0.05], [0.05, 0.22]])  # arcsec^2
    jacobians = [
        np.array([[-0.2, 0.0], [0.0, 0.2]]),
        0.27 * np.array([[-np.cos(0.6), np.sin(0.6)], [np.sin(0.6), np.cos(0.6)]]),
    ]
    centres = [(23.3, 24.1), (22.6, 23.8)]
    epochs = [
        EpochPixels.from_image(_gaussian(jac, centre, cov), jac, centre, variance=1.0)
        for jac, centre in zip(jacobians, centres, strict=True)
    ]
    # adaptive moments of a Gaussian are its covariance, whatever the pixel grids
    record = joint_admom(epochs, guess_sigma=0.4)
    assert record["flags"][0] == 0
    trace = np.trace(cov)
    shape = galsim.Shear(e1=(cov[0, 0] - cov[1, 1]) / trace, e2=2 * cov[0, 1] / trace)
    assert record["T"][0] == pytest.approx(np.trace(cov), rel=1e-6)
    assert (record["g1"][0], record["g2"][0]) == pytest.approx((shape.g1, shape.g2), abs=1e-6)
    assert (record["x"][0], record["y"][0]) == pytest.approx(centres[0], abs=1e-6)
    # fixed weight: each epoch alone measures the same; jointly, the same again with the
    # flux S/N of both (equal inverse-variance weights per unit area)
    alone = [joint_wmom([e], 1.2) for e in epochs]
    both = joint_wmom(epochs, 1.2)
    for field in ("g1", "g2", "T"):
        assert both[field][0] == pytest.approx(alone[0][field][0], rel=1e-6)
        assert alone[1][field][0] == pytest.approx(alone[0][field][0], rel=1e-6)
    single = measure_wmom(epochs[0].image, galsim.JacobianWCS(*jacobians[0].ravel()), 1.0,
                          centres[0], 1.2)  # fmt: skip
    assert alone[0]["s2n"][0] == pytest.approx(single["s2n"][0], rel=1e-12)
    snr = np.hypot(alone[0]["s2n"][0], alone[1]["s2n"][0])  # independent noise
    assert both["s2n"][0] == pytest.approx(snr, rel=1e-4)


def test_bfd_epoch_sum_is_the_sum_of_the_epochs():
    obj = simulate_object(SimConfig(), 3, 2, add_noise=False)
    geometry = EpochGeometry.of(obj, 35)
    total = bfd.measure_moments(bfd_epoch_sum(SETTINGS, obj.exposures, geometry, 1.0))
    weight = bfd.KSigmaWeight(sigma=SETTINGS.bfd_sigma)
    kw = {"noise_variance": 1.0, "weight": weight, "oversample": SETTINGS.bfd_oversample}
    each = [
        bfd.measure_moments(bfd.fourier_data(e.image, psf, jac, centre=c, **kw))
        for e, psf, jac, c in zip(
            obj.exposures, geometry.psfs, geometry.jacobians, geometry.centres, strict=True
        )
    ]
    assert total.converged and len(each) == obj.exposures.__len__() == 10
    # every epoch sees the same deconvolved galaxy (own PSF, own WCS, same sky origin)
    fluxes = np.array([m.even[0] for m in each])
    assert np.ptp(fluxes) < 2e-3 * fluxes.mean()
    np.testing.assert_allclose(total.even, np.sum([m.even for m in each], axis=0), rtol=2e-4)
    np.testing.assert_allclose(
        total.cov_even, np.sum([m.cov_even for m in each], axis=0), rtol=1e-10
    )
    assert np.hypot(*total.centre) < 0.01  # arcsec: the sky position is the galaxy's


#: 6 pairs in the default suite, 16 with the slow tests; in 2 processes, which
#: test_multi_epoch_results_do_not_depend_on_workers compares with a serial run
@pytest.fixture(
    scope="module",
    params=[pytest.param(6, id="6-pairs"), pytest.param(16, id="16-pairs", marks=pytest.mark.slow)],
)
def metacal_run(request):
    return validate_shear(
        "multi-epoch", n_objects=request.param, snr=HIGH_SNR, seed=21, workers=2,
        progress=False, return_measurements=True,
    )  # fmt: skip


def test_multi_epoch_metacal_bias_is_small_at_high_snr(metacal_run):
    # measured: m1 = -2e-5 +- 3.9e-4 (seed 21, 16 pairs), +6e-5 +- 3.7e-4 (6 pairs)
    result = metacal_run
    assert result["mode"] == "multi-epoch" and result["method"] == "metacal"
    assert abs(result["m1"]) < 2e-3
    assert abs(result["m1"]) < 3.0 * result["m1_err"] + 1e-4
    assert result["m1_err"] < 2e-3
    for name in ("c1", "c2"):
        assert abs(result[name]) < 1e-3
    assert result["incomplete_coadds"] == 0 and result["n_used"] == result["n_objects"]
    assert 0.2 < result["R11"] < 0.6 and result["R11"] == pytest.approx(result["R22"], rel=0.05)
    assert result["s2n_median"] > 1000
    assert (result["paper_m1"], result["paper_m1_err"]) == (0.0004, 0.0004)
    assert "paper, metacal multi-epoch" in format_bias_table([result])


def test_multi_epoch_results_do_not_depend_on_workers(metacal_run):
    pairs = metacal_run["measurements"]
    settings = ValidationSettings(**metacal_run["settings"])
    again = measure_pairs(settings, [5, 2])  # serially, in another order
    for name in pairs.plus:
        assert again.plus[name].tobytes() == pairs.plus[name][[5, 2]].tobytes()
        assert again.minus[name].tobytes() == pairs.minus[name][[5, 2]].tobytes()
    assert np.all(pairs.n_inputs == 10)


def test_modes_and_methods_that_cannot_run_together_are_refused():
    with pytest.raises(ConfigError, match="multi-epoch"):
        validate_shear("multi-epoch", n_objects=2, method="anacal")
    with pytest.raises(ConfigError, match="dilate"):
        validate_shear("multi-epoch", n_objects=2, reconvolution_psf="dilate")
    with pytest.raises(ValueError, match="rotated_partners"):
        ValidationSettings(method="bfd", bfd_template_sample="targets")
    result = CliRunner().invoke(
        validate_shear_command, ["--method", "anacal", "--mode", "multi-epoch"]
    )
    assert result.exit_code == 2 and "joint multi-epoch" in result.output


def test_cli_runs_multi_epoch():
    args = ["--mode", "multi-epoch", "--n-objects", "2", "--snr", "1000", "--json", "--quiet"]
    result = CliRunner().invoke(validate_shear_command, args)
    assert result.exit_code == 0, result.output
    output = json.loads(result.output)
    assert output["mode"] == "multi-epoch" and output["n_used"] == 2
    assert output["paper_m1"] == 0.0004 and output["incomplete_coadds"] == 0


@pytest.mark.slow
def test_multi_epoch_bfd_at_high_snr():
    # the check of tests/test_validation.py::test_bfd_coadd_bias_is_small_at_high_snr on
    # the summed epochs' moments (~25 s: the prior sums 10 epochs of 16 templates);
    # measured: m1 = +3e-5 +- 3.9e-4 (seed 5)
    result = validate_shear(
        "multi-epoch", n_objects=16, snr=HIGH_SNR, seed=5, workers=2, progress=False,
        method="bfd", bfd_template_sample="targets", rotated_partners=False, shear=1.0e-3,
    )  # fmt: skip
    assert result["n_used"] == 16 and result["incomplete_coadds"] == 0
    assert abs(result["m1"]) < 2e-3 and abs(result["m1"]) < 3.0 * result["m1_err"]
