"""How precisely a shear-bias validation run measures ``m1``: the error model behind the
forecast and the advice of ``cellcoadd validate-shear``.

The jackknife error on ``m1`` falls as ``1 / sqrt(N)`` with the number ``N`` of ``+g/-g``
pairs; its per-pair scale ``sigma(m1) * sqrt(N)`` depends on the pixel noise. The scales
here were measured with this code (``docs/validation.md``: "Why so many pairs" and the
nearly noise-free test), metacalibration with adaptive moments (the default shape) at the
input shear :data:`REFERENCE_SHEAR`:

* S/N >= :data:`HIGH_SNR` (nearly noise free): about ``1.5e-3`` (300 pairs bound ``m1`` to
  about 1e-4);
* S/N from the paper's cut (:data:`SNR_CUT`) to 50: ``1.2`` to ``2.2`` (runs gave 1.70, 2.2,
  1.6 and 1.35 on coadds, 1.2 and 1.6 on single epochs; ``wmom`` 1.25 with its cuts in
  45,000- and 9,500-pair runs, 0.9 without them). It is dominated by the objects at
  S/N < 20, whose responses scatter (with heavy tails for adaptive moments), and by the
  objects the cuts keep in one sheared image and drop in its opposite;
* the paper's noise: of order ``100`` (most objects fail the S/N cut; 200 pairs gave
  about +-10).

The part of the error due to pixel noise scales as ``REFERENCE_SHEAR / |g|`` with another
input shear ``g``.
"""

from __future__ import annotations

import math

#: Input shear g1 at which the scales were measured (the default of ``validate-shear``).
REFERENCE_SHEAR = 0.02
#: Lowest S/N treated as nearly noise free.
HIGH_SNR = 1000.0
#: The paper's S/N cut: objects below it are not used.
SNR_CUT = 10.0
#: ``sigma(m1) * sqrt(N)`` when nearly noise free (S/N >= :data:`HIGH_SNR`).
HIGH_SNR_SCALE = 1.5e-3
#: Range of ``sigma(m1) * sqrt(N)`` at S/N from :data:`SNR_CUT` to 50.
REALISTIC_SNR_SCALES = (1.2, 2.2)
#: Order of ``sigma(m1) * sqrt(N)`` at the paper's noise level.
PAPER_NOISE_SCALE = 100.0
#: The precision a run aims at: a 3-sigma test of the requirement ``|m1| < 1e-3``
#: (:data:`cellcoadd.pipelines.validation.bias_table.M_REQUIREMENT`).
TARGET_M_ERR = 3e-4


def error_scales(lowest_snr: float | None) -> tuple[float, float] | None:
    """Range ``(low, high)`` of ``sigma(m1) * sqrt(N)`` at :data:`REFERENCE_SHEAR` for
    objects of S/N from ``lowest_snr`` up (None: the paper's noise level); None when
    ``lowest_snr`` is below the S/N cut (most objects fail it: no useful forecast)."""
    if lowest_snr is None:
        return (PAPER_NOISE_SCALE, PAPER_NOISE_SCALE)
    if lowest_snr >= HIGH_SNR:
        return (HIGH_SNR_SCALE, HIGH_SNR_SCALE)
    if lowest_snr >= SNR_CUT:
        return REALISTIC_SNR_SCALES
    return None


def pairs_needed(m1_err: float, n_pairs: int, target: float = TARGET_M_ERR) -> int:
    """Pairs that would bring an error ``m1_err`` measured with ``n_pairs`` pairs down to
    ``target`` (the error falls as ``1 / sqrt(N)``)."""
    return math.ceil(n_pairs * (m1_err / target) ** 2)


__all__ = [
    "HIGH_SNR",
    "HIGH_SNR_SCALE",
    "PAPER_NOISE_SCALE",
    "REALISTIC_SNR_SCALES",
    "REFERENCE_SHEAR",
    "SNR_CUT",
    "TARGET_M_ERR",
    "error_scales",
    "pairs_needed",
]
