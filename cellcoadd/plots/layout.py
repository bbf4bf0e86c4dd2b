"""Patch layout figure in the style of the paper's Fig. 7."""

from __future__ import annotations

import os

from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Patch


def _outline(ax, box: Box, **style) -> None:
    # box edges sit half a pixel outside the first and last pixel centres
    ax.add_patch(
        Rectangle((box.x_start - 0.5, box.y_start - 0.5), box.nx, box.ny, fill=False, **style)
    )


def _draw(ax, patch: Patch, title: str) -> None:
    inner = patch.inner_bbox
    ax.add_patch(
        Rectangle(
            (inner.x_start - 0.5, inner.y_start - 0.5),
            inner.nx,
            inner.ny,
            color="0.85",
            zorder=0,
            label="patch inner region",
        )
    )
    for cell in patch.cells:
        _outline(ax, cell.inner_bbox, edgecolor="tab:cyan", linewidth=0.8)
        cx, cy = cell.index
        if cx % 2 == 0 and cy % 2 == 0:  # every other cell, as in the paper
            _outline(ax, cell.outer_bbox, edgecolor="tab:red", linewidth=0.8)
    # proxies so the legend names each outline once
    ax.plot([], [], color="tab:cyan", label="cell inner region")
    ax.plot([], [], color="tab:red", label="cell outer region (every other cell)")
    ax.set_xlabel("tract x [pixels]")
    ax.set_ylabel("tract y [pixels]")
    ax.set_aspect("equal")
    ax.set_title(title)


def plot_patch_layout(patch: Patch, path: str | os.PathLike[str], *, zoom_cells: int = 3) -> str:
    """Draw a patch's cells (paper Fig. 7) and write a PNG.

    Left: the whole patch, with every cell's inner region outlined in cyan, the outer
    region of every other cell in red and the patch inner region shaded grey. Right: a
    zoom on the lower-left corner spanning ``zoom_cells`` cells.

    Parameters
    ----------
    patch : Patch
        The patch to draw.
    path : path-like
        Output PNG file.
    zoom_cells : int
        Width of the zoomed panel, in cells.

    Returns
    -------
    str
        The path written.
    """
    cfg = patch.config
    fig = Figure(figsize=(12, 6), layout="constrained")  # no pyplot: no global figure state
    ax_full, ax_zoom = fig.subplots(1, 2)
    outer = patch.outer_bbox
    _draw(ax_full, patch, f"tract {patch.tract.id}, patch {patch.index}")
    ax_full.set_xlim(outer.x_start - 0.5, outer.x_stop - 0.5)
    ax_full.set_ylim(outer.y_start - 0.5, outer.y_stop - 0.5)
    ax_full.legend(loc="upper right", fontsize="small", framealpha=0.9)
    _draw(ax_zoom, patch, "lower-left corner")
    span = zoom_cells * cfg.cell_inner
    ax_zoom.set_xlim(outer.x_start - 0.5, outer.x_start + span)
    ax_zoom.set_ylim(outer.y_start - 0.5, outer.y_start + span)
    fig.suptitle(
        f"cells: inner {cfg.cell_inner} px, border {cfg.cell_border} px, "
        f"{cfg.cells_per_patch} x {cfg.cells_per_patch} inner cells per patch"
    )
    fig.savefig(path, dpi=90)
    return os.fspath(path)
