"""The paper's Table 1 and a text table of shear-bias results beside it.

:data:`PAPER_TABLE1_ROWS` holds the paper's rows, keyed by ``(method, mode)``: metacal and
BFD on coadds and multi-epoch. ``single`` (the first epoch alone) and AnaCal are our
additions, without a paper value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cellcoadd.pipelines.validation.stamp_pairs import PairCatalogue
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings, expected_inputs

#: Metacalibration rows of the paper's Table 1: (m, 1-sigma error) on g1, by mode. The
#: paper has no single-epoch row ("single" is our extra reference, the first epoch alone).
PAPER_TABLE1: dict[str, tuple[float, float]] = {
    "coadd": (0.0007, 0.0004),
    "multi-epoch": (0.0004, 0.0004),
}
PAPER_LABELS: dict[str, str] = {
    "coadd": "coadd",
    "multi-epoch": "multi-epoch",
    "single": "single epoch",
}
#: Every row of the paper's Table 1, keyed by (method, mode); absent pairs (single mode,
#: AnaCal) have no paper value.
PAPER_TABLE1_ROWS: dict[tuple[str, str], tuple[float, float]] = {
    ("bfd", "coadd"): (0.0012, 0.0007),
    ("bfd", "multi-epoch"): (-0.0014, 0.0007),
    ("metacal", "coadd"): PAPER_TABLE1["coadd"],
    ("metacal", "multi-epoch"): PAPER_TABLE1["multi-epoch"],
}


def paper_value(method: str, mode: str) -> tuple[float, float]:
    """The paper's ``(m1, error)`` for a method and mode, NaNs when Table 1 has no row."""
    return PAPER_TABLE1_ROWS.get((method, mode), (float("nan"), float("nan")))


def summary_fields(
    settings: ValidationSettings,
    catalogue: PairCatalogue,
    kept_plus: np.ndarray,
    kept_minus: np.ndarray,
    cpu_seconds: float,
) -> dict[str, Any]:
    """What every method's summary reports besides its biases: the counts of pairs
    (``kept_*``: the members its selection kept), CPU seconds, mode, method, settings,
    noise, incomplete coadds and the paper's value."""
    paper = paper_value(settings.method, settings.mode)
    return {
        "n_objects": len(catalogue),
        "n_used": int(np.sum(kept_plus & kept_minus)),
        "n_used_plus": int(np.sum(kept_plus)),
        "n_used_minus": int(np.sum(kept_minus)),
        "cpu_seconds": float(cpu_seconds),
        "mode": settings.mode,
        "method": settings.method,
        "settings": settings.model_dump(mode="json"),
        "noise_sigma_median": float(np.median(catalogue.noise_sigma)),
        "incomplete_coadds": int(np.sum(catalogue.n_inputs < expected_inputs(settings))),
        "paper_m1": paper[0],
        "paper_m1_err": paper[1],
    }


#: Requirement on ``|m|`` of ambitious surveys quoted by the paper.
M_REQUIREMENT = 1.0e-3


def _label(result: dict[str, Any]) -> str:
    method = result.get("method", "metacal")
    name = {"metacal": "metacal", "bfd": "BFD"}.get(method, "AnaCal FPFS")
    shape = result["settings"].get("shape", "admom")
    if method == "metacal" and shape != "admom":
        name += f" {shape}"
    return f"{name} {result['mode']}"


def format_bias_table(results: Sequence[dict[str, Any]]) -> str:
    """A text table of :func:`~cellcoadd.pipelines.validate_shear` results beside the
    paper's Table 1.

    One line per result, followed by the paper's value for that method and mode.
    """
    header = f"{'sample':<38} {'m1':>20} {'c1':>20} {'c2':>20} {'N used/N':>13} {'CPU s':>9}"
    shears = sorted({_true_g(result) for result in results})
    g_text = ", ".join(f"{g:g}" for g in shears)
    lines = [
        f"Multiplicative bias on g1 (g_true = {g_text}; metacal cuts S/N > 10, "
        "T/T_psf > 0.5 (admom) or 1 (wmom); BFD flux 5 < S/N < 50)",
        header,
        "-" * len(header),
    ]
    for result in results:
        mode = result["mode"]
        method = result.get("method", "metacal")
        snr = result["settings"].get("snr")
        snr_text = "sim noise" if snr is None else _snr_text(snr)
        label = f"ours, {_label(result)} ({snr_text})"
        lines.append(
            f"{label:<38} {_pm(result['m1'], result['m1_err']):>20} "
            f"{_pm(result['c1'], result['c1_err']):>20} "
            f"{_pm(result['c2'], result['c2_err']):>20} "
            f"{str(result['n_used']) + '/' + str(result['n_objects']):>13} "
            f"{result['cpu_seconds']:>9.0f}"
        )
        if method == "anacal":
            continue  # not in the paper
        paper_name = "metacal" if method == "metacal" else "BFD"
        paper_label = f"paper, {paper_name} {PAPER_LABELS[mode]}"
        paper = PAPER_TABLE1_ROWS.get((method, mode))
        paper_text = "-" if paper is None else _pm(*paper)
        lines.append(f"{paper_label:<38} {paper_text:>20}")
    lines.append(f"requirement: |m1| < {M_REQUIREMENT:g}")
    if any(result["mode"] == "single" for result in results):
        lines.append("note: 'single' (the first epoch alone) has no row in the paper's Table 1")
    return "\n".join(lines)


def format_cut_comparison(result: dict[str, Any]) -> str:
    """A text table of a metacal result's ``"cut_comparison"``
    (:func:`~cellcoadd.pipelines.validation.shear_validation.cut_comparison`): ``m1`` per selection,
    its paired difference from no cuts (``dm1``) and the per-pair scatter."""
    lines = [
        f"{_label(result)}, {result['n_objects']} pairs: m1 by cuts (dm1: paired difference "
        "from no cuts; scatter: m1_err x sqrt(pairs))",
        f"  {'cuts':16s} {'m1':>18s} {'dm1':>18s} {'scatter':>8s}",
    ]
    for name, entry in result["cut_comparison"].items():
        m1 = _pm(entry["m1"], entry["m1_err"])
        dm1 = _pm(entry["dm1"], entry["dm1_err"]) if "dm1" in entry else ""
        lines.append(f"  {name:16s} {m1:>18s} {dm1:>18s} {entry['scatter']:8.2f}")
    return "\n".join(lines)


def _true_g(result: dict[str, Any]) -> float:
    """The input shear g1 of a result (its settings' simulation)."""
    return float(result["settings"].get("sim", {}).get("shear", (0.02, 0.0))[0])


def _pm(value: float, error: float) -> str:
    return f"{value:+.4f} +- {error:.4f}"


def _snr_text(snr: Sequence[float]) -> str:
    low, high = snr
    return f"S/N {low:g}" if low == high else f"S/N {low:g}-{high:g}"


__all__ = [
    "M_REQUIREMENT",
    "PAPER_LABELS",
    "PAPER_TABLE1",
    "PAPER_TABLE1_ROWS",
    "format_bias_table",
    "format_cut_comparison",
    "paper_value",
]
