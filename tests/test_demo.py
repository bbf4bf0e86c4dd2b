"""The demo runs end to end and writes every file it promises; field edges reject inputs."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from cellcoadd import BuildConfig, build_patch
from cellcoadd.builder.mapping import footprint_box, map_box
from cellcoadd.cli.main import cli
from cellcoadd.geometry import Box
from cellcoadd.sim import DEMO_PATCH, FieldConfig, SimConfig, demo_skymap, simulate_field

PNG = b"\x89PNG\r\n\x1a\n"


def test_demo_command_writes_everything(tmp_path):
    out = tmp_path / "demo"
    result = CliRunner().invoke(
        cli, ["demo", "--out", str(out), "--visits", "3", "--workers", "1", "--quiet"]
    )
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert {
        "coadd.fits",
        "coadd.h5",
        "truth.fits",
        "truth_trimmed.fits",
        "skymap.json",
        "report.txt",
        "layout.png",
        "stitched.png",
        "cell.png",
        "inputs.png",
    } <= names
    # the bulky exposures stay in memory unless --keep-exposures
    assert not any("-det" in name for name in names) and "exposures" not in names
    assert all(p.is_file() for p in out.iterdir())  # nothing in sub-folders
    assert "--keep-exposures writes them" in result.output
    for png in ("layout.png", "stitched.png", "cell.png", "inputs.png"):
        assert (out / png).read_bytes()[:8] == PNG
    assert "each kept by exactly one cell" in result.output
    assert "identical to the built cell" in result.output


@pytest.fixture(scope="module")
def field():
    skymap = demo_skymap()
    config = SimConfig(field=FieldConfig(ccd_nx=500, ccd_ny=500))
    sim = simulate_field(config, skymap, 0, DEMO_PATCH, 4, seed=3)
    patch = skymap[0].patch(*DEMO_PATCH)
    coadd = build_patch(patch, sim.exposures, BuildConfig(n_noise=1), seed=3, progress=False)
    return sim, patch, coadd


def test_field_edges_reject_inputs_for_some_cells_only(field):
    sim, patch, coadd = field
    status = {}
    for index, cell in coadd.cells.items():
        for record in cell.inputs:
            status.setdefault(record.key, {})[index] = record.status
    both = [key for key, by_cell in status.items() if {"edge", "used"} <= set(by_cell.values())]
    assert both, "no exposure is used for one cell and rejected as edge for another"


def test_used_inputs_fully_cover_their_cells(field):
    sim, patch, coadd = field
    exposures = {e.key: e for e in sim.exposures}
    cells = {c.index: c for c in patch.cells}
    checked = 0
    for index, cell_coadd in coadd.cells.items():
        cell = cells[index]
        for record in cell_coadd.inputs:
            exposure = exposures[record.key]
            mapping = map_box(cell.wcs, Box.from_shape(cell.outer_bbox.shape), exposure.wcs)
            covered = exposure.valid_box.contains_box(footprint_box(mapping))
            assert covered == (record.status not in ("edge", "no_overlap")), (index, record)
            checked += record.status == "used"
    assert checked > 20


def test_stitched_field_has_no_gaps_where_cells_have_inputs(field):
    _, _, coadd = field
    image = coadd.stitch("image")
    for index in coadd.inner_cell_indices:
        if not coadd.cells[index].is_empty:
            view = coadd.cells[index].inner.image
            assert np.isfinite(view).all()
    assert np.isfinite(image).mean() > 0.5
