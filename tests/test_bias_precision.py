"""The error model of m1 (``cellcoadd.pipelines.validation.bias_precision``) and the forecast of
``cellcoadd validate-shear`` that uses it."""

from __future__ import annotations

import math

import pytest

from cellcoadd.cli.shear import expected_precision, target_cost
from cellcoadd.errors import ConfigError
from cellcoadd.pipelines.validation import bias_precision as model
from cellcoadd.pipelines.validation.bias_presets import BFD_DEFAULT_TEMPLATES, choose_bfd
from cellcoadd.pipelines.validation.bias_table import M_REQUIREMENT


def test_scales_grow_with_the_noise():
    high = model.error_scales(1e4)
    realistic = model.error_scales(20.0)
    paper = model.error_scales(None)
    assert high is not None and realistic is not None and paper is not None
    assert high[1] < realistic[0] <= realistic[1] < paper[0]
    assert model.error_scales(model.HIGH_SNR) == high
    assert model.error_scales(model.SNR_CUT) == realistic
    assert model.error_scales(model.SNR_CUT - 0.1) is None


def test_target_is_a_three_sigma_test_of_the_requirement():
    assert 3 * model.TARGET_M_ERR <= M_REQUIREMENT


@pytest.mark.parametrize("n_pairs", [1, 100, 4000])
def test_pairs_needed_reaches_the_target(n_pairs):
    err = 0.01
    needed = model.pairs_needed(err, n_pairs)
    assert err * math.sqrt(n_pairs / needed) <= model.TARGET_M_ERR
    assert err * math.sqrt(n_pairs / (needed - 1)) > model.TARGET_M_ERR


def test_forecast_quotes_the_stored_table():
    n = 400
    # the measured rows, not the optimistic 1.5e-3 of before
    row = model.forecast("metacal", "coadd", 1e4)
    assert row is not None and row.scale == 2.6e-3
    assert model.forecast("metacal", "multi-epoch", 1e4).scale == 1.9e-3  # type: ignore[union-attr]
    assert model.forecast("bfd", "multi-epoch", 1e4).scale == 9.6e-3  # type: ignore[union-attr]
    assert model.forecast("metacal", "coadd", 20.0, "wmom").scale == 0.92  # type: ignore[union-attr]
    assert f"{2.6e-3 / 20:.2g}" in expected_precision("10000", n)
    assert "metacal admom coadd, S/N >= 1000" in expected_precision("10000", n)
    # objects at random positions: metacal's scatter doubles (its own row)
    at_random = expected_precision("10000", n, object_offset=5.0)
    assert f"{4.8e-3 / 20:.2g}" in at_random and "random positions" in at_random
    assert model.forecast("metacal", "multi-epoch", 1e4, offset=True).scale == 1.9e-3  # type: ignore[union-attr]
    bfd = expected_precision("10000", n, shear=1e-3, method="bfd", mode="multi-epoch")
    assert f"{9.6e-3 / 20:.2g}" in bfd and "measured at" not in bfd
    # another input shear: the pixel-noise error scales as the row's shear / |g|
    assert f"{2.6e-3 * 20 / 20:.2g}" in expected_precision("10000", n, shear=0.001)
    # no stored row: the generic range, or no forecast below the cut
    assert model.forecast("metacal", "multi-epoch", 20.0) is None
    low, upper = model.error_scales(20.0) or (math.nan, math.nan)
    assert f"{low / 20:.1g}-{upper / 20:.1g}" in expected_precision("20,50", n, mode="multi-epoch")
    assert "large error" in expected_precision("5", n)
    assert f"{model.PAPER_NOISE_SCALE:g}" in expected_precision("paper", n)


def test_target_sigma_uses_the_stored_row():
    row = model.forecast("metacal", "coadd", 1e4)
    assert row is not None
    # a lucky short run (m1_err half the true one) does not halve the forecast pairs
    line = target_cost(1.3e-4, 100, 50.0, 2e-4, (row, 0.02))
    assert f"~{(2.6e-3 / 2e-4) ** 2:.2g} pairs" in line and "stored" in line
    hours = (2.6e-3 / 2e-4) ** 2 * 0.5 / 3600
    assert f"~{hours:.3g} CPU hours" in line
    assert "this run's error" in target_cost(1.3e-4, 100, 50.0, 2e-4)
    assert "no estimate" in target_cost(float("nan"), 100, 50.0, 2e-4)


def test_bfd_settings_follow_the_snr():
    # the default S/N 10^4: the targets as templates, no ring partners, g1 = 1e-3
    high = choose_bfd(1e4)
    assert (high.template_sample, high.rotated_partners, high.shear) == ("targets", False, 1e-3)
    assert "--bfd-template-sample targets --no-rotated-partners --shear 0.001" in high.note
    assert choose_bfd(1e4, shear=0.02).shear == 0.02  # an explicit shear is kept
    # independent templates there are refused, naming the flags that fix it
    for kwargs in ({"template_sample": "independent"}, {"templates": 100}):
        with pytest.raises(ConfigError, match="--bfd-template-sample targets") as info:
            choose_bfd(1e4, **kwargs)  # type: ignore[arg-type]
        assert "--snr 10,50" in str(info.value)
    with pytest.raises(ConfigError, match="straddles"):
        choose_bfd((10.0, 1e4))
    # realistic S/N: enough independent templates for the forecast precision
    for snr in ((10.0, 50.0), 20.0, None):
        low = choose_bfd(snr)
        assert low.template_sample == "independent" and low.rotated_partners
        assert low.templates == BFD_DEFAULT_TEMPLATES == 1600 and low.note == ""
    few = choose_bfd((10.0, 50.0), templates=100)
    assert few.templates == 100 and few.note.startswith("warning")
    # the forecast of the default realistic run is the stored 1600-template row
    row = model.forecast("bfd", "coadd", 10.0)
    assert row is not None and row.scale == 0.40


def test_cli_refuses_bfd_settings_that_give_a_wrong_m1():
    from click.testing import CliRunner

    from cellcoadd.cli.shear import validate_shear

    result = CliRunner().invoke(validate_shear, ["--method", "bfd", "--bfd-templates", "100"])
    assert result.exit_code != 0
    assert "--bfd-template-sample targets --no-rotated-partners --shear 0.001" in result.output
