"""The coverage figure of a tract run: input depth per cell over the whole tract."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import BoundaryNorm
from matplotlib.figure import Figure
from matplotlib.patches import Patch as LegendPatch
from matplotlib.patches import Rectangle

from cellcoadd.geometry.tract import Tract


def plot_tract_coverage(
    tract: Tract,
    patches: Sequence[dict[str, Any]],
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    dpi: int = 90,
) -> str:
    """Draw the inputs used per cell over a tract, with RA/Dec axes.

    Parameters
    ----------
    tract : Tract
        The tract (its WCS gives the sky axes).
    patches : sequence of dict
        One per patch: ``patch`` ``[px, py]``, ``state`` (``done``, ``failed``,
        ``pending``, ``no_inputs``) and, when built, ``depth``: ``[cx, cy, n_used]`` per
        cell (tract cell indices; only the patch's inner cells are drawn, so each cell
        once).
    path : path-like
        The PNG to write.

    Cells of built patches are coloured by the number of inputs used (0: an empty cell,
    drawn grey with a cross); failed patches are hatched red, patches not built (no
    input, or not yet) are left white; patch boundaries are drawn and labelled.
    """
    cfg = tract.config
    n_cells = cfg.cells_per_tract
    size = cfg.cell_inner
    depth = np.full((n_cells, n_cells), np.nan)
    for item in patches:
        px, py = item["patch"]
        lo_x, lo_y = px * cfg.cells_per_patch, py * cfg.cells_per_patch
        for cx, cy, used in item.get("depth") or []:
            if lo_x <= cx < lo_x + cfg.cells_per_patch and lo_y <= cy < lo_y + cfg.cells_per_patch:
                depth[cy, cx] = used
    top = int(np.nanmax(depth)) if np.isfinite(depth).any() else 1
    top = max(top, 1)
    bounds = np.arange(0.5, top + 1.5) if top <= 12 else np.linspace(0.5, top + 0.5, 13)
    cmap = colormaps["viridis"].with_extremes(under="0.6")  # empty cells
    norm = BoundaryNorm(bounds, cmap.N)
    fig = Figure(figsize=(8.2, 7), layout="constrained")
    ax = fig.add_subplot(projection=tract.wcs)
    extent = (-0.5, n_cells * size - 0.5, -0.5, n_cells * size - 0.5)
    shown = ax.imshow(
        np.ma.masked_invalid(depth), origin="lower", extent=extent, cmap=cmap, norm=norm,
        interpolation="nearest",
    )  # fmt: skip
    empty_y, empty_x = np.nonzero(depth == 0)
    if len(empty_x):
        ax.plot(
            (empty_x + 0.5) * size - 0.5, (empty_y + 0.5) * size - 0.5, "x", color="0.25",
            markersize=max(2.0, 200.0 / n_cells), linestyle="none",
        )  # fmt: skip
    side = cfg.patch_inner
    states: set[str] = set()
    for item in patches:
        px, py = item["patch"]
        state = item.get("state", "done")
        states.add(state)
        x0, y0 = px * side - 0.5, py * side - 0.5
        if state == "failed":
            ax.add_patch(
                Rectangle((x0, y0), side, side, facecolor=(0.85, 0.1, 0.1, 0.35),
                          edgecolor="tab:red", hatch="//", lw=1.5)
            )  # fmt: skip
        ax.text(
            x0 + side / 2, y0 + side / 2, f"patch {px},{py}", ha="center", va="center",
            fontsize="small", color="black",
            bbox={"facecolor": "white", "alpha": 0.6, "edgecolor": "none", "pad": 1.5},
        )  # fmt: skip
    if n_cells <= 120:  # cell boundaries, faint
        for k in range(n_cells + 1):
            ax.axvline(k * size - 0.5, color="0.2", lw=0.3, alpha=0.35)
            ax.axhline(k * size - 0.5, color="0.2", lw=0.3, alpha=0.35)
    for k in range(cfg.patches_per_tract + 1):
        edge = k * side - 0.5
        ax.axvline(edge, color="black", lw=1.0)
        ax.axhline(edge, color="black", lw=1.0)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    lon, lat = ax.coords[0], ax.coords[1]
    lon.set_axislabel("RA (ICRS)")
    lat.set_axislabel("Dec (ICRS)")
    lon.set_ticks(number=4)
    lat.set_ticks(number=4)
    lon.set_ticklabel(exclude_overlapping=True)
    colourbar = fig.colorbar(shown, ax=ax, shrink=0.85, extend="min")
    colourbar.set_label("inputs used per cell")
    if top <= 12:
        colourbar.set_ticks(range(1, top + 1))
    handles = [LegendPatch(facecolor="0.6", label="empty cell (x)")]
    if "failed" in states:
        handles.append(
            LegendPatch(facecolor=(0.85, 0.1, 0.1, 0.35), edgecolor="tab:red", hatch="//",
                        label="failed patch")
        )  # fmt: skip
    if states & {"no_inputs", "pending"}:
        handles.append(LegendPatch(facecolor="white", edgecolor="0.5", label="not built"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.08), ncol=3,
              frameon=False)  # fmt: skip
    ax.set_title(title or f"tract {tract.id}: input depth per cell (patch boundaries in black)")
    fig.savefig(path, dpi=dpi, format="png")  # path may be a temporary name
    return os.fspath(path)
