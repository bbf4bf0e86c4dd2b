"""Per-row presets of the shear-bias table (benchmarks/shear_bias.py), without running it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from cellcoadd.errors import ConfigError
from cellcoadd.pipelines import ValidationSettings
from cellcoadd.pipelines.validation.bias_presets import (
    HIGH_SNR_PAIRS,
    describe_settings,
    row_settings,
)
from cellcoadd.pipelines.validation.validation_settings import BFD_OVERSAMPLE
from cellcoadd.sim import SimConfig

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "shear_bias.py"
TABLE1 = ("metacal-coadd", "metacal-multi-epoch", "bfd-coadd", "bfd-multi-epoch", "anacal-coadd")


def _settings(options: dict) -> ValidationSettings:
    """The ValidationSettings a row's options give (validate_shear's own checks)."""
    fields = {k: v for k, v in options.items() if k != "shear"}
    return ValidationSettings(sim=SimConfig(shear=(options["shear"], 0.0)), **fields)


@pytest.mark.parametrize("row", TABLE1)
def test_high_snr_preset_gives_each_row_what_it_needs(row):
    options = row_settings(row, "high-snr")
    settings = _settings(options)  # a combination the settings accept
    assert settings.snr == (1.0e4, 1.0e4)
    if row.startswith("bfd"):
        assert settings.bfd_template_sample == "targets" and not settings.rotated_partners
        assert settings.sim.shear == (1.0e-3, 0.0)
        assert settings.bfd_oversample == BFD_OVERSAMPLE
        assert "templates: the targets" in describe_settings(options)
    else:
        assert settings.rotated_partners and settings.sim.shear == (0.02, 0.0)
        assert "ring partners" in describe_settings(options)
    assert HIGH_SNR_PAIRS[row] >= 32


def test_no_preset_keeps_the_command_line_settings():
    options = row_settings("bfd-coadd", snr=(10.0, 50.0), shear=0.01, shape="wmom")
    settings = _settings(options)
    assert settings.bfd_template_sample == "independent" and settings.rotated_partners
    assert settings.sim.shear == (0.01, 0.0) and settings.shape == "admom"
    assert describe_settings(options).startswith("S/N 10-50, g1 = 0.01, ring partners")
    assert row_settings("metacal-coadd", shape="wmom")["shape"] == "wmom"
    # an explicit shear wins over the preset's
    assert row_settings("bfd-coadd", "high-snr", shear=2e-3)["shear"] == 2e-3


@pytest.mark.parametrize(
    ("row", "preset", "shear", "message"),
    [
        ("anacal-multi-epoch", "none", None, "AnaCal"),
        ("foo-coadd", "none", None, "unknown method"),
        ("metacal-coadd", "fast", None, "unknown preset"),
        ("metacal-coadd", "none", 0.0, "must not be 0"),
    ],
)
def test_bad_rows_are_refused(row, preset, shear, message):
    with pytest.raises(ConfigError, match=message):
        row_settings(row, preset, shear=shear)


def test_benchmark_table_and_pair_counts():
    spec = importlib.util.spec_from_file_location("shear_bias_benchmark", BENCHMARK)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rows = ["metacal-coadd", "bfd-coadd"]
    assert bench._pairs(None, rows, "high-snr") == [HIGH_SNR_PAIRS[r] for r in rows]
    assert bench._pairs("300,40", rows, "none") == [300, 40]
    assert bench._pairs("50", rows, "high-snr") == [50, 50]
    with pytest.raises(ValueError, match="2 rows"):
        bench._pairs("1,2,3", rows, "none")
    result = {
        "method": "bfd", "mode": "coadd", "m1": 6.0e-4, "m1_err": 1.4e-4, "c1": 1e-5,
        "c1_err": 2e-5, "c2": -1e-5, "c2_err": 3e-5, "n_used": 32, "n_objects": 32,
        "cpu_seconds": 30.0, "wall_seconds": 20.0, "settings": {"sim": {"shear": [1e-3, 0]}},
    }  # fmt: skip
    text = bench.table([result])
    assert "+0.00060 +- 0.00014" in text and "+0.00120 +- 0.00070" in text  # ours, paper
    assert "32/32" in text and "0.001" in text
    (line,) = bench.cost_lines([result], [2e-4], workers=2)
    assert "sigma_m = 0.0002 needs ~16 pairs" in line
