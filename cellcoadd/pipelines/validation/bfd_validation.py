"""Summary of a BFD shear-bias validation run (``validate-shear --method bfd``).

The pairs are measured by :func:`cellcoadd.pipelines.validation.stamp_pairs.measure_pair` (BFD
moments of the coadd, the first epoch or the summed epochs). :func:`bfd_posterior` builds
the template prior for the targets' mean moment covariance
(:func:`~cellcoadd.pipelines.validation.stamp_pairs.bfd_templates`: an independent deep sample at 8
rotations, or the targets themselves unsheared at one) and each member's ``P, Q, R``;
:func:`summarize_bfd` turns them into ``m1, c1, c2`` with jackknife errors
(:func:`cellcoadd.shear.bfd.paired_bias`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from cellcoadd.errors import BfdError
from cellcoadd.pipelines.validation.bias_table import summary_fields
from cellcoadd.pipelines.validation.stamp_pairs import PairCatalogue, bfd_noise_sigma, bfd_templates
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings
from cellcoadd.shear import bfd
from cellcoadd.shear.response import Groups


@dataclass(frozen=True, eq=False)
class BfdPosterior:
    """The prior of a BFD run and the ``P, Q, R`` of its targets.

    Attributes
    ----------
    plus, minus : Pqr
        Of the ``+g`` and ``-g`` members (targets whose moments failed: not selected).
    prior : TemplatePrior
        Built for the targets' mean moment covariance.
    n_templates : int
        Templates that could be measured.
    cpu_seconds : float
        CPU time of the templates, the prior and ``P, Q, R``.
    """

    plus: bfd.Pqr
    minus: bfd.Pqr
    prior: bfd.TemplatePrior
    n_templates: int
    cpu_seconds: float


def bfd_posterior(
    settings: ValidationSettings,
    catalogue: PairCatalogue,
    templates: list[bfd.KData] | None = None,
) -> BfdPosterior:
    """The template prior for the targets' mean moment covariance, and ``P, Q, R``.

    ``templates``: the run's (:func:`~cellcoadd.pipelines.validation.stamp_pairs.bfd_templates`),
    made here when not given (then included in ``cpu_seconds``); a comparison of prior
    settings on the same pairs passes them to make them once.

    Raises
    ------
    ValueError
        No target could be measured, or no template.
    """
    plus, minus = catalogue.plus["bfd"], catalogue.minus["bfd"]
    good = (plus["flags"] == 0) & (minus["flags"] == 0)
    if not np.any(good):
        raise BfdError("no BFD target could be measured")
    cov_even = np.mean(np.concatenate([plus["cov_even"][good], minus["cov_even"][good]]), axis=0)
    cov_odd = np.mean(np.concatenate([plus["cov_odd"][good], minus["cov_odd"][good]]), axis=0)
    start = time.process_time()
    if templates is None:
        templates = bfd_templates(settings, bfd_noise_sigma(settings), catalogue.index.tolist())
    # templates that are the targets themselves already have the targets' orientations
    rotations = 1 if settings.bfd_template_sample == "targets" else 8
    prior = bfd.TemplatePrior.from_templates(
        templates, cov_even, cov_odd, n_rotations=rotations, snr_range=settings.bfd_snr_range,
        mirror=settings.bfd_mirror,
    )  # fmt: skip
    pqrs = []
    for member in (plus, minus):
        pqr = prior.pqr(member["even"])
        ok = member["flags"] == 0
        pqrs.append(
            bfd.Pqr(
                P=np.where(ok, pqr.P, 0.0),
                Q=pqr.Q,
                R=pqr.R,
                log_scale=pqr.log_scale,
                selected=pqr.selected & ok,
            )
        )
    return BfdPosterior(pqrs[0], pqrs[1], prior, len(templates), time.process_time() - start)


def summarize_bfd(
    settings: ValidationSettings, catalogue: PairCatalogue, group: Groups
) -> dict[str, Any]:
    """Biases and diagnostics of a catalogue of BFD pairs (``group``: jackknife rows
    removed together, :data:`~cellcoadd.shear.response.Groups`: ring partners)."""
    start = time.process_time()
    posterior = bfd_posterior(settings, catalogue)
    bias = bfd.paired_bias(
        posterior.plus, posterior.minus, posterior.prior, true_g=settings.sim.shear[0],
        group=group,
    )  # fmt: skip
    prior_cpu = time.process_time() - start
    sel_plus, sel_minus = posterior.plus.selected, posterior.minus.selected
    plus, minus = catalogue.plus["bfd"], catalogue.minus["bfd"]
    good = (plus["flags"] == 0) & (minus["flags"] == 0)
    cpu = float(catalogue.cpu_seconds.sum()) + prior_cpu
    return {
        **bias,
        **summary_fields(settings, catalogue, sel_plus, sel_minus, cpu),
        "prior_cpu_seconds": prior_cpu,
        "n_templates": posterior.n_templates,
        "flux_snr_median": float(np.median(plus["snr"][good])),
    }


__all__ = ["BfdPosterior", "bfd_posterior", "summarize_bfd"]
