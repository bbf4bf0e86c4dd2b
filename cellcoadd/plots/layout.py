"""Patch layout figure in the style of the paper's Fig. 7."""

from __future__ import annotations

import os
from typing import Any

from cellcoadd.geometry.box import Box
from cellcoadd.geometry.tract import Cell, Patch
from cellcoadd.plots import style


def _rectangle(box: Box, **options: Any) -> Any:
    from matplotlib.patches import Rectangle

    # box edges sit half a pixel outside the first and last pixel centres
    return Rectangle((box.x_start - 0.5, box.y_start - 0.5), box.nx, box.ny, **options)


def _union(boxes: list[Box]) -> Box:
    return Box(
        x_start=min(b.x_start for b in boxes),
        x_stop=max(b.x_stop for b in boxes),
        y_start=min(b.y_start for b in boxes),
        y_stop=max(b.y_stop for b in boxes),
    )


def _drawn_outer(patch: Patch) -> list[Cell]:
    """Every other cell in x and y, counted from the patch's lower-left cell (so the corner
    cell is one of them), as in the paper's figure."""
    x0 = min(c.index[0] for c in patch.cells)
    y0 = min(c.index[1] for c in patch.cells)
    return [c for c in patch.cells if (c.index[0] - x0) % 2 == 0 and (c.index[1] - y0) % 2 == 0]


def _draw(ax: Any, patch: Patch) -> None:
    ax.add_patch(_rectangle(patch.inner_bbox, color=style.PATCH, zorder=0, linewidth=0))
    for cell in patch.cells:
        ax.add_patch(
            _rectangle(cell.inner_bbox, fill=False, edgecolor=style.INNER, linewidth=style.LINE)
        )
    for cell in _drawn_outer(patch):
        ax.add_patch(
            _rectangle(cell.outer_bbox, fill=False, edgecolor=style.OUTER, linewidth=style.LINE)
        )
    ax.set_xlabel("tract x [pixels]")
    ax.set_ylabel("tract y [pixels]")
    ax.set_aspect("equal")


def _limits(ax: Any, box: Box, margin: float) -> None:
    ax.set_xlim(box.x_start - 0.5 - margin, box.x_stop - 0.5 + margin)
    ax.set_ylim(box.y_start - 0.5 - margin, box.y_stop - 0.5 + margin)


def _dimension(ax: Any, start: float, stop: float, at: float, text: str) -> None:
    """A horizontal double arrow from ``start`` to ``stop`` (pixel edges) at height ``at``,
    labelled just above it."""
    ax.annotate(
        "", xy=(stop, at), xytext=(start, at), arrowprops={"arrowstyle": "<->", "linewidth": 0.9}
    )
    ax.annotate(
        text,
        xy=((start + stop) / 2, at),
        xytext=(0, 3),
        textcoords="offset points",
        ha="center",
        va="bottom",
        fontsize="small",
    )


def patch_layout_figure(patch: Patch, *, zoom_cells: int = 3) -> Any:
    """The figure :func:`plot_patch_layout` writes (a :class:`matplotlib.figure.Figure`).

    The left panel spans every cell's outer region; the right one zooms on the patch's
    lower-left cell, its inner and outer regions drawn thick, with their sizes.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch as LegendPatch

    cfg = patch.config
    fig = style.figure(13.0, 6.9)
    ax_full, ax_zoom = fig.subplots(1, 2)
    everything = _union([c.outer_bbox for c in patch.cells])
    _draw(ax_full, patch)
    _limits(ax_full, everything, 0.35 * cfg.cell_border)
    ax_full.set_title(f"tract {patch.tract.id}, patch {patch.index}: every cell")

    corner = min(patch.cells, key=lambda c: (c.index[1], c.index[0]))
    outer, inner = corner.outer_bbox, corner.inner_bbox
    span = zoom_cells * cfg.cell_inner
    zoom = Box(
        x_start=outer.x_start,
        x_stop=outer.x_start + span,
        y_start=outer.y_start,
        y_stop=outer.y_start + span,
    )
    _draw(ax_zoom, patch)
    ax_zoom.add_patch(_rectangle(outer, facecolor=style.OUTER, alpha=0.08, linewidth=0))
    ax_zoom.add_patch(_rectangle(outer, fill=False, edgecolor=style.OUTER, linewidth=2.2))
    ax_zoom.add_patch(_rectangle(inner, fill=False, edgecolor=style.INNER, linewidth=2.2))
    margin = 0.08 * cfg.cell_inner
    _limits(ax_zoom, zoom, margin)
    ax_zoom.set_title(f"lower-left corner: cell {corner.index}")
    below = outer.y_start - 0.5 + 0.3 * cfg.cell_border  # in the border strip
    _dimension(
        ax_zoom, inner.x_start - 0.5, inner.x_stop - 0.5, below, f"inner {cfg.cell_inner} px"
    )
    _dimension(
        ax_zoom,
        outer.x_start - 0.5,
        inner.x_start - 0.5,
        inner.y_start - 0.5 + 0.5 * cfg.cell_inner,
        f"{cfg.cell_border} px",
    )
    ax_zoom.annotate(
        f"outer region of cell {corner.index}",
        xy=(outer.x_stop - 0.5, outer.y_stop - 0.5),
        xytext=(-4, -4),
        textcoords="offset points",
        ha="right",
        va="top",
        fontsize="small",
        color=style.OUTER,
    )
    ax_full.add_patch(
        _rectangle(zoom, fill=False, edgecolor="black", linestyle="--", linewidth=1.0)
    )
    ax_full.annotate(
        "zoomed (right)",
        xy=(zoom.x_start - 0.5, zoom.y_stop - 0.5),
        xytext=(2, 3),
        textcoords="offset points",
        va="bottom",
        fontsize="small",
        bbox={"boxstyle": "round,pad=0.1", "facecolor": "white", "edgecolor": "none"},
    )
    handles = [
        LegendPatch(facecolor=style.PATCH, label="patch inner region"),
        Line2D([], [], color=style.INNER, label="cell inner region"),
        Line2D([], [], color=style.OUTER, label="cell outer region (every other cell)"),
        Line2D([], [], color="black", linestyle="--", label="zoomed area"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=4, frameon=False)
    fig.suptitle(
        f"cells: inner {cfg.cell_inner} px, border {cfg.cell_border} px "
        f"(outer {cfg.cell_inner + 2 * cfg.cell_border} px); {cfg.cells_per_patch} x "
        f"{cfg.cells_per_patch} inner cells per patch, {cfg.patch_border_cells} border "
        f"cell{'s' if cfg.patch_border_cells != 1 else ''} on each side; "
        f'{cfg.pixel_scale:g}"/pixel'
    )
    return fig


@style.styled
def plot_patch_layout(patch: Patch, path: str | os.PathLike[str], *, zoom_cells: int = 3) -> str:
    """Draw a patch's cells (paper Fig. 7) and write a PNG.

    Left: the whole patch, with every cell's inner region outlined in cyan, the outer
    region of every other cell (the lower-left one included) in red and the patch inner
    region shaded grey; the axes span every cell's outer region. Right: a zoom on the
    patch's lower-left cell, ``zoom_cells`` cells wide, its inner and outer regions drawn
    thick with their sizes.

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
    return style.save(patch_layout_figure(patch, zoom_cells=zoom_cells), path)
