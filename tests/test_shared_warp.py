"""Each exposure mapped once per patch and warped once per block of cells.

A tract pixel gets the same contribution from an exposure whichever cell, block or process
builds it: overlapping cells that accepted the same inputs hold identical pixels, and a
patch is the same however its cells are grouped.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from exposure_factory import make_exposure

from cellcoadd import BuildConfig, MaskBits, SkyMap, SkyMapConfig, build_patch
from cellcoadd.builder.cell import CellBlock, build_cells
from cellcoadd.builder.exposure_frame import ExposureFrame, exposure_frame, projected_valid_box
from cellcoadd.builder.inputs import BuildInput, BuildSettings, prepare
from cellcoadd.builder.mapping import map_box
from cellcoadd.geometry.box import Box

CONFIG = SkyMapConfig(cell_inner=30, cell_border=12, cells_per_patch=4, patches_per_tract=1)
BUILD = BuildConfig(n_noise=2, psf_size=21, units="count", zero_point=30.0)
VARIANTS = [
    dict(pixel_scale=0.26, rotation_deg=0.0, offset=(0.3, -0.2)),
    dict(pixel_scale=0.2, rotation_deg=33.0, offset=(-0.4, 0.1), shape=(150, 170)),
    dict(pixel_scale=0.24, rotation_deg=-71.0, offset=(0.1, 0.45), shape=(120, 200)),
    dict(pixel_scale=0.26, rotation_deg=12.0, offset=(0.25, 0.25), shear=0.02, sip=True),
]
BITS = MaskBits(bits={"BAD": 0, "CR": 1, "SAT": 2, "NO_DATA": 3, "EDGE": 4})


@pytest.fixture(scope="module")
def patch():
    return SkyMap.from_centers([(30.0, -10.0)], CONFIG)[0].patch(0, 0)


@pytest.fixture(scope="module")
def exposures(patch):
    """Four exposures, some not covering every cell, with bad columns and cosmic rays."""
    ra, dec = patch.tract.pixel_to_sky([60.0], [60.0])
    out = []
    for visit, variant in enumerate(VARIANTS):
        variant = {"shape": (280, 280), **variant}
        exposure = make_exposure(
            (float(ra[0]) + 0.0004 * visit, float(dec[0])),
            visit=visit,
            noise_sigma=1.0,
            sky=3.0,
            seed=visit,
            **variant,
        )
        mask = np.zeros(exposure.image.shape, dtype=np.int32)
        mask[:, 70 + 20 * visit] = 1  # a bad column
        mask[60 + visit, 100:102] = 2  # a cosmic ray
        out.append(dataclasses.replace(exposure, mask=mask, mask_bits=BITS))
    return out


@pytest.fixture(scope="module")
def serial(patch, exposures):
    return build_patch(patch, exposures, BUILD, seed=4, progress=False)


def _used(cell):
    return [(r.visit, r.detector) for r in cell.inputs if r.status == "used"]


def test_overlapping_cells_with_the_same_inputs_hold_the_same_pixels(serial):
    compared = partial_inputs = 0
    for a, b in itertools.combinations(serial.cells.values(), 2):
        common = (
            a.outer_bbox.intersection(b.outer_bbox) if a.outer_bbox.overlaps(b.outer_bbox) else None
        )
        if common is None or not _used(a):
            continue
        if _used(a) != _used(b):
            continue
        ra, rb = common.slices_in(a.outer_bbox), common.slices_in(b.outer_bbox)
        for name in ("image", "variance", "mfrac", "mask"):
            assert np.array_equal(getattr(a, name)[ra], getattr(b, name)[rb]), (a.index, b.index)
        assert np.array_equal(a.noise[:, ra[0], ra[1]], b.noise[:, rb[0], rb[1]])
        compared += 1
        partial_inputs += len(_used(a)) < len(VARIANTS)
    assert compared >= 40
    assert partial_inputs > 0  # pairs where some exposure was rejected for both
    statuses = {r.status for cell in serial.cells.values() for r in cell.inputs}
    assert {"used", "edge"} <= statuses
    assert max(cell.mfrac.max() for cell in serial.cells.values()) > 0  # bad pixels warped


def test_a_patch_is_the_same_however_its_cells_are_grouped(patch, exposures, serial):
    area = patch.outer_bbox
    frames = [exposure_frame(patch.tract.wcs, area, e, BUILD.mapping_tolerance) for e in exposures]
    mask_bits = serial.metadata.mask_bits
    cells = patch.cells
    for grouping in ([[c] for c in cells], [cells[::2], cells[1::2]], [cells[:7], cells[7:]]):
        for group in grouping:
            built = build_cells(
                group, exposures, BUILD, seed=4, mask_bits=mask_bits, area=area, frames=frames
            )
            for cell in built:
                assert cell.equals(serial.cells[cell.index]), cell.index
    pooled = build_patch(patch, exposures, BUILD, seed=4, progress=False, workers=2)
    for index, cell in serial.cells.items():
        assert cell.equals(pooled.cells[index]), index


def test_a_cell_built_alone_agrees_with_its_patch(patch, exposures, serial):
    """Mapped over its own box instead of the patch, a cell differs by the mapping's
    tolerance only."""
    cell = patch.tract.cell(1, 1)
    alone = build_cells([cell], exposures, BUILD, seed=4, mask_bits=serial.metadata.mask_bits)[0]
    in_patch = serial.cells[cell.index]
    assert _used(alone) == _used(in_patch)
    scale = float(np.abs(in_patch.image).max())
    np.testing.assert_allclose(alone.image, in_patch.image, rtol=0, atol=1e-4 * scale)
    np.testing.assert_allclose(alone.noise, in_patch.noise, rtol=0, atol=1e-3)


def test_the_shared_mapping_is_the_exact_mapping_within_tolerance(patch, exposures):
    exposure = exposures[3]  # SIP, sheared
    frame = exposure_frame(patch.tract.wcs, patch.outer_bbox, exposure, 1e-3)
    assert frame.mapping is not None and not frame.serves_nothing
    box = Box(x_start=20, x_stop=57, y_start=31, y_stop=70)
    part = frame.mapping.restricted(box)
    exact = map_box(patch.tract.wcs, box, exposure.wcs, tolerance=1e-9, grid_step=1)
    assert np.hypot(part.x - exact.x, part.y - exact.y).max() < 1e-3
    # a sub-box holds exactly the values of the box around it
    inner = Box(x_start=23, x_stop=40, y_start=33, y_stop=41)
    rows, cols = inner.slices_in(box)
    assert np.array_equal(frame.mapping.restricted(inner).x, part.x[rows, cols])


def test_the_projected_valid_box_holds_every_valid_pixel(patch, exposures):
    for exposure in exposures:
        region = projected_valid_box(patch.tract.wcs, exposure)
        ny, nx = exposure.shape
        yy, xx = np.mgrid[0:ny:7, 0:nx:7]
        ra, dec = exposure.wcs.all_pix2world(xx.ravel(), yy.ravel(), 0)
        tx, ty = patch.tract.wcs.all_world2pix(ra, dec, 0)
        assert region.contains(tx, ty).all()


def test_an_exposure_serving_none_of_the_area_is_left_out(patch, exposures):
    far = make_exposure((210.0, 10.0), visit=9)
    frame = exposure_frame(patch.tract.wcs, patch.outer_bbox, far, 1e-3)
    assert frame.serves_nothing
    settings = BuildSettings(BUILD, 0, BITS, "r", patch.outer_bbox, record_distant=False)
    block = CellBlock(patch.cells[:2], settings)
    block.add(BuildInput.of(far), frame)
    assert all(not records for records in block.records)


def test_block_sums_equal_each_cell_summing_alone():
    """Followers share one array until an input misses them; every cell ends with exactly
    the sums of adding its own inputs in order."""
    from cellcoadd.builder.cell_sums import BlockSums

    rng = np.random.default_rng(3)
    boxes = [
        Box.from_shape((9, 11), x_start=7 * i, y_start=5 * j) for j in range(3) for i in range(3)
    ]
    block = BlockSums(boxes, n_noise=1, psf_size=3)
    naive = [np.zeros((4, *b.shape)) for b in boxes]
    naive_mask = [np.zeros(b.shape, dtype=np.int32) for b in boxes]
    for _ in range(12):
        contributions = []
        chosen = [i for i in range(len(boxes)) if rng.random() < 0.7]
        split = int(rng.integers(0, len(chosen) + 1))
        groups = [chosen[:split], *[[i] for i in chosen[split:]]]  # one shared, some alone
        for cells in filter(None, groups):
            box = Box.enclosing(boxes[i] for i in cells).grow(int(rng.integers(0, 2)))
            n_planes = int(rng.choice([3, 4]))  # with or without the masked fraction
            planes = rng.normal(size=(n_planes, *box.shape)) * 10.0 ** rng.uniform(-8, 8)
            mask = rng.integers(0, 4, box.shape).astype(np.int32)
            contributions.append((box, planes, mask, cells))
            for i in cells:
                rows, cols = boxes[i].slices_in(box)
                naive[i][:n_planes] += planes[:, rows, cols]
                naive_mask[i] |= mask[rows, cols]
        block.add(contributions)
    assert any(own is None for own in block.own) and any(own is not None for own in block.own)
    for i in range(len(boxes)):
        sums = block.cell(i)
        assert np.array_equal(sums.planes, naive[i]), i
        assert np.array_equal(sums.mask, naive_mask[i]), i


def test_frames_hold_only_their_grid_nodes_and_share_interpolation_weights(patch, exposures):
    # every exposure mapped over a patch is held until the patch is built: hundreds of them
    grids: dict = {}
    frames = [
        exposure_frame(patch.tract.wcs, patch.outer_bbox, exposure, 1e-3, grids)
        for exposure in exposures
    ]
    for frame in frames:
        assert frame.mapping is not None
        for name in ("x", "y", "area_ratio"):
            deferred = frame.mapping.__dict__["_" + name]
            # the node values alone, in an array of their own (not a view keeping the dense
            # grid of check points, or the offset positions of the area ratio, alive)
            n_rows = int(deferred.rows.first.max()) + 4
            n_cols = int(deferred.cols.first.max()) + 4
            assert deferred.nodes.shape == (n_rows, n_cols)
            assert deferred.nodes.base is None
    same_region = [(a, b) for a, b in itertools.combinations(frames, 2) if a.region == b.region]
    assert same_region
    for a, b in same_region:
        assert a.mapping.__dict__["_x"].rows.weights is b.mapping.__dict__["_y"].rows.weights
    # and sharing changes no value
    for frame, exposure in zip(frames, exposures, strict=True):
        alone = exposure_frame(patch.tract.wcs, patch.outer_bbox, exposure, 1e-3)
        for name in ("x", "y", "area_ratio"):
            assert np.array_equal(getattr(alone.mapping, name), getattr(frame.mapping, name))


def test_cells_mapping_themselves_take_the_same_warp(patch, exposures, serial):
    """Without a shared mapping (as for an exposure partly off its projection) each cell
    maps itself and goes through the same warp, PSF and records: the same inputs are used
    and the pixels agree within the mapping's tolerance."""
    area = patch.outer_bbox
    no_shared = [ExposureFrame(area, None) for _ in exposures]
    mask_bits = serial.metadata.mask_bits
    cells = patch.cells[:6]
    built = build_cells(
        cells, exposures, BUILD, seed=4, mask_bits=mask_bits, area=area, frames=no_shared
    )
    compared = 0
    for cell in built:
        in_patch = serial.cells[cell.index]
        assert _used(cell) == _used(in_patch)
        if not _used(cell):
            continue
        compared += 1
        scale = float(np.abs(in_patch.image).max())
        np.testing.assert_allclose(cell.image, in_patch.image, rtol=0, atol=1e-4 * scale)
        np.testing.assert_allclose(cell.noise, in_patch.noise, rtol=0, atol=1e-3)
        np.testing.assert_allclose(cell.psf, in_patch.psf, rtol=0, atol=1e-6)
        assert np.array_equal(cell.mask, in_patch.mask)
    assert compared >= 3


def test_an_input_in_memory_is_its_own_source(exposures):
    exposure = exposures[1]
    item = BuildInput.of(exposure)
    assert item.source is None and item.header is exposure and item.key == exposure.key
    loaded, origin = item.load(Box(x_start=10, x_stop=20, y_start=5, y_stop=9))
    assert loaded is exposure and origin == (0, 0)  # whole: positions need no shift
    assert BuildInput.of(item) is item


def test_the_candidates_of_a_cell_hold_every_input_it_records(patch, exposures, serial):
    """A patch build sends a block only the inputs its frames put near one of its cells:
    every input a cell records (used or rejected) is among them, a far one is not."""
    far = dataclasses.replace(make_exposure((210.0, 10.0), visit=9), mask_bits=BITS)
    build = prepare(
        patch.cells,
        [*exposures, far],
        BUILD,
        4,
        one_band=True,
        area=patch.outer_bbox,
        record_distant=False,
    )
    keys = [item.key for item in build.inputs]
    served = 0
    for cell in patch.cells:
        candidates = {keys[k] for k in build.candidates([cell])}
        recorded = {(r.visit, r.detector) for r in serial.cells[cell.index].inputs}
        assert recorded <= candidates, cell.index
        assert far.key not in candidates
        served += bool(recorded)
    assert served == len(patch.cells)
    assert build.candidates(patch.cells) == list(range(len(exposures)))
