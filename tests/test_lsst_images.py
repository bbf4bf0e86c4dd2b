"""Conversion to and from lsst-images (the ``lsst`` extra, Python >= 3.12).

Skipped with a message where lsst-images cannot be imported; with ``CI`` set, a missing
lsst-images on Python >= 3.12 fails instead (``make test-lsst`` runs this file there).
"""

from __future__ import annotations

import os
import sys

import astropy.units as u
import numpy as np
import pytest
from coadd_factory import make_patch

try:
    import lsst.images
    import lsst.images.cells
except ImportError as err:
    if os.environ.get("CI") and sys.version_info >= (3, 12):
        raise ImportError(f"CI must run the lsst-images tests, but it is missing: {err}") from err
    pytest.skip(
        "lsst-images is not importable (needs Python >= 3.12 and the 'lsst' extra; "
        "`make test-lsst` runs these tests in .venv-lsst)",
        allow_module_level=True,
    )

import cellcoadd
from cellcoadd.errors import CellCoaddFormatError, InvalidCoaddError
from cellcoadd.io.foreign.lsst_images import from_lsst_images, to_lsst_images
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata

PLANES = ("image", "mask", "variance", "mfrac")


def counts_patch(patch: PatchCoadd, zero_point: float = 30.0) -> PatchCoadd:
    dump = patch.metadata.model_dump()
    dump.update(units="count", zero_point=zero_point)
    dump["build_config"].update(units="count", zero_point=zero_point)
    return PatchCoadd(PatchMetadata.model_validate(dump), patch.cells)


@pytest.fixture(scope="module")
def patch() -> PatchCoadd:
    # arbitrary float bits (NaN payloads, -0.0), an empty and a missing inner cell
    return make_patch(seed=3, empty=((2, 3),), missing=((3, 3),))


def assert_stitched_equal(read: PatchCoadd, expected: PatchCoadd) -> None:
    for plane in PLANES:
        assert read.stitch(plane).tobytes() == expected.stitch(plane).tobytes(), plane
    for k in range(expected.metadata.n_noise):
        assert read.stitch("noise", k).tobytes() == expected.stitch("noise", k).tobytes()


def test_public_exports() -> None:
    assert cellcoadd.to_lsst_images is to_lsst_images
    assert cellcoadd.from_lsst_images is from_lsst_images


@pytest.mark.parametrize("counts", [False, True], ids=["nJy", "count"])
def test_per_cell_round_trip_is_exact(patch: PatchCoadd, counts: bool) -> None:
    patch = counts_patch(patch) if counts else patch
    coadds = to_lsst_images(patch, mode="per_cell")
    assert set(coadds) == set(patch.cells)
    cell = patch[2, 2]
    one = coadds[2, 2]
    assert isinstance(one, lsst.images.cells.CellCoadd)
    assert str(one.unit) == ("ct" if counts else "nJy")
    assert one.bbox.x.start == cell.outer_bbox.x_start and one.bbox.y.stop == cell.outer_bbox.y_stop
    # Rubin's plane names at our bit numbers: SAT is SATURATED, CR COSMIC_RAY, ...
    rubin = {"SAT": "SATURATED", "CR": "COSMIC_RAY", "INTRP": "INTERPOLATED"}
    rubin["EDGE"] = "SENSOR_EDGE"
    bits = patch.metadata.mask_bits.bits
    assert set(one.mask.schema.names) == {rubin.get(name, name) for name in bits}
    for name, bit in bits.items():
        assert one.mask.schema.bit(rubin.get(name, name)) == one.mask.schema.bit(
            one.mask.schema[bit].name
        )
        assert np.array_equal(one.mask.get(rubin.get(name, name)), (cell.mask >> bit) & 1 != 0)
    assert one.mask.schema.descriptions["NO_DATA"]
    assert one.mask.get("SATURATED").shape == cell.mask.shape
    assert len(one.noise_realizations) == patch.metadata.n_noise
    used = [r for r in cell.inputs if r.is_used]
    contributions = one.provenance.contributions
    assert sorted(contributions["visit"]) == sorted(r.visit for r in used)
    weights = {int(row["visit"]): float(row["weight"]) for row in contributions}
    assert weights == {r.visit: r.weight for r in used}
    back = from_lsst_images(coadds)
    assert back.metadata == patch.metadata
    assert list(back.cells) == list(patch.cells)
    for index, expected in patch.cells.items():
        assert back[index].equals(expected), index  # pixels, noise, mask, mfrac, PSF, inputs


def test_stitched_equals_patch_stitch(patch: PatchCoadd) -> None:
    coadd = to_lsst_images(patch)
    assert isinstance(coadd, lsst.images.cells.CellCoadd)
    box = patch.patch_inner_bbox
    assert (coadd.bbox.x.start, coadd.bbox.y.start) == (box.x_start, box.y_start)
    assert np.array_equal(coadd.image.array.view(np.uint32), patch.stitch("image").view(np.uint32))
    mfrac = coadd.mask_fractions["mfrac"].array
    assert mfrac.tobytes() == patch.stitch("mfrac").tobytes()
    no_data = coadd.mask.get("NO_DATA")
    assert np.array_equal(no_data, patch.stitch("mask") & 16 != 0)
    # the empty and the missing inner cells are marked missing, the others have a PSF
    assert len(coadd.psf.bounds.missing) == 2
    present = [i for i in patch.inner_cell_indices if i in patch and not patch[i].is_empty]
    grid = coadd.psf.bounds.grid
    side = patch.metadata.cell_inner
    for index in present:
        ij = lsst.images.cells.CellIJ(
            i=(index[1] * side - grid.bbox.y.start) // side,
            j=(index[0] * side - grid.bbox.x.start) // side,
        )
        assert np.array_equal(coadd.psf[ij].array, patch[index].psf)
    back = from_lsst_images(coadd)
    assert_stitched_equal(back, patch)
    assert back.metadata == patch.metadata
    assert (2, 3) in back and back[2, 3].is_empty and (3, 3) not in back
    for index in present:
        pairs = zip(back[index].inputs, patch[index].inputs, strict=True)
        assert all(a.identical(b) for a, b in pairs)
        assert np.isnan(back[index].image[0, 0])  # the border is not kept


@pytest.mark.parametrize("suffix", [".fits", ".sdf"])
@pytest.mark.parametrize("mode", ["stitched", "per_cell"])
def test_lsst_images_files(patch: PatchCoadd, tmp_path, suffix: str, mode: str) -> None:
    patch = counts_patch(patch) if suffix == ".sdf" else patch
    out = to_lsst_images(patch, mode=mode)
    coadd = out if mode == "stitched" else out[2, 2]
    path = tmp_path / f"coadd{suffix}"
    coadd.write(str(path))  # lsst-images' own writer
    read = lsst.images.cells.CellCoadd.read(str(path))  # and its own reader
    assert read.unit == coadd.unit
    for back in (from_lsst_images(read), from_lsst_images(path)):
        assert back.metadata == patch.metadata
        if mode == "per_cell":
            assert back[2, 2].equals(patch[2, 2])
        else:
            assert_stitched_equal(back, patch)


def test_suffixes_are_not_mixed(patch: PatchCoadd, tmp_path) -> None:
    ours = tmp_path / "ours.fits"
    cellcoadd.write(patch, ours)
    with pytest.raises(CellCoaddFormatError, match="cellcoadd.read"):
        from_lsst_images(ours)
    with pytest.raises(CellCoaddFormatError, match="Starlink NDF"):
        from_lsst_images(tmp_path / "coadd.h5")
    theirs = tmp_path / "theirs.fits"
    to_lsst_images(patch).write(str(theirs))
    with pytest.raises(CellCoaddFormatError):
        cellcoadd.read(theirs)


def test_refusals(patch: PatchCoadd) -> None:
    with pytest.raises(ValueError, match="mode"):
        to_lsst_images(patch, mode="tiles")  # type: ignore[arg-type]
    coadd = to_lsst_images(patch)
    del coadd.metadata["cellcoadd.format"]
    with pytest.raises(InvalidCoaddError, match="no cellcoadd metadata.*sky map 'cellcoadd'"):
        from_lsst_images(coadd)
    other = make_patch(seed=4, patch=(0, 1))
    mixed = {**to_lsst_images(patch, "per_cell"), (9, 9): to_lsst_images(other, "per_cell")[0, 3]}
    with pytest.raises(InvalidCoaddError, match="different patches"):
        from_lsst_images(mixed)


def test_lsst_images_command_line_reads_our_export(patch: PatchCoadd, tmp_path) -> None:
    """lsst-images' own command line (it needs lsst-daf-butler, in the ``lsst`` extra)."""
    from click.testing import CliRunner
    from lsst.images.cli import main

    path = tmp_path / "coadd.fits"
    to_lsst_images(patch).write(str(path))
    result = CliRunner().invoke(main, ["inspect", str(path)])
    assert result.exit_code == 0, result.output
    assert "schema name:    cell_coadd" in result.output, result.output
    described = CliRunner().invoke(main, ["describe", str(path)])
    assert described.exit_code == 0, described.output
    assert "SATURATED" in described.output and "COSMIC_RAY" in described.output


# ---------------------------------------------------------------------- coadds made by Rubin
#
# A stitched coadd as Rubin's pipelines hand it out through lsst-images: on lsst_cells_v1,
# tract 5063, patch (4, 3) (Rubin's patch id 34), with the patch's cell grid, Rubin's
# (legacy) mask planes, a provenance, aperture corrections and no cellcoadd metadata. It
# covers 2 x 2 inner cells; cell (81, 61) has no PSF (missing).

RUBIN_TRACT, RUBIN_PATCH = 5063, (4, 3)
RUBIN_CELLS = [(80, 60), (81, 60), (80, 61), (81, 61)]
RUBIN_MISSING = (81, 61)
RUBIN_PSF = 7


def rubin_coadd(skymap_name: str = "lsst_cells_v1", tract: int = RUBIN_TRACT):
    from cellcoadd.geometry import SkyMap

    images = lsst.images
    cells = lsst.images.cells
    rng = np.random.default_rng(11)
    lsst_map = SkyMap.named("lsst_cells_v1")
    side = 150
    grid_box = images.Box.factory[
        (60 - 1) * side : (80 + 1) * side, (80 - 1) * side : (100 + 1) * side
    ]
    grid = cells.CellGrid(bbox=grid_box, cell_shape=images.YX(y=side, x=side))
    bbox = images.Box.factory[60 * side : 62 * side, 80 * side : 82 * side]
    missing = cells.CellIJ(i=RUBIN_MISSING[1] - 59, j=RUBIN_MISSING[0] - 79)
    bounds = cells.CellGridBounds(grid=grid, bbox=bbox, missing=frozenset({missing}))
    psf = rng.uniform(size=(2, 2, RUBIN_PSF, RUBIN_PSF))
    psf /= psf.sum(axis=(2, 3), keepdims=True)
    psf[1, 1] = np.nan
    planes = list(lsst.images.get_legacy_non_cell_coadd_mask_planes().values())
    schema = images.MaskSchema(planes)
    mask = images.Mask(0, schema=schema, bbox=bbox)
    for plane in ("DETECTION_EDGE", "SENSOR_EDGE", "DETECTED", "INTERPOLATED"):
        mask.set(plane, rng.uniform(size=(2 * side, 2 * side)) < 0.1)
    image = rng.standard_normal((2 * side, 2 * side)).astype(np.float32)
    tract_box = images.Box.factory[0:30000, 0:30000]
    frame = images.TractFrame(skymap=skymap_name, tract=tract, bbox=tract_box)
    projection = images.SkyProjection.from_fits_wcs(
        lsst_map[tract].wcs, frame, pixel_bounds=tract_box
    )
    provenance_type = cells.CoaddProvenance
    inputs = provenance_type.make_empty_input_table(2)
    for n, (visit, detector) in enumerate([(2025111500123, 94), (2025111600042, 11)]):
        inputs["instrument"][n] = "LSSTCam"
        inputs["visit"][n] = visit
        inputs["detector"][n] = detector
        inputs["physical_filter"][n] = "r_57"
        inputs["day_obs"][n] = 20251115 + n
        inputs["polygon"][n] = images.Polygon.from_box(bbox)
    contributions = provenance_type.make_empty_contribution_table(3)
    rows = [((0, 0), 2025111500123, 94, 0.75), ((0, 1), 2025111600042, 11, 1.25)]
    rows.append(((1, 0), 2025111500123, 94, 0.5))
    for n, ((i, j), visit, detector, weight) in enumerate(rows):
        contributions["cell_i"][n] = 1 + i  # on the grid, which starts at cell (79, 59)
        contributions["cell_j"][n] = 1 + j
        contributions["instrument"][n] = "LSSTCam"
        contributions["visit"][n] = visit
        contributions["detector"][n] = detector
        contributions["overlaps_center"][n] = True
        contributions["overlap_fraction"][n] = 1.0
        contributions["unmasked_fraction"][n] = 1.0
        contributions["weight"][n] = weight
        contributions["psf_shape_xx"][n] = 3.0
        contributions["psf_shape_yy"][n] = 2.0
        contributions["psf_shape_xy"][n] = 0.25
        contributions["psf_shape_flag"][n] = False
    apcorr = np.array([[0.98, 0.99], [1.01, np.nan]])
    coadd = cells.CellCoadd(
        images.Image(image, bbox=bbox, unit=u.nJy),
        mask=mask,
        variance=images.Image(np.full_like(image, 4.0), bbox=bbox, unit=u.nJy**2),
        noise_realizations=[images.Image(image[::-1].copy(), bbox=bbox, unit=u.nJy)],
        sky_projection=projection,
        band="r",
        psf=cells.CellPointSpreadFunction(psf, bounds),
        patch=cells.PatchDefinition(
            id=34,
            index=images.YX(y=3, x=4),
            inner_bbox=images.Box.factory[9000:12000, 12000:15000],
            cells=grid,
        ),
        provenance=provenance_type(inputs=inputs, contributions=contributions),
        aperture_corrections={"base_PsfFlux_instFlux": cells.CellField(bounds, apcorr)},
    )
    return coadd, {"image": image, "psf": psf, "mask": mask, "apcorr": apcorr}


def test_a_coadd_made_by_rubin_is_imported(tmp_path) -> None:
    from cellcoadd.geometry import SkyMap

    coadd, made = rubin_coadd()
    lsst_map = SkyMap.named("lsst_cells_v1")
    for patch in (from_lsst_images(coadd), from_lsst_images(_written(coadd, tmp_path))):
        meta = patch.metadata
        assert meta.skymap_config == lsst_map.config and meta.skymap_config.name == "lsst_cells_v1"
        assert (meta.tract, meta.patch) == (RUBIN_TRACT, RUBIN_PATCH)
        assert meta.tract_center == lsst_map[RUBIN_TRACT].center
        assert meta.geometry.rubin_id == 34
        assert (meta.units, meta.n_noise, meta.psf_size, meta.band) == ("nJy", 1, RUBIN_PSF, "r")
        assert meta.software_version.startswith("unknown")
        # Rubin's planes under our names: SENSOR_EDGE is ours EDGE... unless Rubin's
        # DETECTION_EDGE is there too: then it is Rubin's EDGE, SENSOR_EDGE kept
        bits = meta.mask_bits.bits
        assert {"EDGE", "SENSOR_EDGE", "INTRP", "CR", "SAT", "DETECTED", "NO_DATA"} <= set(bits)
        assert sorted(patch) == sorted(set(RUBIN_CELLS) - {RUBIN_MISSING})
        for cx, cy in patch:
            cell = patch[cx, cy]
            rows = slice((cy - 60) * 150, (cy - 59) * 150)
            cols = slice((cx - 80) * 150, (cx - 79) * 150)
            inner_rows, inner_cols = cell.inner_bbox.slices_in(cell.outer_bbox)
            assert np.array_equal(cell.image[inner_rows, inner_cols], made["image"][rows, cols])
            assert np.isnan(cell.image[0, 0]) and np.isnan(cell.mfrac).all()  # unknown
            assert np.array_equal(cell.psf, made["psf"][cy - 60, cx - 80])
            detection = made["mask"].get("DETECTION_EDGE")[rows, cols]
            ours = cell.mask[inner_rows, inner_cols] & meta.mask_bits.value("EDGE") != 0
            assert np.array_equal(ours, detection)
        assert [(r.visit, r.detector, r.weight) for r in patch[80, 60].inputs] == [
            (2025111500123, 94, 0.75)
        ]
        record = patch[81, 60].inputs[0]
        assert record.psf_T == pytest.approx(5.0 * 0.04) and np.isnan(record.zero_point)
        assert meta.observations is not None and meta.observations.instrument == "LSSTCam"
        assert [v.day_obs for v in meta.observations.visits] == [20251115, 20251116]
        corrections = meta.aperture_corrections
        assert corrections is not None and corrections.algorithms == ("base_PsfFlux_instFlux",)
        assert corrections.of((80, 61)) == {"base_PsfFlux_instFlux": 1.01}
    # exported again: lsst-images' names, Rubin's EDGE as DETECTION_EDGE (not EDGE)
    back = to_lsst_images(patch)
    names = set(back.mask.schema.names)
    assert {"DETECTION_EDGE", "SENSOR_EDGE", "INTERPOLATED", "COSMIC_RAY"} <= names
    assert "EDGE" not in names and "INTRP" not in names
    assert back.aperture_corrections["base_PsfFlux_instFlux"].value_in_cell(
        lsst.images.cells.CellIJ(i=61 - 59, j=80 - 79)
    ) == pytest.approx(1.01)
    assert from_lsst_images(back).metadata == patch.metadata


def _written(coadd, tmp_path):
    path = tmp_path / "rubin.fits"
    coadd.write(str(path))
    return path


def test_a_rubin_coadd_needs_a_known_sky_map_that_agrees() -> None:
    coadd, _ = rubin_coadd(skymap_name="hsc_rings_v1")
    with pytest.raises(InvalidCoaddError, match="'hsc_rings_v1'.*DC2_cells_v1, lsst"):
        from_lsst_images(coadd)
    coadd, _ = rubin_coadd(tract=RUBIN_TRACT + 1)  # the frame says 5064, the WCS is 5064's
    with pytest.raises(InvalidCoaddError, match="patch id 34 is patch|disagrees"):
        from_lsst_images(_relabelled(coadd, RUBIN_TRACT))


def _relabelled(coadd, tract: int):
    """``coadd`` with its frame's tract changed (its WCS kept)."""
    images = lsst.images
    frame = images.TractFrame(
        skymap="lsst_cells_v1", tract=tract, bbox=coadd.sky_projection.pixel_bounds
    )
    wcs = coadd.sky_projection.as_fits_wcs(coadd.sky_projection.pixel_bounds)
    projection = images.SkyProjection.from_fits_wcs(wcs, frame, pixel_bounds=frame.bbox)
    return lsst.images.cells.CellCoadd(
        coadd.image,
        mask=coadd.mask,
        variance=coadd.variance,
        noise_realizations=list(coadd.noise_realizations),
        sky_projection=projection,
        band=coadd.band,
        psf=coadd.psf,
        patch=coadd.patch,
        provenance=coadd.provenance,
    )


def test_cell_edges_on_request(patch: PatchCoadd) -> None:
    from cellcoadd.model.stitched import cell_edge_mask

    coadd = to_lsst_images(patch, cell_edges=2)
    edges = coadd.mask.get("CELL_EDGE")
    side = patch.metadata.cell_inner
    box = patch.patch_inner_bbox
    assert edges.shape == box.shape
    offset_x = (np.arange(box.x_start, box.x_stop) % side)[np.newaxis, :]
    offset_y = (np.arange(box.y_start, box.y_stop) % side)[:, np.newaxis]
    expected = (offset_x < 2) | (offset_x >= side - 2) | (offset_y < 2) | (offset_y >= side - 2)
    assert np.array_equal(edges, expected)
    assert np.array_equal(cell_edge_mask(patch, width=2), expected)
    back = from_lsst_images(coadd)  # the plane is dropped again
    assert_stitched_equal(back, patch)
    assert "CELL_EDGE" not in back.metadata.mask_bits.bits
    assert "CELL_EDGE" not in to_lsst_images(patch).mask.schema.names
    with pytest.raises(ValueError, match="cell_edges applies to mode='stitched'"):
        to_lsst_images(patch, mode="per_cell", cell_edges=1)
