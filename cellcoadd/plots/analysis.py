"""PNG figures of the S/N-loss (paper Fig. 4) and edge-rejection (paper Fig. 6) results.

The results come from :mod:`cellcoadd.analysis`.

Figures are built with :class:`matplotlib.figure.Figure` directly (no pyplot state), so they
are safe in scripts, tests and worker processes; matplotlib is imported only when plotting.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cellcoadd.analysis.rejection import RejectionStats
from cellcoadd.analysis.snr_loss import SnrLossTable, exact_ratio_curve, toy_variance_ratio
from cellcoadd.plots import style
from cellcoadd.plots.style import save as save_figure


@style.styled
def plot_snr_loss(table: SnrLossTable, path: str | Path, n_curve: int = 41, dpi: int = 90) -> Path:
    """Plot measured ratios with error bars, the exact prediction (solid) and the toy (dashed).

    Parameters
    ----------
    table : SnrLossTable
        Output of :func:`~cellcoadd.analysis.snr_loss.monte_carlo_ratio`.
    path : str or Path
        PNG file to write.
    n_curve : int
        Points of the exact curve; it is recomputed on a fine ``R`` grid with the table's
        settings when the PSF sizes were the deterministic quantiles, and otherwise drawn
        through the table's own exact values.
    dpi : int
        Resolution of the PNG.

    Returns
    -------
    Path
        The written file.
    """
    from matplotlib.figure import Figure

    path = Path(path)
    r_max = float(max(np.max(table.resolution), 0.8))
    grid = np.linspace(0.0, r_max, n_curve)
    if table.psf_sizes == "quantiles":
        exact = exact_ratio_curve(
            grid, table.dsigma_over_sigma, table.n_epochs, table.psf_fwhm, table.pixel_scale
        )
        exact_r = grid
    else:
        exact_r, exact = table.resolution, table.ratio_exact
    figure = Figure(figsize=(5.0, 3.6))
    axes = figure.add_subplot()
    axes.errorbar(
        table.resolution,
        table.ratio_mc,
        yerr=table.ratio_mc_err,
        fmt="o",
        color="black",
        ms=4,
        capsize=2,
        label=f"simulation ({table.n_trials} trials)",
    )
    axes.plot(exact_r, exact, "-", color="tab:blue", label="exact (eqs. A5/A7)")
    axes.plot(
        grid,
        toy_variance_ratio(grid, table.dsigma_over_sigma),
        "--",
        color="tab:orange",
        label="toy model (eq. 10)",
    )
    axes.axhline(1.0, color="grey", lw=0.5)
    axes.set_xlabel(r"$R = \sigma_g^2 / (\sigma_g^2 + \sigma_p^2)$")
    axes.set_ylabel(r"var $\hat A_{\rm coadd}$ / var $\hat A_{\rm multi}$")
    axes.set_title(
        rf"$\Delta\sigma_p/\sigma_p$ = {table.dsigma_over_sigma:g}, {table.n_epochs} epochs",
        fontsize=10,
    )
    axes.legend(fontsize=8, frameon=False)
    figure.tight_layout()
    save_figure(figure, path, dpi)  # atomically: a link there is replaced
    return path


@style.styled
def plot_rejection(results: Sequence[RejectionStats], path: str | Path, dpi: int = 80) -> Path:
    """Histograms of the rejected-visit fraction and the 5-sigma depth loss per cell.

    One colour per cell size, solid lines for the random dither and dashed for the spiral,
    as in the paper's Fig. 6 (which shows depths rather than depth losses).

    Parameters
    ----------
    results : sequence of RejectionStats
        Output of :func:`~cellcoadd.analysis.rejection.rejection_survey`.
    path : str or Path
        PNG file to write.
    dpi : int
        Resolution of the PNG.

    Returns
    -------
    Path
        The written file.
    """
    from matplotlib.figure import Figure

    path = Path(path)
    sizes = sorted({stats.cell_size_arcmin for stats in results})
    colours = {size: f"C{index}" for index, size in enumerate(sizes)}
    styles = {"random": "-", "spiral": "--"}
    fraction_max = max(float(np.nanmax(s.fraction_rejected)) for s in results)
    loss_values = [s.depth_loss_mag[np.isfinite(s.depth_loss_mag)] for s in results]
    loss_max = max(float(v.max(initial=0.0)) for v in loss_values)
    fraction_bins = np.linspace(0.0, fraction_max * 1.05 + 1e-6, 50)
    loss_bins = np.linspace(0.0, loss_max * 1.05 + 1e-6, 50)
    figure = Figure(figsize=(9.0, 3.4))
    left, right = figure.subplots(1, 2)
    for stats, losses in zip(results, loss_values, strict=True):
        style = {"color": colours[stats.cell_size_arcmin], "ls": styles.get(stats.dither, ":")}
        label = f"{stats.cell_size_arcmin:.3g}' {stats.dither}"
        fraction = stats.fraction_rejected[stats.n_covering > 0]
        left.hist(100 * fraction, bins=100 * fraction_bins, histtype="step", label=label, **style)
        right.hist(losses, bins=loss_bins, histtype="step", **style)
    left.set_xlabel("visits rejected per cell (%)")
    left.set_ylabel("cells")
    right.set_xlabel("5-sigma depth loss per cell (mag)")
    left.legend(fontsize=7, frameon=False, ncol=2)
    figure.tight_layout()
    save_figure(figure, path, dpi)  # atomically: a link there is replaced
    return path
