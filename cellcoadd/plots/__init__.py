"""Figures (matplotlib, no pyplot state): layouts, coadd planes, input maps and the
S/N-loss and edge-rejection results of :mod:`cellcoadd.analysis`.

``import cellcoadd.plots`` loads no matplotlib: each name is imported from its module
(:mod:`~cellcoadd.plots.layout`, :mod:`~cellcoadd.plots.coadd`,
:mod:`~cellcoadd.plots.analysis`) on first use. Every figure has the look of
:mod:`~cellcoadd.plots.style` (fonts, colours, resolution), set only while it is drawn.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from cellcoadd._lazy import lazy_exports

#: public name -> module that defines it
_EXPORTS: dict[str, str] = {
    "plot_cell_planes": "cellcoadd.plots.coadd",
    "plot_inputs_map": "cellcoadd.plots.coadd",
    "plot_stitched": "cellcoadd.plots.coadd",
    "plot_patch_layout": "cellcoadd.plots.layout",
    "plot_rejection": "cellcoadd.plots.analysis",
    "plot_snr_loss": "cellcoadd.plots.analysis",
    "cell_planes_figure": "cellcoadd.plots.coadd",
    "patch_layout_figure": "cellcoadd.plots.layout",
}

__all__ = [
    "cell_planes_figure",
    "patch_layout_figure",
    "plot_cell_planes",
    "plot_inputs_map",
    "plot_patch_layout",
    "plot_rejection",
    "plot_snr_loss",
    "plot_stitched",
]


__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS, ("style",))


if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from cellcoadd.plots.analysis import plot_rejection, plot_snr_loss
    from cellcoadd.plots.coadd import (
        cell_planes_figure,
        plot_cell_planes,
        plot_inputs_map,
        plot_stitched,
    )
    from cellcoadd.plots.layout import patch_layout_figure, plot_patch_layout
