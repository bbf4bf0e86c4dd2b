"""Simulations: paper section 3 distributions, shear, determinism, WCS/image agreement,
and the field mode's focal plane."""

from __future__ import annotations

import json

import galsim
import numpy as np
import pytest
from click.testing import CliRunner
from pydantic import ValidationError
from scipy import integrate, stats

from cellcoadd.cli.simulate import simulate
from cellcoadd.geometry import SkyMap
from cellcoadd.geometry.wcs_utils import local_jacobian
from cellcoadd.io.exposures.exposure_io import read_exposure
from cellcoadd.model.psf_profiles import VaryingPsf
from cellcoadd.pipelines.simulation_files import write_field_simulation
from cellcoadd.sim import (
    DEMO_PATCH,
    FieldConfig,
    GalaxyConfig,
    PsfConfig,
    SimConfig,
    WcsVariationConfig,
    demo_skymap,
    draw_ellipticities,
    draw_psf_parameters,
    simulate_field,
    simulate_object,
    simulate_sheared,
    simulate_stamp_pair,
    simulate_stamps,
)
from cellcoadd.sim.psf import lognormal_parameters

QUIET_FIELD = FieldConfig(
    galaxy_density=0.0, star_density=6.0, bad_columns=0.0, cosmic_rays=0.0, star_mag_max=21.0
)


def centroid(image: np.ndarray) -> tuple[float, float]:
    y, x = np.indices(image.shape)
    total = image.sum()
    return float((image * x).sum() / total), float((image * y).sum() / total)


def hsm_shape(image: np.ndarray, scale: float) -> galsim.hsm.ShapeData:
    return galsim.hsm.FindAdaptiveMom(galsim.Image(image, scale=scale))


# -- distributions ---------------------------------------------------------------------
def test_psf_fwhm_distribution_matches_truncated_lognormal():
    config = PsfConfig()
    params = draw_psf_parameters(config, np.random.default_rng(1), 20_000)
    assert params.fwhm.min() >= 0.8 and params.fwhm.max() <= 1.15
    mu, s = lognormal_parameters(0.95, 0.1)
    parent = stats.lognorm(s=s, scale=np.exp(mu))
    lo, hi = parent.cdf(0.8), parent.cdf(1.15)

    def truncated_cdf(x):
        return (parent.cdf(x) - lo) / (hi - lo)

    assert stats.kstest(params.fwhm, truncated_cdf).pvalue > 1e-3
    expected_mean = integrate.quad(lambda x: x * parent.pdf(x), 0.8, 1.15)[0] / (hi - lo)
    assert abs(params.fwhm.mean() - expected_mean) < 4 * params.fwhm.std() / np.sqrt(20_000)
    assert abs(expected_mean - 0.95) < 0.01  # the truncation barely moves the mean
    # the untruncated log-normal has the configured mean and standard deviation
    assert parent.mean() == pytest.approx(0.95) and parent.std() == pytest.approx(0.1)


def test_psf_shape_distribution():
    n = 20_000
    params = draw_psf_parameters(PsfConfig(), np.random.default_rng(2), n)
    tolerance = 4 * 0.01 / np.sqrt(n)
    assert abs(params.g1.mean() - 0.0) < tolerance
    assert abs(params.g2.mean() - 0.01) < tolerance
    assert params.g1.std() == pytest.approx(0.01, rel=0.03)
    assert params.g2.std() == pytest.approx(0.01, rel=0.03)


def test_exposure_psfs_have_the_drawn_size_and_shape():
    obj = simulate_stamps(SimConfig(n_epochs=4), 1, seed=3, add_noise=False)[0]
    for exposure, epoch in zip(obj.exposures, obj.epochs, strict=True):
        scale = 0.02
        measured = hsm_shape(exposure.psf.drawImage(nx=301, ny=301, scale=scale).array, scale)
        round_psf = galsim.Moffat(beta=3.5, fwhm=epoch.psf_fwhm).drawImage(
            nx=301, ny=301, scale=scale
        )
        reference = hsm_shape(round_psf.array, scale)
        assert measured.observed_shape.g1 == pytest.approx(epoch.psf_g1, abs=2e-4)
        assert measured.observed_shape.g2 == pytest.approx(epoch.psf_g2, abs=2e-4)
        # shearing keeps the area, so the determinant size is that of the round Moffat
        assert measured.moments_sigma == pytest.approx(reference.moments_sigma, rel=1e-3)
        assert galsim.Moffat(beta=3.5, fwhm=epoch.psf_fwhm).calculateFWHM() == pytest.approx(
            epoch.psf_fwhm, rel=1e-3
        )


def test_intrinsic_ellipticity_distribution():
    sigma = 0.3  # wide enough for the (1 - e^2)^2 factor to matter
    e1, e2 = draw_ellipticities(np.random.default_rng(4), 20_000, sigma)
    e = np.hypot(e1, e2)
    assert e.max() < 1.0

    def radial_pdf(x):
        return x * (1 - x**2) ** 2 * np.exp(-(x**2) / (2 * sigma**2))

    norm = integrate.quad(radial_pdf, 0, 1)[0]
    grid = np.linspace(0, 1, 2001)
    cdf = np.concatenate([[0], np.cumsum(0.5 * (radial_pdf(grid[1:]) + radial_pdf(grid[:-1])))])
    cdf *= (grid[1] - grid[0]) / norm
    assert stats.kstest(e, lambda x: np.interp(x, grid, cdf)).pvalue > 1e-3
    # isotropic
    assert abs(np.mean(np.cos(2 * np.arctan2(e2, e1)))) < 0.03
    small1, _ = draw_ellipticities(np.random.default_rng(4), 20_000, 0.02)
    assert small1.std() == pytest.approx(0.02, rel=0.03)
    assert np.all(draw_ellipticities(np.random.default_rng(4), 10, 0.0)[0] == 0)


# -- shear ------------------------------------------------------------------------------
def round_config(**changes) -> SimConfig:
    """Round galaxies, round PSFs, no WCS variation, no shift: only the shear is left."""
    settings = dict(
        galaxy=GalaxyConfig(sigma_e=0.0, mag_sigma=0.0, mag_mean=20.0, hlr_ln_sigma=0.0),
        psf=PsfConfig(g2_mean=0.0, g_sigma=0.0, fwhm_sigma=0.0, fwhm_mean=0.9),
        wcs=WcsVariationConfig(scale_sigma=0.0, shear_sigma=0.0),
        max_shift=0.0,
        n_epochs=2,
    )
    settings.update(changes)
    return SimConfig(**settings)


def test_galaxy_carries_the_configured_shear():
    config = round_config()
    sheared = simulate_stamps(config, 1, seed=5, add_noise=False)[0]
    unsheared = simulate_stamps(config, 1, seed=5, shear=(0.0, 0.0), add_noise=False)[0]
    scale = 0.02
    shape_sheared = hsm_shape(sheared.galaxy.drawImage(nx=401, ny=401, scale=scale).array, scale)
    shape_round = hsm_shape(unsheared.galaxy.drawImage(nx=401, ny=401, scale=scale).array, scale)
    assert shape_round.observed_shape.g1 == pytest.approx(0.0, abs=1e-5)
    assert shape_sheared.observed_shape.g1 == pytest.approx(0.02, abs=1e-4)
    assert shape_sheared.observed_shape.g2 == pytest.approx(0.0, abs=1e-5)


def test_shear_reaches_the_pixels_with_the_right_sign():
    config = round_config()
    plus, minus = simulate_stamp_pair(config, 1, seed=6, add_noise=False)
    for exp_p, exp_m in zip(plus[0].exposures, minus[0].exposures, strict=True):
        shape_p = hsm_shape(exp_p.image, 0.27).observed_shape
        shape_m = hsm_shape(exp_m.image, 0.27).observed_shape
        # PSF dilution shrinks the observed shear, but its sign and axis survive
        assert 0.005 < shape_p.g1 < 0.02 and -0.02 < shape_m.g1 < -0.005
        assert shape_p.g1 == pytest.approx(-shape_m.g1, rel=1e-3)
        assert abs(shape_p.g2) < 1e-4


def test_matched_pair_shares_everything_but_the_shear():
    config = SimConfig(n_epochs=3)
    plus, minus = simulate_stamp_pair(config, 2, seed=7)
    plus_clean, minus_clean = simulate_stamp_pair(config, 2, seed=7, add_noise=False)
    for p, m, pc, mc in zip(plus, minus, plus_clean, minus_clean, strict=True):
        assert (p.truth.g1, m.truth.g1) == (0.02, -0.02)
        assert (p.truth.flux, p.truth.hlr, p.truth.e1) == (m.truth.flux, m.truth.hlr, m.truth.e1)
        for ep, em, ecp, ecm in zip(
            p.exposures, m.exposures, pc.exposures, mc.exposures, strict=True
        ):
            assert ep.psf == em.psf
            assert ep.wcs.to_header_string() == em.wcs.to_header_string()
            # identical noise: the noisy difference is the noise-free difference
            np.testing.assert_allclose(
                ep.image - em.image, ecp.image - ecm.image, rtol=0, atol=1e-9
            )


def test_sheared_members_equal_separate_simulations_and_share_one_wcs():
    """simulate_sheared makes each epoch's WCS once for all members, and each member is
    bit for bit the object simulate_object makes alone (WCS header, image, truth)."""
    config = SimConfig(n_epochs=3)
    shears = [(0.02, 0.0), (-0.02, 0.0), (0.0, 0.01)]
    together = simulate_sheared(config, 5, 4, shears, add_noise=True, rotate_shape=True)
    for obj, shear in zip(together, shears, strict=True):
        alone = simulate_object(config, 5, 4, shear, rotate_shape=True)
        assert (obj.truth.g1, obj.truth.g2) == shear
        assert obj.truth == alone.truth
        for a, b in zip(obj.exposures, alone.exposures, strict=True):
            np.testing.assert_array_equal(a.image, b.image)
            assert a.wcs.to_header_string() == b.wcs.to_header_string()
            np.testing.assert_array_equal(a.wcs.wcs.pc, b.wcs.wcs.pc)
            np.testing.assert_array_equal(a.wcs.wcs.cdelt, b.wcs.wcs.cdelt)
            np.testing.assert_array_equal(a.wcs.wcs.crpix, b.wcs.wcs.crpix)
    for epoch in range(config.n_epochs):
        assert len({id(obj.exposures[epoch].wcs) for obj in together}) == 1


# -- determinism ----------------------------------------------------------------------
def test_stamps_are_deterministic():
    config = SimConfig(n_epochs=3)
    first = simulate_stamps(config, 3, seed=11)
    second = simulate_stamps(config, 3, seed=11)
    other = simulate_stamps(config, 3, seed=12)
    chunk = simulate_stamps(config, 2, seed=11, first_index=1)
    for a, b in zip(first, second, strict=True):
        for ea, eb in zip(a.exposures, b.exposures, strict=True):
            np.testing.assert_array_equal(ea.image, eb.image)
    for a, c in zip(first[1:], chunk, strict=True):
        np.testing.assert_array_equal(a.exposures[0].image, c.exposures[0].image)
    for a, o in zip(first, other, strict=True):
        assert not np.array_equal(a.exposures[0].image, o.exposures[0].image)
        assert a.truth.flux != o.truth.flux
    assert len({o.truth.flux for o in first}) == 3  # objects differ from one another


# -- WCS and image agree ----------------------------------------------------------------
@pytest.mark.parametrize("rotate", [False, True])
def test_stamp_star_lands_where_the_wcs_says(rotate):
    config = SimConfig(
        n_epochs=10,
        psf=PsfConfig(g_sigma=0.03),
        wcs=WcsVariationConfig(scale_sigma=0.03, shear_sigma=0.03, rotate=rotate),
    )

    def point_like(rng, n):
        return np.full(n, 18.0), np.full(n, 1e-4)

    obj = simulate_stamps(config, 1, seed=13, add_noise=False, sampler=point_like)[0]
    for exposure, epoch in zip(obj.exposures, obj.epochs, strict=True):
        x_wcs, y_wcs = exposure.wcs.all_world2pix(obj.ra, obj.dec, 0)
        x_c, y_c = centroid(exposure.image)
        assert abs(x_c - x_wcs) < 0.01 and abs(y_c - y_wcs) < 0.01
        assert (float(x_wcs), float(y_wcs)) == pytest.approx(epoch.position, abs=1e-8)
        jacobian = local_jacobian(exposure.wcs, *epoch.position)
        np.testing.assert_allclose(jacobian, epoch.jacobian, rtol=0, atol=1e-9)
        assert exposure.image.sum() == pytest.approx(obj.truth.flux, rel=2e-3)


def test_field_stars_land_where_the_wcs_says():
    config = SimConfig(
        noise_sigma=0.0,
        field=QUIET_FIELD.model_copy(
            update=dict(rotate=True, sip_k=2e-9, psf_fwhm_edge=0.1, psf_g_edge=0.03)
        ),
    )
    result = simulate_field(config, demo_skymap(), 0, DEMO_PATCH, 2, seed=17)
    truth = result.truth
    checked = 0
    for exposure in result.exposures:
        assert isinstance(exposure.psf, VaryingPsf)
        x, y = exposure.wcs.all_world2pix(truth["ra"], truth["dec"], 0, tolerance=1e-10)
        for k in np.flatnonzero(
            (x > 20) & (x < exposure.shape[1] - 21) & (y > 20) & (y < exposure.shape[0] - 21)
        ):
            if np.sum(np.hypot(x - x[k], y - y[k]) < 30) > 1:
                continue  # a neighbour would bias the centroid
            ix, iy = int(round(x[k])), int(round(y[k]))
            cut = exposure.image[iy - 20 : iy + 21, ix - 20 : ix + 21].astype(float)
            # adaptive moments: the weight follows the star, so window edges do not bias it
            found = galsim.hsm.FindAdaptiveMom(galsim.Image(cut, xmin=ix - 20, ymin=iy - 20))
            assert abs(found.moments_centroid.x - x[k]) < 0.01
            assert abs(found.moments_centroid.y - y[k]) < 0.01
            checked += 1
    assert checked >= 10


# -- field mode -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def field_run():
    return simulate_field(SimConfig(), demo_skymap(), 0, DEMO_PATCH, 6, seed=21)


def cell_coverage(result, cell) -> dict[int, str]:
    """Per visit: 'inside' one CCD's valid box, 'crossed' by an edge, or 'off'."""
    tract = result.skymap[result.tract_id]
    box = cell.outer_bbox
    xs = np.linspace(box.x_start - 0.5, box.x_stop - 0.5, 21)
    ys = np.linspace(box.y_start - 0.5, box.y_stop - 0.5, 21)
    bx = np.concatenate([xs, xs, np.full(21, xs[0]), np.full(21, xs[-1])])
    by = np.concatenate([np.full(21, ys[0]), np.full(21, ys[-1]), ys, ys])
    ra, dec = tract.pixel_to_sky(bx, by)
    status: dict[int, str] = {}
    for exposure in result.exposures:
        x, y = exposure.wcs.all_world2pix(ra, dec, 0)
        inside = exposure.valid_box.contains(x, y)
        if inside.all():
            status[exposure.visit] = "inside"
        elif inside.any() and status.get(exposure.visit) != "inside":
            status[exposure.visit] = "crossed"
        else:
            status.setdefault(exposure.visit, "off")
    return status


def test_field_covers_the_patch_and_ccd_edges_cross_cells(field_run):
    assert len(field_run.exposures) == 6 * 9
    patch = field_run.skymap[0].patch(*DEMO_PATCH)
    statuses = {cell.index: cell_coverage(field_run, cell) for cell in patch.cells}
    # every cell is observed in every visit (fully or partly): the focal plane covers the patch
    assert all(s == "inside" or s == "crossed" for st in statuses.values() for s in st.values())
    # some cell is crossed by a CCD edge in one visit and fully inside a CCD in another
    assert any({"inside", "crossed"} <= set(st.values()) for st in statuses.values())
    n_crossed = sum(s == "crossed" for st in statuses.values() for s in st.values())
    assert 0 < n_crossed < 6 * len(statuses)


def test_field_exposures_are_well_formed(field_run):
    bits = field_run.exposures[0].mask_bits
    for exposure in field_run.exposures:
        assert exposure.image.dtype == np.float32 and exposure.shape == (
            FieldConfig().ccd_ny,
            FieldConfig().ccd_nx,
        )
        assert (
            exposure.valid_box.x_start == 2
            and exposure.valid_box.x_stop == FieldConfig().ccd_nx - 2
        )
        assert np.all(exposure.mask[0, :] & bits.value("EDGE"))
        assert np.isfinite(exposure.image).all()
    masked = sum(
        int(np.count_nonzero(e.mask & bits.mask_of(["BAD", "CR"]))) for e in field_run.exposures
    )
    assert masked > 0
    assert set(field_run.truth.colnames) >= {
        "id",
        "ra",
        "dec",
        "flux",
        "hlr",
        "g1",
        "g2",
        "is_star",
        "mag",
    }
    galaxies = field_run.truth[~field_run.truth["is_star"]]
    assert np.all(galaxies["g1"] == 0.02) and np.all(galaxies["hlr"] > 0)
    assert field_run.truth["is_star"].any()
    assert len(set(field_run.visits["ra"])) == 6  # dithered


def test_field_is_deterministic_and_dither_patterns(field_run):
    again = simulate_field(SimConfig(), demo_skymap(), 0, DEMO_PATCH, 2, seed=21)
    for a, b in zip(field_run.exposures[:18], again.exposures, strict=True):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.mask, b.mask)
    other = simulate_field(SimConfig(), demo_skymap(), 0, DEMO_PATCH, 1, seed=22)
    assert not np.array_equal(other.exposures[4].image, field_run.exposures[4].image)
    spiral = simulate_field(
        SimConfig(field=QUIET_FIELD.model_copy(update=dict(dither="spiral"))),
        demo_skymap(),
        0,
        DEMO_PATCH,
        8,
        seed=1,
    )
    tract = spiral.skymap[0]
    x, y = tract.sky_to_pixel(np.array(spiral.visits["ra"]), np.array(spiral.visits["dec"]))
    radius = np.hypot(x - x.mean(), y - y.mean()) * 0.2
    assert radius.max() < 41.0 and np.all(np.diff(np.sort(radius)) > 0)


def test_field_write(field_run, tmp_path):
    small = simulate_field(SimConfig(), demo_skymap(), 0, DEMO_PATCH, 1, seed=21)
    paths = write_field_simulation(small, tmp_path)
    assert (tmp_path / "visit0000-det04.fits").exists() and len(paths) == 9 + 4
    back = read_exposure(tmp_path / "visit0000-det04.fits")
    np.testing.assert_array_equal(back.image, small.exposures[4].image)
    skymap = SkyMap.from_json((tmp_path / "skymap.json").read_text())
    assert skymap[0].center == small.skymap[0].center
    description = json.loads((tmp_path / "simulation.json").read_text())
    assert description["patch"] == list(DEMO_PATCH) and description["seed"] == 21
    with pytest.raises(FileExistsError):
        write_field_simulation(small, tmp_path)


def test_config_validation():
    with pytest.raises(ValidationError):
        PsfConfig(fwhm_min=1.2, fwhm_max=1.0)
    with pytest.raises(ValidationError):
        SimConfig(shear=(0.8, 0.8))
    with pytest.raises(ValidationError):
        FieldConfig(edge_pixels=200, ccd_nx=400)
    with pytest.raises(ValidationError):
        SimConfig(pixel_scale=-1)
    with pytest.raises(ValidationError):
        SimConfig().model_copy(update={}).__class__(unknown=1)
    config = SimConfig()
    assert (config.pixel_scale, config.stamp_size, config.n_epochs) == (0.27, 48, 10)
    assert (config.psf.beta, config.psf.fwhm_mean, config.psf.fwhm_sigma) == (3.5, 0.95, 0.1)
    assert (config.galaxy.sigma_e, config.shear) == (0.02, (0.02, 0.0))


def test_cli_simulate(tmp_path):
    runner = CliRunner()
    result = runner.invoke(
        simulate, ["--mode", "stamps", "--out", str(tmp_path / "s"), "--objects", "2", "-q"]
    )
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "s").glob("object*/epoch*.fits"))) == 20
    result = runner.invoke(
        simulate, ["--mode", "stamps", "--out", str(tmp_path / "s"), "--objects", "2", "-q"]
    )
    assert result.exit_code != 0 and "--overwrite" in result.output
    result = runner.invoke(
        simulate, ["--mode", "field", "--out", str(tmp_path / "f"), "--visits", "1", "--sip"]
    )
    assert result.exit_code == 0, result.output
    assert read_exposure(tmp_path / "f" / "visit0000-det00.fits").wcs.sip is not None
    assert "Examples" in runner.invoke(simulate, ["--help"]).output
