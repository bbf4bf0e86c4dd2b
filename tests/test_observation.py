"""Cells handed to shear codes: to_observation fields, jacobian, weight; to_ngmix."""

from __future__ import annotations

import sys

import galsim
import numpy as np
import pytest
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, SkyMap, SkyMapConfig, build_cell
from cellcoadd.geometry.wcs_utils import gnomonic_uv
from cellcoadd.shear import (
    EmptyCellError,
    measure_metacal,
    observation_jacobian,
    to_ngmix,
    to_observation,
)

CONFIG = SkyMapConfig(cell_inner=40, cell_border=15, cells_per_patch=2, patches_per_tract=1)
BUILD = BuildConfig(n_noise=3, psf_size=25)
NOISE_SIGMA = 2.0


@pytest.fixture(scope="module")
def cell():
    # cell (1, 0) is off the tract's tangent point, so the jacobian is not trivially exact
    return SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0].cell(1, 0)


@pytest.fixture(scope="module")
def coadd(cell):
    galaxy = galsim.Exponential(half_light_radius=0.5, flux=5000.0).shear(g1=0.2, g2=-0.1)
    ra, dec = cell.center_sky
    exposures = [
        make_exposure(
            cell.center_sky,
            pixel_scale=0.26,
            rotation_deg=rotation,
            offset=offset,
            psf=galsim.Moffat(beta=3.5, fwhm=fwhm),
            sources=[(ra, dec, galaxy)],
            noise_sigma=NOISE_SIGMA,
            visit=visit,
            seed=visit,
        )
        for visit, (rotation, offset, fwhm) in enumerate(
            [(0.0, (0.3, -0.2), 0.9), (30.0, (-0.1, 0.4), 1.0), (-65.0, (0.2, 0.1), 0.85)]
        )
    ]
    return build_cell(cell, exposures, BUILD, seed=4)


def test_fields_are_float64_copies_of_the_cell(coadd):
    obs = to_observation(coadd, noise_index=1)
    shape = coadd.shape
    for key in ("image", "weight", "noise", "bmask", "ormask", "mfrac"):
        assert obs[key].shape == shape, key
    assert obs["image"].dtype == obs["noise"].dtype == obs["mfrac"].dtype == np.float64
    np.testing.assert_array_equal(obs["image"], coadd.image)
    np.testing.assert_array_equal(obs["noise"], coadd.noise[1])
    np.testing.assert_array_equal(obs["bmask"], coadd.mask)
    np.testing.assert_array_equal(obs["ormask"], coadd.mask)
    np.testing.assert_array_equal(obs["mfrac"], coadd.mfrac)
    np.testing.assert_array_equal(obs["psf"]["image"], coadd.psf)
    assert np.all(obs["psf"]["weight"] == 1.0) and obs["psf"]["weight"].shape == coadd.psf.shape
    # copies: changing the observation leaves the cell alone
    before = coadd.image.copy()
    obs["image"][:] = 0.0
    obs["bmask"][:] = 7
    np.testing.assert_array_equal(coadd.image, before)
    assert not np.any(coadd.mask == 7)


def test_noise_index_selects_the_realization(coadd):
    planes = [to_observation(coadd, noise_index=k)["noise"] for k in range(coadd.n_noise)]
    assert not np.array_equal(planes[0], planes[1])
    with pytest.raises(ValueError, match="noise_index"):
        to_observation(coadd, noise_index=coadd.n_noise)


def test_weight_is_inverse_variance_of_the_noise_realizations(coadd):
    obs = to_observation(coadd)
    weight = obs["weight"]
    assert np.all(weight == weight[0, 0]), "the weight must be constant"
    inner = np.asarray(coadd.inner.noise, dtype=np.float64)
    expected = np.mean([np.var(plane) for plane in inner])
    assert weight[0, 0] == pytest.approx(1.0 / expected, rel=1e-12)
    assert obs["meta"]["noise_variance"] == pytest.approx(expected, rel=1e-12)
    # each realization agrees: the variance of correlated noise over 40 x 40 pixels scatters
    # by ~3.5% (160 seeds) with a long upper tail; a wrong scaling would be off by far more
    for plane in inner:
        assert np.var(plane) * weight[0, 0] == pytest.approx(1.0, abs=0.2)
    # the stored variance plane ignores the smoothing by the resampling: it is higher
    assert np.median(coadd.inner.variance) * weight[0, 0] > 1.1


def test_jacobian_matches_the_cell_wcs(cell, coadd):
    obs = to_observation(coadd)
    jac = obs["jacobian"]
    ny, nx = coadd.shape
    # the reference pixel is the cell-centre pixel, where the PSF stamp is centred
    assert (jac["row0"], jac["col0"]) == (ny // 2, nx // 2)
    assert (coadd.outer_bbox.x_start + nx // 2, coadd.outer_bbox.y_start + ny // 2) == cell.center
    ra, dec = coadd.wcs.all_pix2world([jac["col0"]], [jac["row0"]], 0)
    # independent finite difference of one pixel through astropy and the gnomonic projection
    ra_step, dec_step = coadd.wcs.all_pix2world(
        [jac["col0"] + 1.0, jac["col0"]], [jac["row0"], jac["row0"] + 1.0], 0
    )
    u, v = gnomonic_uv(ra_step, dec_step, ra[0], dec[0])
    assert jac["dudcol"] == pytest.approx(u[0], abs=1e-6)
    assert jac["dvdcol"] == pytest.approx(v[0], abs=1e-6)
    assert jac["dudrow"] == pytest.approx(u[1], abs=1e-6)
    assert jac["dvdrow"] == pytest.approx(v[1], abs=1e-6)
    # tract cells: 0.2 arcsec pixels, North up, East left (u = West grows with column)
    assert jac["dudcol"] == pytest.approx(0.2, rel=1e-6)
    assert jac["dvdrow"] == pytest.approx(0.2, rel=1e-6)
    assert abs(jac["dudrow"]) < 1e-5 and abs(jac["dvdcol"]) < 1e-5
    assert ra_step[0] < ra[0] and dec_step[1] > dec[0]
    np.testing.assert_array_equal(
        observation_jacobian(obs),
        [[jac["dudcol"], jac["dudrow"]], [jac["dvdcol"], jac["dvdrow"]]],
    )


def test_observation_feeds_metacal(coadd):
    obs = to_observation(coadd)
    jac = obs["jacobian"]
    result = measure_metacal(
        obs["image"],
        obs["psf"]["image"],
        obs["noise"],
        observation_jacobian(obs),
        noise_sigma=float(np.sqrt(obs["meta"]["noise_variance"])),
        guess_centroid=(jac["col0"], jac["row0"]),
    )
    noshear = result["noshear"]
    assert noshear["flags"][0] == 0
    # the galaxy sits on the reference pixel and keeps its sign of shape (g1 > 0, g2 < 0)
    assert abs(noshear["x"][0] - jac["col0"]) < 0.3 and abs(noshear["y"][0] - jac["row0"]) < 0.3
    assert noshear["g1"][0] > 0.03 and noshear["g2"][0] < -0.01
    assert result["1p"]["g1"][0] > result["1m"]["g1"][0]


def test_empty_cell_is_refused(cell):
    far = make_exposure((cell.center_sky[0] + 1.0, cell.center_sky[1]), visit=9)
    empty = build_cell(cell, [far], BUILD)
    assert empty.is_empty
    with pytest.raises(EmptyCellError, match="empty"):
        to_observation(empty)


def test_no_noise_realization_is_refused(cell, coadd):
    exposure = make_exposure(cell.center_sky, noise_sigma=1.0, visit=0)
    no_noise = build_cell(cell, [exposure], BuildConfig(n_noise=0, psf_size=25))
    with pytest.raises(ValueError, match="n_noise"):
        to_observation(no_noise)


def test_to_ngmix_without_ngmix_says_it_is_optional(coadd, monkeypatch):
    monkeypatch.setitem(sys.modules, "ngmix", None)  # makes "import ngmix" fail
    with pytest.raises(ImportError, match="optional"):
        to_ngmix(coadd)


def test_to_ngmix_builds_an_observation(coadd):
    ngmix = pytest.importorskip("ngmix")
    obs = to_ngmix(coadd, noise_index=2)
    plain = to_observation(coadd, noise_index=2)
    assert isinstance(obs, ngmix.Observation)
    np.testing.assert_array_equal(obs.image, plain["image"])
    np.testing.assert_array_equal(obs.weight, plain["weight"])
    np.testing.assert_array_equal(obs.noise, plain["noise"])
    np.testing.assert_array_equal(obs.bmask, plain["bmask"])
    np.testing.assert_array_equal(obs.mfrac, plain["mfrac"])
    row0, col0 = obs.jacobian.get_cen()
    assert (row0, col0) == (plain["jacobian"]["row0"], plain["jacobian"]["col0"])
    assert obs.jacobian.dudcol == pytest.approx(plain["jacobian"]["dudcol"])
    assert obs.psf.jacobian.get_cen() == ((coadd.psf.shape[0] - 1) / 2,) * 2


def test_to_ngmix_refuses_empty_cells(cell):
    pytest.importorskip("ngmix")
    far = make_exposure((cell.center_sky[0] + 1.0, cell.center_sky[1]), visit=9)
    with pytest.raises(EmptyCellError):
        to_ngmix(build_cell(cell, [far], BUILD))


class _Recorder:
    """Stands for ngmix.Observation / ngmix.Jacobian: records its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def test_to_ngmix_passes_ngmix_documented_arguments(coadd, monkeypatch):
    # ngmix is not installable here: check the calls against its documented signatures
    # Observation(image, weight=, bmask=, ormask=, noise=, jacobian=, psf=, meta=, mfrac=)
    # and Jacobian(row=, col=, dudrow=, dudcol=, dvdrow=, dvdcol=)
    fake = type(sys)("ngmix")
    fake.Observation = type("Observation", (_Recorder,), {})
    fake.Jacobian = type("Jacobian", (_Recorder,), {})
    monkeypatch.setitem(sys.modules, "ngmix", fake)
    obs = to_ngmix(coadd, noise_index=1)
    plain = to_observation(coadd, noise_index=1)
    (image,) = obs.args
    np.testing.assert_array_equal(image, plain["image"])
    assert set(obs.kwargs) == {
        "weight",
        "bmask",
        "ormask",
        "noise",
        "mfrac",
        "jacobian",
        "psf",
        "meta",
    }
    np.testing.assert_array_equal(obs.kwargs["noise"], coadd.noise[1])
    jac = obs.kwargs["jacobian"].kwargs
    keys = ("dudrow", "dudcol", "dvdrow", "dvdcol")
    expected = {key: plain["jacobian"][key] for key in keys}
    assert jac == {"row": plain["jacobian"]["row0"], "col": plain["jacobian"]["col0"], **expected}
    psf = obs.kwargs["psf"]
    np.testing.assert_array_equal(psf.args[0], coadd.psf)
    centre = (coadd.psf.shape[0] - 1) / 2
    assert psf.kwargs["jacobian"].kwargs["row"] == psf.kwargs["jacobian"].kwargs["col"] == centre


@pytest.mark.parametrize("index", [(100, 100), (0, 0), (199, 0), (0, 199), (199, 66)])
def test_cell_jacobian_is_a_scaled_rotation_without_flip(index):
    """No flip, no leakage: what a scalar-pixel-scale code (AnaCal) silently assumes.

    On the default (1.7 degree) tract the cell jacobian is ``0.2 R(phi)`` to 2e-4, with
    ``phi`` the angle between the tract's pixel grid and local North (meridian convergence,
    ~ delta_ra sin(dec)), zero at the tract centre.
    """
    tract = SkyMap.from_centers([(30.0, -10.0)], SkyMapConfig())[0]
    cell = tract.cell(*index)
    exposure = make_exposure(cell.center_sky, shape=(300, 300), noise_sigma=1.0, visit=0)
    jac = observation_jacobian(to_observation(build_cell(cell, [exposure], BUILD)))
    # no flip: column -> u (West), row -> v (North), both increasing
    assert jac[0, 0] > 0.0 and jac[1, 1] > 0.0 and np.linalg.det(jac) > 0.0
    scale = np.sqrt(np.linalg.det(jac))
    assert scale == pytest.approx(0.2, rel=1e-3)
    phi = np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1])
    rotation = scale * np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    # what is left is a WCS shear (gnomonic distortion) of at most ~1e-4
    assert np.max(np.abs(jac - rotation)) / scale < 2e-4
    ra, dec = cell.center_sky
    convergence = np.radians(ra - 30.0) * np.sin(np.radians(dec))
    if index == (100, 100):
        # at the tract centre the jacobian is diagonal: 0.2 arcsec/px, North up, East left
        assert abs(jac[0, 1]) / scale < 1e-4 and abs(jac[1, 0]) / scale < 1e-4
        assert abs(phi) < 1e-4
    else:
        # away from it, local North turns by the meridian convergence (up to 0.15 deg here)
        assert phi == pytest.approx(convergence, rel=0.1)
        assert abs(phi) > 1e-3
