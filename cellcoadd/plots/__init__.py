"""Figures (matplotlib, no pyplot state): layouts, coadd planes, input maps and the
S/N-loss and edge-rejection results of :mod:`cellcoadd.analysis`.

``import cellcoadd.plots`` loads no matplotlib: each name is imported from its module
(:mod:`~cellcoadd.plots.layout`, :mod:`~cellcoadd.plots.coadd`,
:mod:`~cellcoadd.plots.analysis`) on first use.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

#: public name -> module that defines it
_EXPORTS: dict[str, str] = {
    "plot_cell_planes": "cellcoadd.plots.coadd",
    "plot_inputs_map": "cellcoadd.plots.coadd",
    "plot_stitched": "cellcoadd.plots.coadd",
    "plot_patch_layout": "cellcoadd.plots.layout",
    "plot_rejection": "cellcoadd.plots.analysis",
    "plot_snr_loss": "cellcoadd.plots.analysis",
}

__all__ = [
    "plot_cell_planes",
    "plot_inputs_map",
    "plot_patch_layout",
    "plot_rejection",
    "plot_snr_loss",
    "plot_stitched",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'cellcoadd.plots' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from cellcoadd.plots.analysis import plot_rejection, plot_snr_loss
    from cellcoadd.plots.coadd import plot_cell_planes, plot_inputs_map, plot_stitched
    from cellcoadd.plots.layout import plot_patch_layout
