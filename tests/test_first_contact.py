"""What a new user meets first: defaults that give a useful coadd, warnings when they do
not, one vocabulary for inputs, readable ``show`` lines, figures with units and axes."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from cellcoadd import BuildConfig, build_patch
from cellcoadd.cli.inspect import input_lines
from cellcoadd.cli.main import cli
from cellcoadd.cli.shear import parse_snr, precision_advice
from cellcoadd.pipelines.coverage import count_inputs, coverage_warning
from cellcoadd.sim import DEMO_PATCH, FieldConfig, SimConfig, demo_skymap, simulate_field


def _coadd(ccd_pixels: int, visits: int, seed: int):
    skymap = demo_skymap()
    config = SimConfig(field=FieldConfig(ccd_nx=ccd_pixels, ccd_ny=ccd_pixels))
    sim = simulate_field(config, skymap, 0, DEMO_PATCH, visits, seed=seed)
    patch = skymap[0].patch(*DEMO_PATCH)
    return build_patch(patch, sim.exposures, BuildConfig(n_noise=1), seed=seed, progress=False)


@pytest.fixture(scope="module")
def default_coadd():
    """The tutorial's command-line sequence: `cellcoadd simulate` defaults, 10 visits."""
    return _coadd(FieldConfig().ccd_nx, visits=10, seed=0)


@pytest.fixture(scope="module")
def small_ccd_coadd():
    return _coadd(200, visits=3, seed=5)  # CCDs of 54", one cell outer box: visits lost


def test_default_ccds_give_a_useful_coadd_without_warning(default_coadd):
    counts = count_inputs(default_coadd)
    assert counts.n_empty == 0
    assert counts.visits_used_per_cell.min() >= 1
    inner = [
        len({r.visit for r in default_coadd.cells[i].inputs if r.status == "used"})
        for i in default_coadd.inner_cell_indices
    ]
    assert np.median(inner) >= 6  # of 10 visits (400-pixel CCDs gave 1)
    assert coverage_warning(default_coadd) is None


def test_small_ccds_warn_with_the_likely_cause(small_ccd_coadd):
    message = coverage_warning(small_ccd_coadd)
    assert message is not None
    assert "CCDs small compared with cells" in message
    assert "cells are empty" in message and "CCD edge" in message


def test_counts_use_records_and_visits_consistently(default_coadd):
    counts = count_inputs(default_coadd)
    records = sum(len(cell.inputs) for cell in default_coadd.cells.values())
    assert sum(counts.records.values()) == records  # what `cellcoadd info` counts
    pairs = sum(len({r.visit for r in c.inputs}) for c in default_coadd.cells.values())
    assert sum(counts.visits.values()) == pairs
    assert counts.visits["used"] == int(counts.visits_used_per_cell.sum())
    first, second = counts.summary_lines()
    assert (
        first.startswith("input records (one per cell and overlapping exposure")
        and str(records) in first
    )
    assert "visits used per cell (of 10)" in second


def test_show_prints_a_dash_for_missing_values(small_ccd_coadd):
    cell = next(c for c in small_ccd_coadd.cells.values() if c.n_used < len(c.inputs))
    rejected = next(r for r in cell.inputs if r.status != "used")
    nan_record = rejected.model_copy(update={"psf_fwhm": float("nan"), "weight": 0.0})
    lines = input_lines(_with_inputs([nan_record]))
    assert "nan" not in lines[0].lower()
    assert "PSF FWHM      -" in lines[0] and "weight          -" in lines[0]


def _with_inputs(records):
    class _View:
        inputs = records

    return _View()


def test_negative_declination_needs_no_double_dash():
    result = CliRunner().invoke(cli, ["locate", "10.0", "-30.0", "--json"])
    assert result.exit_code == 0, result.output
    assert '"tract"' in result.output


def test_validate_shear_defaults_and_advice():
    assert parse_snr("paper") is None and parse_snr("10000") == 10000.0
    advice = precision_advice(10.0, 200)
    assert "--n-objects" in advice and "1/sqrt(N)" in advice
    needed = int(advice.split("--n-objects ")[1].split()[0])
    assert needed == pytest.approx(200 * (10.0 / 3e-4) ** 2, rel=1e-6)
    assert "enough" in precision_advice(2e-4, 100)
    assert "no error estimate" in precision_advice(float("nan"), 100)
    help_text = " ".join(CliRunner().invoke(cli, ["validate-shear", "--help"]).output.split())
    assert "[default: 10000]" in help_text and "[default: 100; x>=2]" in help_text


@pytest.mark.slow
def test_demo_keeps_exposures_only_when_asked(tmp_path):
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--visits", "1", "--workers", "1", "--keep-exposures"]
    result = CliRunner().invoke(cli, [*args, "--quiet"])
    assert result.exit_code == 0, result.output
    assert len(list((out / "exposures").glob("visit*-det*.fits"))) == 9
    assert "cellcoadd build" in result.output  # how to rebuild from them
