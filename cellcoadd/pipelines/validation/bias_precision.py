"""How precisely a shear-bias validation run measures ``m1``: the error model behind the
forecast and the advice of ``cellcoadd validate-shear``.

The jackknife error on ``m1`` falls as ``1 / sqrt(N)`` with the number ``N`` of ``+g/-g``
pairs; its per-pair scale ``sigma(m1) * sqrt(N)`` depends on the method, the mode, the
pixel noise and the input shear. :data:`FORECAST_TABLE` stores the scale measured for each
row (method, mode, S/N regime, shape) with the run it came from; :func:`forecast` picks
the row of a run, and ``validate-shear`` prints it before the run and uses it for
``--target-sigma``. Measured with this code (``docs/validation.md``):

* S/N >= :data:`HIGH_SNR` (nearly noise free): metacal ``2.6e-3`` on coadds and
  ``1.9e-3`` multi-epoch (100 pairs of a seed the project had not used; an earlier
  300-pair run gave 2.1e-3, so the old single constant 1.5e-3 was optimistic), AnaCal
  ``1.5e-3``, BFD (the targets as templates, ``g1 = 1e-3``) ``2.3e-3`` on coadds and
  ``9.6e-3`` multi-epoch (its rare outlying pairs);
* S/N from the paper's cut (:data:`SNR_CUT`) to 50: metacal ``admom`` 1.70 on coadds
  (runs gave 1.2 to 2.2: :data:`REALISTIC_SNR_SCALES` where no row is stored), ``wmom``
  0.92 on coadds and 0.88 multi-epoch; BFD with its default 1600 independent templates
  0.40 on coadds (0.33 and 0.40 in two 400-pair runs: the larger is kept). It is
  dominated by the objects at S/N < 20, whose responses scatter (with heavy tails for
  adaptive moments), and by the objects the cuts keep in one sheared image and drop in
  its opposite;
* the paper's noise: of order ``100`` (most objects fail the S/N cut; 200 pairs gave
  about +-10).

The part of the error due to pixel noise scales as ``shear / |g|`` with an input shear
``g`` other than the row's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

#: Input shear g1 at which the scales were measured (the default of ``validate-shear``).
REFERENCE_SHEAR = 0.02
#: Lowest S/N treated as nearly noise free.
HIGH_SNR = 1000.0
#: The paper's S/N cut: objects below it are not used.
SNR_CUT = 10.0
#: ``sigma(m1) * sqrt(N)`` when nearly noise free (S/N >= :data:`HIGH_SNR`), where no row
#: of :data:`FORECAST_TABLE` is stored (metacal on coadds: the largest of the metacal rows).
HIGH_SNR_SCALE = 2.6e-3
#: Range of ``sigma(m1) * sqrt(N)`` at S/N from :data:`SNR_CUT` to 50.
REALISTIC_SNR_SCALES = (1.2, 2.2)
#: Order of ``sigma(m1) * sqrt(N)`` at the paper's noise level.
PAPER_NOISE_SCALE = 100.0
#: The precision a run aims at: a 3-sigma test of the requirement ``|m1| < 1e-3``
#: (:data:`cellcoadd.pipelines.validation.bias_table.M_REQUIREMENT`).
TARGET_M_ERR = 3e-4


#: S/N regime of a run: nearly noise free, from the S/N cut to 50, the paper's noise.
Regime = Literal["high", "realistic", "paper"]


@dataclass(frozen=True)
class ForecastRow:
    """The measured per-pair scale of ``sigma(m1)`` for one kind of run.

    Attributes
    ----------
    method, mode : str
        ``"metacal"``, ``"bfd"``, ``"anacal"``; ``"coadd"``, ``"multi-epoch"``,
        ``"single"``.
    regime : {"high", "realistic", "paper"}
        S/N >= :data:`HIGH_SNR`; S/N from :data:`SNR_CUT` to 50; the paper's noise.
    scale : float
        ``sigma(m1) * sqrt(N)``, dimensionless, at the input shear ``shear``.
    shear : float
        Input ``g1`` of the measuring run (the pixel-noise part scales as ``shear / |g|``).
    shape : str
        Metacal shape (``"admom"``, ``"wmom"``); ``"-"`` for the other methods.
    source : str
        The run that measured it.
    offset : bool
        Measured with objects at random positions of the cell (``object_offset``,
        coadd mode): metacal's per-pair scatter doubles there.
    """

    method: str
    mode: str
    regime: Regime
    scale: float
    shear: float
    shape: str
    source: str
    offset: bool = False

    def label(self) -> str:
        """``"metacal admom coadd, S/N >= 1000"``: what the row is."""
        shape = f" {self.shape}" if self.shape != "-" else ""
        regime = {
            "high": f"S/N >= {HIGH_SNR:g}",
            "realistic": f"S/N {SNR_CUT:g}-50",
            "paper": "paper noise",
        }[self.regime]
        where = ", random positions" if self.offset else ""
        return f"{self.method}{shape} {self.mode}, {regime}{where}"


#: Measured ``sigma(m1) * sqrt(N)`` per row (docs/validation.md has the commands).
FORECAST_TABLE: tuple[ForecastRow, ...] = (
    ForecastRow("metacal", "coadd", "high", 2.6e-3, 0.02, "admom", "100 pairs, m1_err 2.6e-4"),
    ForecastRow("metacal", "coadd", "high", 2.6e-3, 0.02, "wmom", "as admom (not measured)"),
    ForecastRow("metacal", "multi-epoch", "high", 1.9e-3, 0.02, "admom", "100 pairs, 1.9e-4"),
    ForecastRow("metacal", "single", "high", 1.6e-3, 0.02, "admom", "400 pairs, 8e-5"),
    ForecastRow("anacal", "coadd", "high", 1.5e-3, 0.02, "-", "100 pairs, 1.5e-4"),
    ForecastRow("bfd", "coadd", "high", 2.3e-3, 1e-3, "-", "200 pairs, 1.6e-4; targets"),
    ForecastRow("bfd", "multi-epoch", "high", 9.6e-3, 1e-3, "-", "measured 9.6e-3; targets"),
    ForecastRow("metacal", "coadd", "realistic", 1.70, 0.02, "admom", "1000 pairs, 0.054"),
    ForecastRow("metacal", "coadd", "realistic", 0.92, 0.02, "wmom", "3000 pairs, 0.017"),
    ForecastRow("metacal", "multi-epoch", "realistic", 0.88, 0.02, "wmom", "1200 pairs, 0.025"),
    ForecastRow("bfd", "coadd", "realistic", 0.40, 0.02, "-", "2 x 400 pairs: 0.33, 0.40"),
    # objects within 5 px of the cell centre, measured with psf_at (seed 100)
    ForecastRow("metacal", "coadd", "high", 4.8e-3, 0.02, "admom", "300 pairs, 2.8e-4", True),
    ForecastRow("metacal", "coadd", "high", 4.8e-3, 0.02, "wmom", "as admom", True),
    ForecastRow("anacal", "coadd", "high", 1.8e-3, 0.02, "-", "150 pairs, 1.5e-4", True),
    ForecastRow("bfd", "coadd", "high", 2.3e-3, 1e-3, "-", "centred row kept (0.7e-3)", True),
)


def regime_of(lowest_snr: float | None) -> Regime | None:
    """The :attr:`ForecastRow.regime` of objects of S/N from ``lowest_snr`` up (None: the
    paper's noise); None below the S/N cut (most objects fail it: no useful forecast)."""
    if lowest_snr is None:
        return "paper"
    if lowest_snr >= HIGH_SNR:
        return "high"
    if lowest_snr >= SNR_CUT:
        return "realistic"
    return None


def forecast(
    method: str, mode: str, lowest_snr: float | None, shape: str = "admom", offset: bool = False
) -> ForecastRow | None:
    """The stored row of :data:`FORECAST_TABLE` for a run (``offset``: objects at random
    positions of the cell; the centred row where no such row is stored), or None when
    none is stored (:func:`error_scales` then gives the generic range)."""
    regime = regime_of(lowest_snr)
    wanted = shape if method == "metacal" else "-"
    rows = [
        row
        for row in FORECAST_TABLE
        if (row.method, row.mode, row.regime, row.shape) == (method, mode, regime, wanted)
    ]
    # the row measured as the run places its objects first
    return min(rows, key=lambda row: row.offset != (offset and mode == "coadd"), default=None)


def forecast_scale(row: ForecastRow, shear: float) -> float:
    """``sigma(m1) * sqrt(N)`` of ``row`` at the input shear ``shear`` (the pixel-noise
    error scales as ``row.shear / |shear|``)."""
    return row.scale * row.shear / abs(shear)


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
    "FORECAST_TABLE",
    "ForecastRow",
    "HIGH_SNR",
    "HIGH_SNR_SCALE",
    "PAPER_NOISE_SCALE",
    "REALISTIC_SNR_SCALES",
    "REFERENCE_SHEAR",
    "SNR_CUT",
    "TARGET_M_ERR",
    "error_scales",
    "forecast",
    "forecast_scale",
    "pairs_needed",
    "regime_of",
]
