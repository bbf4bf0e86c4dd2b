"""The cell builder: PSF consistency, flux, constant sky, noise, edges, determinism."""

from __future__ import annotations

import dataclasses
import pickle
import time

import galsim
import numpy as np
import pytest
from exposure_factory import make_exposure

from cellcoadd import Box, BuildConfig, SkyMap, SkyMapConfig, build_cell, build_patch
from cellcoadd.model.planes import optional_plane_flags
from cellcoadd.model.psf import GalSimPsf

CONFIG = SkyMapConfig(cell_inner=40, cell_border=15, cells_per_patch=2, patches_per_tract=1)
# counts at the inputs' zero point 30, so pixel values compare with the inputs' as is
BUILD = BuildConfig(n_noise=2, psf_size=25, units="count", zero_point=30.0)
# every optional plane on (psf_corners, ...): the routes between workers must carry them all
EVERY_PLANE = BUILD.model_copy(update={flag: True for flag in optional_plane_flags().values()})
# varied inputs: pixel scales, rotations, sub-pixel offsets, shears, SIP, PSF sizes/shapes
VARIANTS = [
    dict(pixel_scale=0.26, rotation_deg=0.0, offset=(0.3, -0.2), psf=(0.85, 0.0, 0.02)),
    dict(pixel_scale=0.2, rotation_deg=33.0, offset=(-0.4, 0.1), psf=(0.95, 0.03, -0.01)),
    dict(pixel_scale=0.24, rotation_deg=-71.0, offset=(0.1, 0.45), psf=(1.1, -0.02, 0.0)),
    dict(
        pixel_scale=0.26,
        rotation_deg=12.0,
        offset=(0.25, 0.25),
        shear=0.02,
        sip=True,
        psf=(0.9, 0.0, 0.04),
    ),
]


@pytest.fixture(scope="module")
def tract():
    return SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0]


def _psf(fwhm, e1, e2):
    return galsim.Moffat(beta=3.5, fwhm=fwhm).shear(e1=e1, e2=e2)


def _exposures(center, sources=(), **common):
    out = []
    for visit, variant in enumerate(VARIANTS):
        variant = dict(variant)
        psf = _psf(*variant.pop("psf"))
        out.append(
            make_exposure(center, psf=psf, sources=list(sources), visit=visit, **variant, **common)
        )
    return out


def _stamp(image, center, size):
    half = size // 2
    return image[center[1] - half : center[1] + half + 1, center[0] - half : center[0] + half + 1]


def test_star_at_cell_centre_equals_the_psf(tract):
    cell = tract.cell(0, 1)
    ra, dec = cell.center_sky
    coadd = build_cell(cell, _exposures((ra, dec), [(ra, dec, galsim.DeltaFunction())]), BUILD)
    assert [r.status for r in coadd.inputs] == ["used"] * 4
    ny, nx = coadd.image.shape
    star = _stamp(coadd.image.astype(float), (nx // 2, ny // 2), BUILD.psf_size)
    star = star / star.sum()
    assert coadd.psf.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.abs(star - coadd.psf).max() < 1e-4 * coadd.psf.max()


def test_star_off_centre_equals_the_psf_drawn_there(tract):
    """A star a few pixels off centre matches the coadd PSF evaluated at its position.

    The PSF at another position is the coadd PSF of a cell shifted there (the same tract
    pixels, hence the same resampling phases). Against the PSF at the cell centre the
    agreement is limited by Lanczos-3's phase-dependent interpolation error (its weights
    move the first moment by up to ~0.02 px), a few 1e-3 of the peak: checked below.
    """
    from dataclasses import replace

    cell = tract.cell(1, 1)
    shift = (3, -2)  # coadd pixels
    cx, cy = cell.center
    ra, dec = tract.pixel_to_sky(cx + shift[0], cy + shift[1])
    star = [(ra[0], dec[0], galsim.DeltaFunction())]
    exposures = _exposures(cell.center_sky, star)
    coadd = build_cell(cell, exposures, BUILD)
    moved = replace(
        cell,
        inner_bbox=cell.inner_bbox.shifted(*shift),
        outer_bbox=cell.outer_bbox.shifted(*shift),
    )
    psf_there = build_cell(moved, exposures, BUILD).psf
    ny, nx = coadd.image.shape
    got = _stamp(coadd.image.astype(float), (nx // 2 + shift[0], ny // 2 + shift[1]), 25)
    got = got / got.sum()
    assert np.abs(got - psf_there).max() < 1e-4 * psf_there.max()
    assert np.abs(got - coadd.psf).max() < 1e-2 * coadd.psf.max()


def test_constant_sky_stays_constant(tract):
    """Constant sky per exposure pixel (linear WCSs: constant on the sky) stays constant."""
    cell = tract.cell(0, 0)
    exposures = _exposures(cell.center_sky, sky=7.0)[:3]  # the SIP one varies on the sky
    coadd = build_cell(cell, exposures, BUILD)
    expected = coadd.image.astype(float).mean()
    assert np.abs(coadd.image / expected - 1).max() < 1e-6
    # per exposure pixel -> per coadd pixel: scaled by the pixel-area ratio
    area_ratios = [(0.2 / v["pixel_scale"]) ** 2 for v in VARIANTS[:3]]
    weights = [1.0 / e.background_variance for e in exposures]
    assert expected == pytest.approx(7.0 * np.average(area_ratios, weights=weights), rel=1e-6)


def test_galaxy_flux_is_conserved_across_pixel_scales(tract):
    cell = tract.cell(1, 0)
    ra, dec = cell.center_sky
    galaxy = galsim.Exponential(half_light_radius=0.5, flux=1000.0).shear(g1=0.2, g2=-0.1)
    coadd = build_cell(cell, _exposures((ra, dec), [(ra, dec, galaxy)]), BUILD)
    assert coadd.image.astype(float).sum() == pytest.approx(1000.0, rel=1e-4)


def test_integer_shift_with_identical_scale_is_an_exact_copy(tract):
    cell = tract.cell(0, 0)
    wcs = cell.wcs.deepcopy()
    wcs.wcs.crpix = wcs.wcs.crpix + np.array([17.0, 9.0])  # exposure pixel = cell pixel + (17, 9)
    wcs.wcs.set()
    rng = np.random.default_rng(2)
    image = rng.normal(size=(120, 110))
    from cellcoadd import Exposure

    exposure = Exposure(
        image=image,
        wcs=wcs,
        variance=1.0,
        psf=galsim.Gaussian(fwhm=0.8),
        visit=1,
        detector=1,
        band="r",
        zero_point=30.0,
    )
    coadd = build_cell(cell, [exposure], BUILD)
    ny, nx = cell.outer_bbox.shape
    np.testing.assert_array_equal(coadd.image, image[9 : 9 + ny, 17 : 17 + nx].astype(np.float32))


def test_edge_rejection_and_coverage(tract):
    cell = tract.cell(1, 1)
    center = cell.center_sky
    covering = make_exposure(center, visit=1)
    # a valid box that stops inside the cell: exposure pixels x < 90 only (centre is 79.5)
    cut = make_exposure(center, visit=2, valid_box=Box(x_start=0, x_stop=90, y_start=0, y_stop=160))
    far = make_exposure((center[0] + 1.0, center[1]), visit=3)
    coadd = build_cell(cell, [covering, cut, far], BUILD)
    status = {r.visit: r.status for r in coadd.inputs}
    assert status == {1: "used", 2: "edge", 3: "no_overlap"}
    fractions = {r.visit: r.overlap_fraction for r in coadd.inputs}
    assert fractions[1] == 1.0 and 0.0 < fractions[2] < 1.0 and fractions[3] == 0.0


def test_empty_cell_is_flagged_not_an_error(tract):
    cell = tract.cell(1, 1)
    far = make_exposure((cell.center_sky[0] + 1.0, cell.center_sky[1]), visit=3)
    coadd = build_cell(cell, [far], BUILD)
    assert coadd.is_empty and np.isnan(coadd.image).all()
    assert (coadd.mask & far.mask_bits.value("NO_DATA")).all()
    assert [r.status for r in coadd.inputs] == ["no_overlap"]


def test_pure_noise_realizations_match_the_image_noise(tract):
    cell = tract.cell(0, 0)
    config = BuildConfig(n_noise=3, psf_size=25)
    sigma = 2.0
    exposures = [
        make_exposure(
            cell.center_sky,
            shape=(200, 200),
            noise_sigma=sigma,
            seed=100 + i,
            visit=i,
            **{k: v for k, v in VARIANTS[i].items() if k != "psf"},
        )
        for i in range(len(VARIANTS))
    ]
    coadd = build_cell(cell, exposures, config, seed=5)
    planes = [coadd.image.astype(float)] + [n.astype(float) for n in coadd.noise]

    def stats(a):
        a = a - a.mean()
        var = a.var()

        def lag(dx, dy):
            return np.mean(a[dy:, dx:] * a[: a.shape[0] - dy, : a.shape[1] - dx]) / var

        return np.array([var, lag(1, 0), lag(0, 1), lag(1, 1)])

    image_stats = stats(planes[0])
    for noise in planes[1:]:
        # 4900 correlated pixels: allow generous but meaningful tolerances
        np.testing.assert_allclose(stats(noise)[0], image_stats[0], rtol=0.15)
        np.testing.assert_allclose(stats(noise)[1:], image_stats[1:], atol=0.08)
    # realizations are mutually independent
    for i in range(1, 4):
        for j in range(i + 1, 4):
            assert abs(np.corrcoef(planes[i].ravel(), planes[j].ravel())[0, 1]) < 0.1
    # the variance plane predicts the uncorrelated part: kernel-smoothing lowers the
    # pixel variance below it, never above
    assert image_stats[0] < coadd.variance.mean()


def test_overlapping_cells_share_the_noise(tract):
    left, right = tract.cell(0, 0), tract.cell(1, 0)
    center = tract.pixel_to_sky(
        *[float(v) for v in left.outer_bbox.intersection(right.outer_bbox).shape[::-1]]
    )  # any position; recomputed below
    overlap = left.outer_bbox.intersection(right.outer_bbox)
    mid = tract.pixel_to_sky([(overlap.x_start + overlap.x_stop) / 2], [left.center[1]])
    center = (float(mid[0][0]), float(mid[1][0]))
    exposures = [
        make_exposure(
            center,
            shape=(200, 200),
            visit=i,
            noise_sigma=1.0,
            seed=i,
            **{k: v for k, v in VARIANTS[i].items() if k != "psf"},
        )
        for i in range(2)
    ]
    a = build_cell(left, exposures, BUILD, seed=9)
    b = build_cell(right, exposures, BUILD, seed=9)
    sa, sb = overlap.slices_in(left.outer_bbox), overlap.slices_in(right.outer_bbox)
    for k in range(BUILD.n_noise):
        diff = np.abs(a.noise[k][sa].astype(float) - b.noise[k][sb])
        assert diff.max() < 1e-3 * a.noise[k].std()
    np.testing.assert_allclose(a.image[sa], b.image[sb], atol=1e-3 * a.image.std())


def test_same_seed_same_arrays_and_different_seed_differs(tract):
    cell = tract.cell(0, 1)
    exposures = _exposures(cell.center_sky, noise_sigma=1.0)
    a = build_cell(cell, exposures, BUILD, seed=3)
    b = build_cell(cell, exposures, BUILD, seed=3)
    c = build_cell(cell, exposures, BUILD, seed=4)
    np.testing.assert_array_equal(a.noise, b.noise)
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.noise, c.noise)


@pytest.fixture(scope="module")
def patch_inputs(tract):
    center = tract.pixel_to_sky([39.5], [39.5])
    exposures = [
        make_exposure(
            (float(center[0][0]), float(center[1][0])),
            shape=(260, 260),
            visit=i,
            noise_sigma=1.0,
            seed=i,
            **{k: v for k, v in VARIANTS[i].items() if k != "psf"},
        )
        for i in range(2)
    ]
    serial = build_patch(tract.patch(0, 0), exposures, EVERY_PLANE, seed=1, progress=False)
    return exposures, serial


def _assert_same_patch(first, second):
    assert list(first.cells) == list(second.cells)
    optional = list(optional_plane_flags())
    assert optional and set(optional) <= set(first.metadata.cell_plane_names)
    for index, cell in first.cells.items():
        assert all(getattr(cell, name) is not None for name in optional), index
        assert cell.equals(second.cells[index]), index


def test_patch_identical_for_any_number_of_workers(tract, patch_inputs):
    exposures, serial = patch_inputs
    parallel = build_patch(
        tract.patch(0, 0), exposures, EVERY_PLANE, seed=1, progress=False, workers=2
    )
    _assert_same_patch(serial, parallel)
    assert sum(not c.is_empty for c in serial.cells.values()) >= 4


def test_patch_identical_on_a_dask_cluster(tract, patch_inputs, dask_client):
    exposures, serial = patch_inputs
    on_dask = build_patch(
        tract.patch(0, 0), exposures, EVERY_PLANE, seed=1, progress=False, scheduler=dask_client
    )
    _assert_same_patch(serial, on_dask)


def test_a_failing_cell_is_named(tract, patch_inputs):
    from cellcoadd import CellBuildError

    exposures, _ = patch_inputs

    def failing_psf(x, y):
        raise ZeroDivisionError("boom")

    bad = dataclasses.replace(
        make_exposure(exposures[0].wcs.wcs.crval, visit=99), psf=GalSimPsf(failing_psf)
    )
    # recorded as bad_psf, not a failure
    ok = build_patch(tract.patch(0, 0), [*exposures, bad], BUILD, seed=1, progress=False)
    assert any(r.status == "bad_psf" for c in ok.cells.values() for r in c.inputs)
    with pytest.raises(CellBuildError, match=r"cell \(-?\d+, -?\d+\) of tract 0 failed"):
        build_patch(tract.patch(0, 0), exposures, BuildConfig(psf_size=99), progress=False)


def test_bad_inputs_are_refused_or_recorded(tract):
    cell = tract.cell(0, 0)
    good = make_exposure(cell.center_sky, visit=1)
    with pytest.raises(ValueError, match="duplicate"):
        build_cell(cell, [good, make_exposure(cell.center_sky, visit=1)], BUILD)
    zero_var = make_exposure(cell.center_sky, visit=2, variance=0.0)
    coadd = build_cell(cell, [good, zero_var], BUILD)
    assert {r.visit: r.status for r in coadd.inputs} == {1: "used", 2: "bad_weight"}

    def broken_psf(x, y):
        raise RuntimeError("no PSF model here")

    bad_psf = dataclasses.replace(
        make_exposure(cell.center_sky, visit=3), psf=GalSimPsf(broken_psf)
    )
    coadd = build_cell(cell, [good, bad_psf], BUILD)
    assert {r.visit: r.status for r in coadd.inputs} == {1: "used", 3: "bad_psf"}


def test_dask_tasks_carry_references_to_exposures_not_pixels(
    tract, patch_inputs, dask_client, monkeypatch
):
    distributed = pytest.importorskip("distributed")
    exposures, serial = patch_inputs
    one_exposure = len(pickle.dumps(exposures[0], protocol=5))
    tasks = []  # per task (a block of cells): its pickled size, each candidate's type
    cells_built = []
    submit = dask_client.submit

    def recording_submit(function, *args, **kwargs):
        tasks.append((len(pickle.dumps(args, protocol=5)), [type(c) for c in args[1]]))
        cells_built.extend(cell.index for cell in args[0])
        return submit(function, *args, **kwargs)

    monkeypatch.setattr(dask_client, "submit", recording_submit)
    on_dask = build_patch(
        tract.patch(0, 0), exposures, EVERY_PLANE, seed=1, progress=False, scheduler=dask_client
    )
    _assert_same_patch(serial, on_dask)
    assert sorted(cells_built) == sorted(serial.cells)  # each cell in one block
    assert len(tasks) > 1  # blocks spread over the workers
    assert all(kinds for _, kinds in tasks)  # exposures referenced
    assert all(kind is distributed.Future for _, kinds in tasks for kind in kinds)
    assert max(size for size, _ in tasks) < one_exposure / 10
    # the exposures broadcast to the workers are released once the patch is built
    for _ in range(100):
        if not dask_client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)):
            break
        time.sleep(0.05)
    assert dask_client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0
