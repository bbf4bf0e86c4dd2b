"""Figures of coadds: the stitched patch, one cell's planes, the inputs used per cell."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import AsinhNorm
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import PatchCoadd


def _stretch(values: np.ndarray) -> AsinhNorm:
    """An asinh stretch from the noise level to the bright end (robust to NaN)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return AsinhNorm(linear_width=1.0, vmin=-1.0, vmax=1.0)
    median = float(np.median(finite))
    sigma = 1.4826 * float(np.median(np.abs(finite - median))) or 1.0
    return AsinhNorm(
        linear_width=sigma, vmin=median - 3 * sigma, vmax=float(np.percentile(finite, 99.9))
    )


def _image_axes(ax, values: np.ndarray, title: str, norm=None, cmap: str = "gray_r", extent=None):
    cmap_obj = colormaps[cmap].with_extremes(bad="tab:orange")
    shown = ax.imshow(values, origin="lower", norm=norm, cmap=cmap_obj, extent=extent)
    ax.set_title(title, fontsize="medium")
    return shown


def plot_stitched(patch: PatchCoadd, path: str | os.PathLike[str]) -> str:
    """The patch inner region stitched from cell inner regions, with the cell grid.

    Empty cells (no input covered them) show in orange. Axes are tract pixels.
    """
    image = patch.stitch("image")
    box = patch.patch_inner_bbox
    extent = (box.x_start - 0.5, box.x_stop - 0.5, box.y_start - 0.5, box.y_stop - 0.5)
    fig = Figure(figsize=(7.5, 7), layout="constrained")
    ax = fig.subplots()
    shown = _image_axes(ax, image, "", _stretch(image), extent=extent)
    side = patch.metadata.cell_inner
    for edge in range(box.x_start, box.x_stop + 1, side):
        ax.axvline(edge - 0.5, color="tab:cyan", linewidth=0.6, alpha=0.7)
    for edge in range(box.y_start, box.y_stop + 1, side):
        ax.axhline(edge - 0.5, color="tab:cyan", linewidth=0.6, alpha=0.7)
    meta = patch.metadata
    ax.set_title(
        f"tract {meta.tract} patch {meta.patch} band {meta.band}: stitched cell inner regions"
    )
    ax.set_xlabel("tract x [pixels]")
    ax.set_ylabel("tract y [pixels]")
    fig.colorbar(shown, ax=ax, shrink=0.8, label=meta.units)
    fig.savefig(path, dpi=90)
    return os.fspath(path)


def plot_cell_planes(
    cell: CellCoadd,
    path: str | os.PathLike[str],
    *,
    mask_bits: MaskBits | None = None,
    noise_index: int = 0,
) -> str:
    """One cell: image, a noise realization, PSF (log), mask bits and masked fraction.

    The inner region is outlined on the image panels.
    """
    fig = Figure(figsize=(16, 3.8), layout="constrained")
    axes = fig.subplots(1, 5)
    if cell.is_empty:
        for ax in axes:
            ax.text(0.5, 0.5, "empty cell", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
    else:
        norm = _stretch(cell.image)
        _image_axes(axes[0], cell.image, "image", norm)
        if cell.n_noise:
            _image_axes(axes[1], cell.noise[noise_index], f"noise realization {noise_index}", norm)
        psf = np.clip(cell.psf, cell.psf.max() * 1e-5, None)
        _image_axes(axes[2], np.log10(psf), "PSF (log10)", cmap="viridis")
        bits = mask_bits or MaskBits()
        present = [name for name in bits.bits if (cell.mask & bits.value(name)).any()]
        _image_axes(axes[3], cell.mask, "mask: " + (", ".join(present) or "none"), cmap="tab20")
        shown = _image_axes(axes[4], cell.mfrac, "masked fraction", cmap="magma")
        fig.colorbar(shown, ax=axes[4], shrink=0.8)
        inner, outer = cell.inner_bbox, cell.outer_bbox
        for ax in (axes[0], axes[1], axes[3], axes[4]):
            ax.add_patch(
                Rectangle(
                    (inner.x_start - outer.x_start - 0.5, inner.y_start - outer.y_start - 0.5),
                    inner.nx,
                    inner.ny,
                    fill=False,
                    edgecolor="tab:cyan",
                    linewidth=0.8,
                )
            )
    used = cell.n_used
    fig.suptitle(
        f"cell {cell.index} of tract {cell.tract}: {used} input(s) used, "
        f"{len(cell.inputs) - used} rejected"
    )
    fig.savefig(path, dpi=80)
    return os.fspath(path)


def plot_inputs_map(patch: PatchCoadd, path: str | os.PathLike[str]) -> str:
    """Per cell: visits used, and visits rejected because a detector edge crossed the cell.

    A visit counts as used when one of its detectors was used, as rejected for an edge
    when none was used and at least one was rejected as ``"edge"``.
    """
    indices = list(patch.cells)
    xs = sorted({i[0] for i in indices})
    ys = sorted({i[1] for i in indices})
    used = np.full((len(ys), len(xs)), np.nan)
    edge = np.full((len(ys), len(xs)), np.nan)
    for (cx, cy), cell in patch.cells.items():
        by_visit: dict[int, set[str]] = {}
        for record in cell.inputs:
            by_visit.setdefault(record.visit, set()).add(record.status)
        counts = Counter(
            "used" if "used" in statuses else ("edge" if "edge" in statuses else "other")
            for statuses in by_visit.values()
        )
        used[ys.index(cy), xs.index(cx)] = counts["used"]
        edge[ys.index(cy), xs.index(cx)] = counts["edge"]
    fig = Figure(figsize=(11, 5), layout="constrained")
    axes = fig.subplots(1, 2)
    extent = (xs[0] - 0.5, xs[-1] + 0.5, ys[0] - 0.5, ys[-1] + 0.5)
    for ax, values, title, cmap in (
        (axes[0], used, "visits used per cell", "viridis"),
        (axes[1], edge, "visits rejected (detector edge)", "magma"),
    ):
        shown = ax.imshow(values, origin="lower", extent=extent, cmap=cmap)
        for (row, col), value in np.ndenumerate(values):
            ax.text(xs[col], ys[row], f"{value:.0f}", ha="center", va="center", color="w")
        inner = patch.inner_cell_indices
        x0 = min(i[0] for i in inner) - 0.5
        y0 = min(i[1] for i in inner) - 0.5
        n = patch.metadata.skymap_config.cells_per_patch
        ax.add_patch(
            Rectangle((x0, y0), n, n, fill=False, edgecolor="w", linestyle="--", linewidth=1.2)
        )
        ax.set_title(title)
        ax.set_xlabel("cell x index")
        ax.set_ylabel("cell y index")
        fig.colorbar(shown, ax=ax, shrink=0.8)
    fig.suptitle("inputs per cell (dashed: patch inner cells)")
    fig.savefig(path, dpi=80)
    return os.fspath(path)
