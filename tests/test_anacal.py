"""AnaCal (the optional extra cellcoadd[anacal]): FPFS on cell coadds in validate-shear."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from cellcoadd.cli.shear import validate_shear as validate_shear_command
from cellcoadd.errors import ConfigError
from cellcoadd.pipelines import ValidationSettings, format_bias_table, validate_shear
from cellcoadd.shear.anacal_adapter import padded_psf, require_anacal

pytest.importorskip("anacal", reason="AnaCal is the optional extra cellcoadd[anacal]")


@pytest.fixture(scope="module")
def anacal_run():
    return validate_shear(
        "coadd", n_objects=16, snr=1.0e4, seed=21, method="anacal", progress=False
    )


def test_anacal_coadd_bias_is_small_at_high_snr(anacal_run):
    result = anacal_run
    assert result["method"] == "anacal" and result["incomplete_coadds"] == 0
    assert result["n_used"] == result["n_used_plus"] == result["n_used_minus"] == 16
    # measured: m1 = +3.9e-4 +- 2.7e-4 (seed 21, 0.8 arcsec kernel)
    assert abs(result["m1"]) < 2e-3
    assert abs(result["m1"]) < 3.0 * result["m1_err"] + 1e-4
    assert result["m1_err"] < 1e-3
    for name in ("c1", "c2"):  # ring partners cancel the intrinsic shapes
        assert abs(result[name]) < 1e-3
    assert 0.2 < result["R11"] < 1.0 and result["R11"] == pytest.approx(result["R22"], rel=0.05)
    assert result["s2n_median"] > 1000


def test_table_has_no_paper_row_for_anacal(anacal_run):
    table = format_bias_table([anacal_run])
    assert "AnaCal FPFS coadd" in table and "paper, AnaCal" not in table


def test_psf_is_padded_onto_the_anacal_centre():
    psf = np.zeros((35, 35))
    psf[17, 17] = 1.0
    psf[17, 18] = 0.5
    for npix in (48, 49, 64, 32):
        out = padded_psf(psf, npix)
        assert out.shape == (npix, npix)
        assert out[npix // 2, npix // 2] == 1.0 and out[npix // 2, npix // 2 + 1] == 0.5
        assert out.sum() == 1.5
    with pytest.raises(ValueError, match="odd"):
        padded_psf(np.ones((34, 34)), 48)


def test_missing_anacal_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "anacal", None)
    with pytest.raises(ImportError, match=r"cellcoadd\[anacal\]"):
        require_anacal()


def test_anacal_on_a_single_epoch_and_not_multi_epoch():
    # FPFS on the first epoch alone, its own noise realization (like metacal single);
    # measured: m1 = -4e-5 +- 3.0e-4. c is looser than on coadds: AnaCal takes a scalar
    # pixel scale, and each epoch's WCS is sheared by ~1% (c2 = +5e-4 +- 4.6e-3)
    result = validate_shear(
        "single", n_objects=16, snr=1.0e4, seed=21, method="anacal", progress=False
    )
    assert result["mode"] == "single" and result["incomplete_coadds"] == 0
    assert result["n_used"] == 16
    assert abs(result["m1"]) < 2e-3 and abs(result["m1"]) < 3.0 * result["m1_err"] + 1e-4
    assert format_bias_table([result]).count("paper,") == 0
    with pytest.raises(ConfigError, match="joint multi-epoch"):
        validate_shear("multi-epoch", n_objects=2, method="anacal")
    with pytest.raises(ValueError, match="joint multi-epoch"):
        ValidationSettings(method="anacal", mode="multi-epoch")
    result = CliRunner().invoke(
        validate_shear_command, ["--method", "anacal", "--mode", "multi-epoch"]
    )
    assert result.exit_code == 2 and "coadd or single" in result.output


def test_cli_json_with_anacal():
    result = CliRunner().invoke(
        validate_shear_command,
        ["--method", "anacal", "--n-objects", "4", "--snr", "1000", "--json", "--quiet"],
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert data["method"] == "anacal" and data["n_used"] == 4
    assert data["paper_m1"] is None and np.isfinite(data["m1"])
