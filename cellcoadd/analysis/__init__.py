"""Predictions of what edge-free cell coadds cost (paper section 5 and appendix A).

- :mod:`~cellcoadd.analysis.snr_loss`: flux variance of a coadd fit versus a joint
  multi-epoch fit (exact eqs. A5 / A7, toy eq. 10, Monte Carlo of Fig. 4).
- :mod:`~cellcoadd.analysis.rejection`: visits rejected because a detector edge crosses a
  cell, and the depth lost (section 5.2, Fig. 6), on the focal planes of
  :mod:`~cellcoadd.sim.focal_plane` with the dithers of :mod:`~cellcoadd.sim.dither`
  (re-exported here).

The corresponding PNG figures are drawn by :mod:`cellcoadd.plots.analysis`.
"""

from cellcoadd.analysis.gaussian_epochs import (
    continuous_gaussian_ratio,
    epoch_psf_sigmas,
    gaussian_templates,
)
from cellcoadd.analysis.rejection import (
    PAPER_CELL_SIZES_ARCMIN,
    PAPER_REJECTED_RANGE,
    RejectionStats,
    classify_cells,
    default_cell_size_arcmin,
    depth_loss_mag,
    rejection_statistics,
    rejection_survey,
    rejection_table,
)
from cellcoadd.analysis.snr_loss import (
    SnrLossTable,
    coadd_template,
    exact_ratio_curve,
    exact_variance_ratio,
    lsst_snr_loss,
    monte_carlo_ratio,
    toy_variance_ratio,
    variance_coadd,
    variance_multi,
)
from cellcoadd.sim.dither import dither_offsets, hexagon_offsets, spiral_offsets
from cellcoadd.sim.focal_plane import (
    Detector,
    DetectorLocator,
    FocalPlaneConfig,
    decam_like_focal_plane,
    lsst_focal_plane,
)

__all__ = [
    "PAPER_CELL_SIZES_ARCMIN",
    "PAPER_REJECTED_RANGE",
    "Detector",
    "DetectorLocator",
    "FocalPlaneConfig",
    "RejectionStats",
    "SnrLossTable",
    "classify_cells",
    "coadd_template",
    "continuous_gaussian_ratio",
    "decam_like_focal_plane",
    "default_cell_size_arcmin",
    "depth_loss_mag",
    "dither_offsets",
    "epoch_psf_sigmas",
    "exact_ratio_curve",
    "exact_variance_ratio",
    "gaussian_templates",
    "hexagon_offsets",
    "lsst_focal_plane",
    "lsst_snr_loss",
    "monte_carlo_ratio",
    "rejection_statistics",
    "rejection_survey",
    "rejection_table",
    "spiral_offsets",
    "toy_variance_ratio",
    "variance_coadd",
    "variance_multi",
]
