"""Summary of an AnaCal (FPFS) shear-bias validation run (``validate-shear --method anacal``).

The pairs are measured by :func:`cellcoadd.pipelines.validation.stamp_pairs.measure_pair` (AnaCal on
the cell coadd, :mod:`cellcoadd.shear.anacal_adapter`); :func:`summarize_anacal` turns
them into ``m1, c1, c2`` with jackknife errors, as the metacal summary does, each member's
mean shear being ``<e> / <de/dg>`` over the pairs whose two members were measured.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cellcoadd.errors import ShearError
from cellcoadd.pipelines.validation.bias_table import summary_fields
from cellcoadd.pipelines.validation.stamp_pairs import PairCatalogue
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear.anacal_adapter import paired_bias
from cellcoadd.shear.response import Groups


def summarize_anacal(
    settings: ValidationSettings, catalogue: PairCatalogue, group: Groups
) -> dict[str, Any]:
    """Biases and diagnostics of a catalogue of AnaCal pairs (``group``: jackknife rows
    removed together, :data:`~cellcoadd.shear.response.Groups`: ring partners)."""
    plus, minus = catalogue.plus["anacal"], catalogue.minus["anacal"]
    good_plus, good_minus = plus["flags"] == 0, minus["flags"] == 0
    if not np.any(good_plus & good_minus):
        raise ShearError("no AnaCal pair could be measured")
    bias = paired_bias(plus, minus, true_g=settings.sim.shear[0], group=group)
    kept = good_plus & good_minus
    cpu = float(catalogue.cpu_seconds.sum())
    return {
        **bias,
        **summary_fields(settings, catalogue, good_plus, good_minus, cpu),
        "R11": float(np.mean(plus["de1_dg1"][kept])),
        "R22": float(np.mean(plus["de2_dg2"][kept])),
        "s2n_median": float(np.median(plus["s2n"][kept])),
    }
