"""The coadd PSF across a cell: corner PSFs (``BuildConfig.psf_corners``), their storage in
both formats (1.4), and ``CellCoadd.psf_at``, checked against stars injected off centre."""

from __future__ import annotations

import json
import math
import warnings

import galsim
import numpy as np
import pytest
from astropy.wcs import WCS
from coadd_factory import make_patch
from conftest import DES_PSF
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, Exposure, SkyMap, SkyMapConfig, build_cell
from cellcoadd.builder.cell import build_cells
from cellcoadd.builder.cell_sums import cell_jacobian
from cellcoadd.builder.psf import psf_moments
from cellcoadd.errors import (
    CellCoaddRangeError,
    CellCoaddValueError,
    ConfigError,
    InvalidCoaddError,
)
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell
from cellcoadd.io import api, read_psfex
from cellcoadd.io.coadd import format_version
from cellcoadd.model import planes as cell_planes
from cellcoadd.model.cell_coadd import CellCoadd, psf_interpolation_weights
from cellcoadd.model.inputs import InputStatus
from cellcoadd.model.patch_coadd import FORMAT_VERSION, PatchCoadd
from cellcoadd.model.psf import CallablePsf
from cellcoadd.sim.psf import focal_plane_psf

#: Default-sized cells (inner 150, border 50: outer 250 px at 0.2"/px).
GRID = SkyMapConfig(cell_inner=150, cell_border=50, cells_per_patch=1, patches_per_tract=1)
#: DECam's pixel scale, arcsec/px.
DECAM_SCALE = 0.263
#: Stars, cell array pixels (the centre is (125, 125), the inner box 50..199): 60 px from
#: the centre along x and along y, 60 px diagonally, and two towards corners.
STARS = [(185, 125), (125, 185), (167, 167), (65, 80), (190, 60)]
#: Half side of the PSF stamps (51 px) and of the star stamps cut from the coadd.
HALF = 25


def _cell() -> Cell:
    return SkyMap.from_centers([(60.0, -30.0)], GRID)[0].cell(0, 0)


def _rotated_wcs(sky: tuple[float, float], centre: tuple[float, float], angle: float) -> WCS:
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = list(sky)
    wcs.wcs.crpix = [centre[0] + 1.0, centre[1] + 1.0]
    c, s = math.cos(angle), math.sin(angle)
    wcs.wcs.cd = np.array([[-c, s], [s, c]]) * DECAM_SCALE / 3600.0
    wcs.wcs.set()
    return wcs


def _with_stars(cell: Cell, wcs: WCS, psf: object, k: int, origin=(0, 0)) -> Exposure:
    """A 500 x 500 exposure holding unit-flux stars at :data:`STARS`, each drawn with the
    exposure's own PSF model where the star falls (pixel response included, as the builder
    draws the PSF), no noise."""
    blank = Exposure(image=np.zeros((500, 500)), wcs=wcs, variance=1.0, psf=psf, visit=k,
                     detector=12, band="r", zero_point=30.0, origin=origin)  # fmt: skip
    image = np.zeros((500, 500))
    for x, y in STARS:
        ra, dec = cell.wcs.pixel_to_world_values(x, y)
        ex, ey = (float(v) for v in wcs.world_to_pixel_values(ra, dec))
        box = Box(x_start=int(ex) - 30, x_stop=int(ex) + 31, y_start=int(ey) - 30,
                  y_stop=int(ey) + 31)  # fmt: skip
        image[box.slices] += blank.draw_psf(ex, ey, box)
    return Exposure(image=image, wcs=wcs, variance=1.0, psf=psf, visit=k, detector=12,
                    band="r", zero_point=30.0, origin=origin)  # fmt: skip


def _build(cell: Cell, exposures: list[Exposure], **config: object) -> CellCoadd:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # small stamps of wide PSFs
        return build_cell(cell, exposures, BuildConfig(n_noise=0, psf_size=2 * HALF + 1, **config))


def _compare(coadd: CellCoadd, cell: Cell) -> list[tuple[float, float, float, float]]:
    """For each star: (dT/T, |de|) of ``psf_at`` and of the centre ``psf`` against the
    star's coadded image (adaptive moments, T = Ixx + Iyy)."""
    jacobian = cell_jacobian(cell)
    centre = psf_moments(coadd.psf, jacobian)
    rows = []
    for x, y in STARS:
        stamp = coadd.image[y - HALF : y + HALF + 1, x - HALF : x + HALF + 1].astype(np.float64)
        star = psf_moments(stamp / stamp.sum(), jacobian)
        at = psf_moments(coadd.psf_at(x, y), jacobian)

        def errors(m: dict[str, float], star: dict[str, float] = star) -> tuple[float, float]:
            de = math.hypot(m["psf_e1"] - star["psf_e1"], m["psf_e2"] - star["psf_e2"])
            return m["psf_T"] / star["psf_T"] - 1.0, de

        rows.append((*errors(at), *errors(centre)))
    return rows


def test_stars_off_centre_match_psf_at_with_the_simulators_variation():
    """The simulator's focal-plane variation (FWHM +5%, |g| = 0.01 at the corner), made
    steep: a 1000-pixel corner radius, the cell at 80% of it, on the same side of the
    boresight in all 6 exposures (rotated, 0.263"/px: real resampling). A Moffat of FWHM
    1.2" keeps resampling's own phase-dependent error (the floor psf_at cannot remove,
    docs/shear.md) at ~4e-4 in T."""
    cell = _cell()
    sky = cell.center_sky
    exposures = []
    for k in range(6):
        centre = (250.0 + 0.3 * k, 250.0 - 0.2 * k)
        phi = 0.3 * k
        boresight = (centre[0] - 800.0 * math.cos(phi), centre[1] - 800.0 * math.sin(phi))
        psf = focal_plane_psf(galsim.Moffat(beta=3.5, fwhm=1.2), boresight, 1000.0, 0.05, 0.01)
        wcs = _rotated_wcs(sky, centre, math.radians(23.0 * k))
        exposures.append(_with_stars(cell, wcs, psf, k))
    coadd = _build(cell, exposures, psf_corners=True)
    assert coadd.n_used == 6
    rows = _compare(coadd, cell)
    for (x, y), (dt_at, de_at, _, _) in zip(STARS, rows, strict=True):
        assert abs(dt_at) < 1e-3 and de_at < 1e-3, ((x, y), dt_at, de_at)
    # the centre's PSF does not describe them: the test fails without psf_at
    failing = [(x, y) for (x, y), row in zip(STARS, rows, strict=True) if abs(row[2]) > 1e-3]
    assert (125, 185) in failing and len(failing) >= 4, rows


def test_stars_off_centre_match_psf_at_with_a_real_decam_psfex_model():
    """The real DECam PSFEx model (exposure 154912, CCD 12), the cell at 6 places of the
    CCD. The exposures share the coadd's pixel grid up to whole-pixel shifts, so the
    resampling is exact and what remains is the model's variation across the cell, which
    psf_at interpolates to ~1e-5 (at 0.263"/px the resampling floor of this undersampled
    PSF, a few 1e-3 in T, would hide it: docs/shear.md)."""
    cell = _cell()
    model = read_psfex(DES_PSF)
    exposures = []
    for k in range(6):
        wcs = cell.wcs.deepcopy()  # exposure pixel (i, j) = cell pixel (i - dx, j - dy)
        wcs.wcs.crpix = wcs.wcs.crpix + np.array([125.0 + 3 * k, 125.0 - 2 * k])
        wcs.wcs.set()
        origin = (1024 + 150 * k - 250, 2048 - 300 * k - 250)
        exposures.append(_with_stars(cell, wcs, model, k, origin))
    coadd = _build(cell, exposures, psf_corners=True)
    assert coadd.n_used == 6
    rows = _compare(coadd, cell)
    for (x, y), (dt_at, de_at, _, _) in zip(STARS, rows, strict=True):
        assert abs(dt_at) < 1e-4 and de_at < 1e-4, ((x, y), dt_at, de_at)
    failing = [(x, y) for (x, y), row in zip(STARS, rows, strict=True) if abs(row[2]) > 1e-3]
    assert len(failing) >= 4, rows


def test_interpolation_weights():
    """Exact at the 5 stamps and for a + b x + c y + d x y + e (x^2 + y^2) over the cell's
    square inner box; not for x^2 alone (5 stamps cannot hold every quadratic)."""
    cell = make_patch(psf_size=5, psf_corners=True)[(1, 1)]
    centre, corners = cell.psf_centre, cell.psf_corner_positions
    inner = cell.inner_bbox.slices_in(cell.outer_bbox)
    assert centre == (cell.shape[1] // 2, cell.shape[0] // 2)
    assert corners.tolist() == [
        [inner[1].start, inner[0].start],
        [inner[1].stop - 1, inner[0].start],
        [inner[1].start, inner[0].stop - 1],
        [inner[1].stop - 1, inner[0].stop - 1],
    ]
    np.testing.assert_array_equal(psf_interpolation_weights(*centre, centre, corners), np.eye(5)[0])
    for k, (x, y) in enumerate(corners):
        weights = psf_interpolation_weights(float(x), float(y), centre, corners)
        np.testing.assert_allclose(weights, np.eye(5)[k + 1], atol=1e-15)
    points = np.array([centre, *corners], dtype=float)

    def field(x, y):
        return 0.3 + 0.02 * x - 0.05 * y + 1e-3 * x * y + 2e-4 * (x**2 + y**2)

    rng = np.random.default_rng(5)
    lo, hi = corners[0] - 0.5, corners[3] + 0.5
    for x, y in rng.uniform(lo, hi, size=(50, 2)):
        weights = psf_interpolation_weights(x, y, centre, corners)
        assert math.isclose(weights.sum(), 1.0, abs_tol=1e-12)
        assert math.isclose(weights @ field(*points.T), field(x, y), rel_tol=1e-12)
    weights = psf_interpolation_weights(4.0, 7.0, centre, corners)
    assert not math.isclose(weights @ points[:, 0] ** 2, 16.0, rel_tol=1e-3)


def test_psf_at_returns_the_stamps_and_refuses_what_it_cannot_give():
    patch = make_patch(psf_size=5, psf_corners=True)
    cell = patch[(1, 1)]
    assert cell.psf_corners is not None
    np.testing.assert_allclose(cell.psf_at(*cell.psf_centre), cell.psf, rtol=1e-14)
    for stamp, (x, y) in zip(cell.psf_corners, cell.psf_corner_positions, strict=True):
        np.testing.assert_allclose(cell.psf_at(x, y), stamp, rtol=1e-12, atol=1e-15)
    middle = cell.psf_at(cell.psf_centre[0] + 0.7, cell.psf_centre[1] - 1.2)
    assert middle.shape == cell.psf.shape and math.isclose(middle.sum(), 1.0, rel_tol=1e-12)
    # the inner box's pixel edges are accepted, beyond needs extrapolate (within the outer)
    rows, cols = cell.inner_bbox.slices_in(cell.outer_bbox)
    assert np.isfinite(cell.psf_at(cols.start - 0.5, rows.stop - 0.5)).all()
    with pytest.raises(CellCoaddRangeError, match=r"cell \(1, 1\).*extrapolate") as info:
        cell.psf_at(cols.start - 0.6, rows.start)
    assert info.value.cell == (1, 1)
    assert np.isfinite(cell.psf_at(0.0, cell.shape[0] - 1.0, extrapolate=True)).all()
    with pytest.raises(CellCoaddRangeError, match="outer box"):
        cell.psf_at(-1.0, 3.0, extrapolate=True)
    # without corners: a clear error naming the cell
    bare = make_patch(psf_size=5)[(2, 1)]
    assert bare.psf_corners is None
    with pytest.raises(CellCoaddValueError, match=r"cell \(2, 1\).*psf_corners=True") as info:
        bare.psf_at(*bare.psf_centre)
    assert info.value.cell == (2, 1)


def test_cells_and_patches_check_the_corners():
    cell = make_patch(psf_size=5, psf_corners=True)[(1, 1)]
    fields = {name: getattr(cell, name) for name in cell_planes.required_plane_names()}
    identity = dict(tract=cell.tract, index=cell.index, inner_bbox=cell.inner_bbox,
                    outer_bbox=cell.outer_bbox, wcs=cell.wcs, inputs=cell.inputs)  # fmt: skip
    with pytest.raises(InvalidCoaddError, match=r"\(4, n, n\)"):
        CellCoadd(**fields, **identity, psf_corners=cell.psf_corners[:3])
    with pytest.raises(InvalidCoaddError, match="sum to 1"):
        CellCoadd(**fields, **identity, psf_corners=2 * cell.psf_corners)
    # all the cells of a patch have them or none does
    patch = make_patch(psf_size=5, psf_corners=True)
    bare = make_patch(psf_size=5)
    mixed = dict(patch.cells)
    mixed[(1, 1)] = bare[(1, 1)]
    with pytest.raises(InvalidCoaddError, match="all the cells of a patch"):
        PatchCoadd(patch.metadata, mixed)
    empty = make_patch(psf_size=5, psf_corners=True, empty=((1, 1),))[(1, 1)]
    assert empty.psf_corners is not None and np.isnan(empty.psf_corners).all()


@pytest.mark.parametrize(
    "name, compression", [("p.fits", None), ("p.fits", "lossless"), ("p.h5", None),
                          ("p.h5", "lossless")]
)  # fmt: skip
def test_corners_round_trip_losslessly(tmp_path, name, compression):
    patch = make_patch(n_noise=1, psf_size=7, psf_corners=True, empty=((0, 0),))
    path = tmp_path / name
    api.write(patch, path, compression=compression)
    back = api.read(path)
    assert back.metadata.format_version == FORMAT_VERSION
    assert back.metadata.build_config.psf_corners and back.has_psf_corners
    for index, cell in patch.items():
        assert back[index].equals(cell)
        assert back[index].psf_corners.tobytes() == cell.psf_corners.tobytes()
    one = api.read_cell(path, (2, 2))
    np.testing.assert_array_equal(one.psf_at(5.0, 6.0, extrapolate=True),
                                  patch[(2, 2)].psf_at(5.0, 6.0, extrapolate=True))  # fmt: skip
    # a patch without them: nothing stored, None read back
    bare = make_patch(n_noise=1, psf_size=7)
    api.write(bare, path, compression=compression, overwrite=True)
    back = api.read(path)
    assert not back.has_psf_corners and back[(1, 1)].psf_corners is None
    assert "psf_corners" not in back.metadata.build_config.model_dump_json()


@pytest.mark.parametrize("name", ["old.fits", "old.h5"])
def test_files_of_format_1_3_read_without_corners(tmp_path, monkeypatch, name):
    """A 1.3 file (no corner plane: no ``HDU_PSF_CORNERS`` column, no dataset listed in
    ``contents``) reads with ``psf_corners = None``; psf_at says why it cannot work."""
    patch = make_patch(n_noise=1, psf_size=5)
    required = tuple(spec for spec in cell_planes.PLANES if not spec.optional)

    def payload(metadata):
        data = json.loads(metadata.model_dump_json())
        data["format_version"] = "1.3"
        return json.dumps(data).encode("utf-8"), "1.3"

    with monkeypatch.context() as patched:  # write with the 1.3 description of the planes
        patched.setattr(cell_planes, "PLANES", required)
        patched.setattr(format_version, "metadata_payload", payload)
        api.write(patch, tmp_path / name)
    if name.endswith(".fits"):
        import fitsio

        with fitsio.FITS(str(tmp_path / name)) as fits:
            assert "HDU_PSF_CORNERS" not in fits["CELLINDEX"].get_colnames()
    back = api.read(tmp_path / name)
    assert back.metadata.format_version == "1.3"
    for index, cell in patch.items():
        assert back[index].equals(cell) and back[index].psf_corners is None
    with pytest.raises(CellCoaddValueError, match="before format 1.4"):
        back[(1, 1)].psf_at(10.0, 10.0)


def _shift_cell(cell: Cell, dx: int, dy: int) -> Cell:
    import dataclasses

    return dataclasses.replace(
        cell, inner_bbox=cell.inner_bbox.shifted(dx, dy), outer_bbox=cell.outer_bbox.shifted(dx, dy)
    )


def test_corners_use_the_cells_inputs_and_change_nothing_else():
    """With corners the cell has the same inputs, weights, pixels and centre PSF, bit for
    bit; an input whose PSF cannot be drawn at a corner is rejected for the whole cell
    (``bad_psf``), so the 5 PSFs always average the same inputs."""
    cell = _cell()
    sky = cell.center_sky
    exposures = [
        make_exposure(
            sky,
            shape=(600, 600),
            pixel_scale=DECAM_SCALE,
            rotation_deg=17.0 * k,
            offset=(0.37 * k, -0.21 * k),
            visit=k,
            detector=1,
            psf=galsim.Moffat(beta=3.5, fwhm=0.8 + 0.05 * k),
        )  # fmt: skip
        for k in range(3)
    ]
    # visit 3: a PSF model that fails farther than 40 exposure pixels from the cell centre
    failing = make_exposure(sky, shape=(400, 400), pixel_scale=DECAM_SCALE, visit=3, detector=1)
    centre_x, centre_y = (float(v) for v in failing.wcs.world_to_pixel_values(*sky))

    def near_centre_only(x: float, y: float) -> galsim.GSObject:
        if math.hypot(x - centre_x, y - centre_y) > 40.0:
            raise galsim.GalSimError("outside the model's validity")
        return galsim.Moffat(beta=3.5, fwhm=1.0)

    exposures.append(
        Exposure(
            image=failing.image,
            wcs=failing.wcs,
            variance=1.0,
            visit=3,
            detector=1,
            band=failing.band,
            zero_point=failing.zero_point,
            psf=CallablePsf(near_centre_only, includes_pixel=False),
        )  # fmt: skip
    )
    plain = _build(cell, exposures)
    corners = _build(cell, exposures, psf_corners=True)
    assert plain.psf_corners is None and corners.psf_corners is not None
    status = {r.visit: r.status for r in corners.inputs}
    assert status == {0: "used", 1: "used", 2: "used", 3: InputStatus.BAD_PSF}
    assert {r.visit: r.status for r in plain.inputs}[3] == "used"
    # without the failing input both builds are the same cell, bit for bit
    plain = _build(cell, exposures[:3])
    corners = _build(cell, exposures[:3], psf_corners=True)
    assert corners.psf_corners is not None
    corners.psf_corners = None
    assert corners.equals(plain)
    # each corner stamp is the centre stamp of the cell moved onto that corner, to the
    # accuracy of its render from the exposures' cores (test_corner_stamps_equal_...)
    restored = _build(cell, exposures[:3], psf_corners=True)
    moved = _build(_shift_cell(cell, 74, 74), exposures[:3])
    assert moved.n_used == 3
    np.testing.assert_allclose(
        restored.psf_corners[3], moved.psf, rtol=0, atol=5e-4 * moved.psf.max()
    )


@pytest.mark.parametrize("kind", ["sim", "psfex"])
def test_corner_stamps_equal_the_psf_drawn_at_the_corners(kind):
    """Each corner stamp is the centre stamp plus what the exposures' oversampled cores
    (drawn per exposure at a grid of nodes and interpolated at the corner) change between
    centre and corner: it equals the stamp drawn and warped at the corner itself (the
    centre stamp of the cell moved there) to 2e-4 in T/T and e and 5e-4 of the peak per
    pixel (measured <= 1.4e-4 and 2.8e-4 with 75-px stamps, docs/shear.md), for varying
    models: the simulator's steep focal-plane variation and the real DECam PSFEx model
    on 6 rotated 0.263"/px exposures. The centre stamp is drawn as before, bit for bit."""
    cell = _cell()
    sky = cell.center_sky
    exposures = []
    for k in range(6):
        wcs = _rotated_wcs(sky, (250.0 + 0.3 * k, 250.0 - 0.2 * k), math.radians(23.0 * k))
        if kind == "sim":
            phi = 0.3 * k
            boresight = (250.0 - 800.0 * math.cos(phi), 250.0 - 800.0 * math.sin(phi))
            psf = focal_plane_psf(galsim.Moffat(beta=3.5, fwhm=0.9), boresight, 1000.0, 0.05,
                                  0.01)  # fmt: skip
            origin = (0, 0)
        else:
            psf = read_psfex(DES_PSF)
            origin = (1024 + 150 * k - 250, 2048 - 300 * k - 250)
        exposures.append(Exposure(image=np.zeros((500, 500)), wcs=wcs, variance=1.0, psf=psf,
                                  visit=k, detector=12, band="r", zero_point=30.0,
                                  origin=origin))  # fmt: skip
    both = _build(cell, exposures, psf_corners=True, psf_phase=True)
    plain = _build(cell, exposures)
    np.testing.assert_array_equal(both.psf, plain.psf)
    jacobian = cell_jacobian(cell)
    xc, yc = both.psf_centre
    for k, (px, py) in enumerate(both.psf_corner_positions):
        exact = _build(_shift_cell(cell, int(px - xc), int(py - yc)), exposures).psf
        got, want = psf_moments(both.psf_corners[k], jacobian), psf_moments(exact, jacobian)
        assert abs(got["psf_T"] / want["psf_T"] - 1.0) < 2e-4, (k, got, want)
        assert abs(got["psf_e1"] - want["psf_e1"]) < 2e-4, (k, got, want)
        assert abs(got["psf_e2"] - want["psf_e2"]) < 2e-4, (k, got, want)
        np.testing.assert_allclose(both.psf_corners[k], exact, rtol=0, atol=5e-4 * exact.max())
        # the corner differs from the centre by far more: the test sees the corners
        centre = psf_moments(both.psf, jacobian)
        assert (
            abs(centre["psf_T"] / want["psf_T"] - 1.0)
            + abs(centre["psf_e1"] - want["psf_e1"])
            + abs(centre["psf_e2"] - want["psf_e2"])
            > 1e-3
        )


def test_renders_of_the_builder_equal_those_of_psf_at():
    """The builder's compiled render of a core (corner stamps) is psf_at's
    (:func:`~cellcoadd.model.psf_phase.render_input`) to rounding, at integral and
    fractional phases and with each position's own map."""
    from cellcoadd.builder.psf import render_cores
    from cellcoadd.model.psf_phase import PHASE_SIDE, prefiltered, render_input

    core = galsim.Moffat(beta=3.5, fwhm=3.4).shear(g1=0.04, g2=-0.02).drawImage(
        nx=PHASE_SIDE, ny=PHASE_SIDE, scale=0.25, method="no_pixel"
    ).array * 16.0  # fmt: skip
    phases = [(0.3, 0.6), (0.0, 0.0), (0.5, 0.25), (0.99, 0.01), (0.0, 0.7)]
    jacobians = [np.array([[0.7, 0.25 + 0.01 * k], [-0.26, 0.69]]) for k in range(5)]
    maps = [
        (jac, 0.58 - 0.01 * k, phase)
        for k, (jac, phase) in enumerate(zip(jacobians, phases, strict=True))
    ]
    rendered = render_cores([prefiltered(core)] * 5, maps, 51)
    for got, (jac, area, phase) in zip(rendered, maps, strict=True):
        want = render_input(core, np.array([*phase, *jac.ravel(), area, 1.0]), phase, 51)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * want.max())
        assert got.sum() > 0.5


def test_corner_stamps_must_fit_in_the_border():
    cell = _cell()
    exposure = make_exposure(cell.center_sky, shape=(400, 400), pixel_scale=DECAM_SCALE)
    with pytest.raises(ConfigError, match="psf_size <= 101"):
        build_cell(cell, [exposure], BuildConfig(n_noise=0, psf_size=103, psf_corners=True))


def test_corner_stamps_of_a_varying_psf_do_not_depend_on_the_block():
    """The exposures' cores are drawn at nodes fixed by the exposure alone and interpolated
    with weights fixed by the cell: 4 neighbouring cells built together (one block, the
    nodes shared) equal each built alone over the same mapped area (as a patch's blocks
    and parts are), bit for bit, with a varying PSF model."""
    grid = SkyMapConfig(cell_inner=150, cell_border=50, cells_per_patch=2, patches_per_tract=1)
    tract = SkyMap.from_centers([(60.0, -30.0)], grid)[0]
    cells = [tract.cell(i, j) for i in range(2) for j in range(2)]
    sky = tract.wcs.pixel_to_world_values(
        *(np.mean([c.outer_bbox.x_start + c.outer_bbox.nx / 2 for c in cells]) - 0.5,
          np.mean([c.outer_bbox.y_start + c.outer_bbox.ny / 2 for c in cells]) - 0.5)
    )  # fmt: skip
    exposures = []
    for k in range(3):
        wcs = _rotated_wcs(
            (float(sky[0]), float(sky[1])), (350.0 + 0.3 * k, 350.0 - 0.2 * k), 0.4 * k
        )
        boresight = (350.0 - 800.0 * math.cos(k), 350.0 - 800.0 * math.sin(k))
        psf = focal_plane_psf(galsim.Moffat(beta=3.5, fwhm=0.9), boresight, 1000.0, 0.05, 0.01)
        exposures.append(Exposure(image=np.zeros((700, 700)), wcs=wcs, variance=1.0, psf=psf,
                                  visit=k, detector=1, band="r", zero_point=30.0))  # fmt: skip
    config = BuildConfig(n_noise=0, psf_size=51, psf_corners=True, psf_phase=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        area = Box.enclosing([cell.outer_bbox for cell in cells])
        together = build_cells(cells, exposures, config, area=area)
        for cell, built in zip(cells, together, strict=True):
            assert built.n_used == 3 and built.psf_corners is not None
            assert built.equals(build_cells([cell], exposures, config, area=area)[0])


def test_corner_stamps_of_a_varying_psf_do_not_depend_on_workers_or_parts():
    """build_patch with a varying PSF model, corners and phase terms: 2 workers, and the
    cells built in two parts, give the serial build's cells bit for bit."""
    from cellcoadd.builder.patch import build_patch

    grid = SkyMapConfig(cell_inner=60, cell_border=40, cells_per_patch=2, patches_per_tract=1)
    tract = SkyMap.from_centers([(60.0, -30.0)], grid)[0]
    patch = tract.patch(0, 0)
    box = patch.inner_bbox
    sky = tract.wcs.pixel_to_world_values(
        box.x_start + box.nx / 2 - 0.5, box.y_start + box.ny / 2 - 0.5
    )
    exposures = []
    for k in range(3):
        wcs = _rotated_wcs(
            (float(sky[0]), float(sky[1])), (350.0 + 0.3 * k, 350.0 - 0.2 * k), 0.4 * k
        )
        boresight = (350.0 - 800.0 * math.cos(k), 350.0 - 800.0 * math.sin(k))
        psf = focal_plane_psf(galsim.Moffat(beta=3.5, fwhm=0.9), boresight, 1000.0, 0.05, 0.01)
        exposures.append(Exposure(image=np.zeros((700, 700)), wcs=wcs, variance=1.0, psf=psf,
                                  visit=k, detector=1, band="r", zero_point=30.0))  # fmt: skip
    config = BuildConfig(n_noise=1, psf_size=51, psf_corners=True, psf_phase=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        serial = build_patch(patch, exposures, config, progress=False)
        pooled = build_patch(patch, exposures, config, progress=False, workers=2)
        indices = sorted(serial.cells)
        part = build_patch(patch, exposures, config, progress=False, cells=indices[::2])
    assert sum(cell.n_used == 3 for cell in serial.cells.values()) >= 4
    for index, cell in serial.cells.items():
        assert cell.equals(pooled[index]), index
    for index in indices[::2]:
        assert part[index].equals(serial[index]), index
