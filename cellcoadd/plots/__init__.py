"""Figures (matplotlib, Agg backend): layouts, coadd planes and input maps."""

from cellcoadd.plots.layout import plot_patch_layout

__all__ = ["plot_patch_layout"]
