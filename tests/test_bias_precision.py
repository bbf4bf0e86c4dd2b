"""The error model of m1 (``cellcoadd.pipelines.validation.bias_precision``) and the forecast of
``cellcoadd validate-shear`` that uses it."""

from __future__ import annotations

import math

import pytest

from cellcoadd.cli.shear import expected_precision
from cellcoadd.pipelines.validation import bias_precision as model
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


def test_forecast_quotes_the_model():
    n = 400
    high = model.error_scales(1e4)
    low, upper = model.error_scales(20.0) or (math.nan, math.nan)
    assert high is not None
    assert f"{high[0] / 20:.1g}" in expected_precision("10000", n)
    assert f"{low / 20:.1g}-{upper / 20:.1g}" in expected_precision("20,50", n)
    assert "large error" in expected_precision("5", n)
    assert f"x {model.REFERENCE_SHEAR}/|g|" in expected_precision("10000", n, shear=0.001)
