"""Figures (matplotlib, no pyplot state): layouts, coadd planes and input maps."""

from cellcoadd.plots.coadd import plot_cell_planes, plot_inputs_map, plot_stitched
from cellcoadd.plots.layout import plot_patch_layout

__all__ = ["plot_cell_planes", "plot_inputs_map", "plot_patch_layout", "plot_stitched"]
