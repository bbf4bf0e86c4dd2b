"""Figures of coadds: the stitched patch, one cell's planes, the inputs used per cell.

Image panels have sky axes (RA, Dec through astropy's WCSAxes) from the cells' WCS,
colourbars labelled with the coadd's pixel units (from its metadata), and the mask is
drawn one colour per bit with a legend.
"""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import AsinhNorm, ListedColormap, Normalize
from matplotlib.patches import Rectangle

from cellcoadd.geometry.wcs_utils import shifted_wcs
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.maskbits import MaskBits
from cellcoadd.model.patch_coadd import PatchCoadd
from cellcoadd.plots import style


def unit_label(units: str | None, zero_point: float | None = None) -> str:
    """Colourbar label of the image plane from the metadata's ``units``.

    ``"count"`` -> ``"counts / pixel (AB zero point 30)"``, ``"nJy"`` -> ``"nJy / pixel"``;
    other (older, free-text) units are shown as they are.

    Examples
    --------
    >>> unit_label("nJy"), unit_label("count", 30.0)
    ('nJy / pixel', 'counts / pixel (AB zero point 30)')
    """
    if not units:
        return "pixel value"
    if units in ("count", "counts", "ct"):
        suffix = f" (AB zero point {zero_point:g})" if zero_point is not None else ""
        return f"counts / pixel{suffix}"
    if " " in units:  # free text of older files, already a description
        return units
    return f"{units} / pixel"


def _sky_axes(ax, *, ra: bool = True, dec: bool = True) -> None:
    """Label the RA/Dec axes of a WCSAxes panel (or hide their labels)."""
    lon, lat = ax.coords[0], ax.coords[1]
    lon.set_axislabel("RA (ICRS)" if ra else "")
    lat.set_axislabel("Dec (ICRS)" if dec else "")
    lon.set_ticklabel(exclude_overlapping=True)
    lat.set_ticklabel(exclude_overlapping=True)
    lon.set_ticks(number=3)
    lat.set_ticks(number=4)
    if not dec:
        lat.set_ticklabel_visible(False)


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


def _sparse_ticks(norm: Normalize) -> list[float]:
    """A few round colourbar ticks that do not overlap on an asinh (or linear) bar."""
    vmin, vmax = float(norm.vmin or 0.0), float(norm.vmax or 0.0)
    span = max(abs(vmin), abs(vmax), 1e-30)
    candidates = {0.0}
    for power in range(int(np.floor(np.log10(span))) - 3, int(np.floor(np.log10(span))) + 1):
        for mantissa in (1, 2, 5):
            candidates.update({mantissa * 10.0**power, -mantissa * 10.0**power})
    inside = sorted(c for c in candidates if vmin <= c <= vmax)
    ticks: list[float] = []
    for value in sorted(inside, key=lambda v: (v != 0.0, -abs(v))):  # 0, then large first
        position = float(norm(value))
        if all(abs(position - float(norm(t))) > 0.1 for t in ticks):
            ticks.append(value)
    return sorted(ticks)


def _colourbar(fig, shown, ax, label: str, norm: Normalize | None = None):
    bar = fig.colorbar(shown, ax=ax, shrink=0.85, pad=0.02)
    bar.set_label(label)
    if isinstance(norm, AsinhNorm):
        bar.set_ticks(_sparse_ticks(norm))
        bar.ax.yaxis.set_major_formatter("{x:g}")
        bar.ax.minorticks_off()
    return bar


def _image_axes(ax, values: np.ndarray, title: str, norm=None, cmap: str = "gray_r", extent=None):
    cmap_obj = colormaps[cmap].with_extremes(bad=style.NO_DATA)
    shown = ax.imshow(values, origin="lower", norm=norm, cmap=cmap_obj, extent=extent)
    ax.set_title(title)
    return shown


def _stitched_wcs(patch: PatchCoadd):
    """WCS of the stitched array (array pixel (0, 0) is the patch inner box's corner)."""
    box = patch.patch_inner_bbox
    for cell in patch.cells.values():
        outer = cell.outer_bbox
        return shifted_wcs(cell.wcs, box.x_start - outer.x_start, box.y_start - outer.y_start)
    return None


@style.styled
def plot_stitched(patch: PatchCoadd, path: str | os.PathLike[str]) -> str:
    """The patch inner region stitched from cell inner regions, on RA/Dec axes, with the
    cell grid. Empty cells (no input covered them) show in orange.
    """
    image = patch.stitch("image")
    box = patch.patch_inner_bbox
    meta = patch.metadata
    wcs = _stitched_wcs(patch)
    fig = style.figure(8.0, 7.0)
    ax = fig.add_subplot(projection=wcs) if wcs is not None else fig.add_subplot()
    norm = _stretch(image)
    shown = _image_axes(ax, image, "", norm)
    side = meta.cell_inner
    for edge in range(0, box.nx + 1, side):
        ax.axvline(edge - 0.5, color=style.INNER, linewidth=0.6, alpha=0.7)
    for edge in range(0, box.ny + 1, side):
        ax.axhline(edge - 0.5, color=style.INNER, linewidth=0.6, alpha=0.7)
    ax.set_xlim(-0.5, box.nx - 0.5)
    ax.set_ylim(-0.5, box.ny - 0.5)
    scale = meta.skymap_config.pixel_scale
    ax.set_title(
        f"tract {meta.tract} patch {meta.patch} band {meta.band}: stitched cell inner regions\n"
        f'(cyan: cells of {side} px = {side * scale:g}"; tract pixels x {box.x_start}-'
        f"{box.x_stop - 1}, y {box.y_start}-{box.y_stop - 1}; orange: no data)",
        fontsize="medium",
        pad=14,
    )
    if wcs is not None:
        _sky_axes(ax)
    else:
        ax.set_xlabel("x [pixels]")
        ax.set_ylabel("y [pixels]")
    _colourbar(fig, shown, ax, unit_label(meta.units, getattr(meta, "zero_point", None)), norm)
    return style.save(fig, path)


def _mask_categories(mask: np.ndarray, bits: MaskBits) -> tuple[np.ndarray, list[str]]:
    """Per pixel, 1 + the index of its first set bit among the bits present (0: none)."""
    present = [name for name in bits.bits if (mask & bits.value(name)).any()]
    categories = np.zeros(mask.shape, dtype=int)
    for number, name in reversed(list(enumerate(present, 1))):
        categories[(mask & bits.value(name)) != 0] = number
    return categories, present


def _outline_inner(ax, cell: CellCoadd) -> None:
    inner, outer = cell.inner_bbox, cell.outer_bbox
    ax.add_patch(
        Rectangle(
            (inner.x_start - outer.x_start - 0.5, inner.y_start - outer.y_start - 0.5),
            inner.nx,
            inner.ny,
            fill=False,
            edgecolor=style.INNER,
            linewidth=style.LINE,
        )
    )


def _inputs_text(cell: CellCoadd, rows: int = 14) -> str:
    """The cell's inputs as a small monospace table (the first ``rows``, used first)."""
    lines = [f"{'visit':>7} {'det':>4}  {'status':<16}{'weight':>9}"]
    records = sorted(cell.inputs, key=lambda r: (r.status != "used", r.visit, r.detector))
    for record in records[:rows]:
        weight = f"{record.weight:.3g}" if record.weight > 0 else "-"
        lines.append(f"{record.visit:>7} {record.detector:>4}  {record.status:<16}{weight:>9}")
    if len(cell.inputs) > rows:
        lines.append(f"... and {len(cell.inputs) - rows} more")
    return "\n".join(lines)


def cell_planes_figure(
    cell: CellCoadd,
    *,
    mask_bits: MaskBits | None = None,
    noise_index: int = 0,
    units: str | None = None,
    zero_point: float | None = None,
):
    """The figure :func:`plot_cell_planes` writes (a :class:`matplotlib.figure.Figure`).

    A 2 x 3 grid: image, noise realization ``noise_index`` and PSF on the first row; mask
    bits, masked fraction and the list of inputs on the second.
    """
    used = cell.n_used
    if cell.is_empty:  # a message and the reasons its inputs were rejected
        rows = min(len(cell.inputs), 8)
        fig = style.figure(7.0, 1.4 + 0.22 * (rows + 2) if rows else 1.4)
        fig.suptitle(f"cell {cell.index} of tract {cell.tract}: empty, no input covers it")
        ax = fig.add_subplot()
        ax.set_axis_off()
        if cell.inputs:
            ax.set_title(f"inputs ({len(cell.inputs)}, all rejected)")
            text = _inputs_text(cell, rows=rows)
            ax.text(0.0, 1.0, text, family="monospace", va="top", fontsize="small")
        else:
            ax.set_title("no exposure overlaps it")
        return fig
    fig = style.figure(13.5, 6.9, compressed=True)
    label = unit_label(units, zero_point)
    fig.suptitle(
        f"cell {cell.index} of tract {cell.tract}: {used} input(s) used, "
        f"{len(cell.inputs) - used} rejected (cyan: inner region; orange: no data)"
    )
    grid = fig.add_gridspec(2, 3)
    sky = {"projection": cell.wcs}
    ax_image = fig.add_subplot(grid[0, 0], **sky)
    ax_noise = fig.add_subplot(grid[0, 1], **sky)
    ax_psf = fig.add_subplot(grid[0, 2])
    ax_mask = fig.add_subplot(grid[1, 0], **sky)
    ax_mfrac = fig.add_subplot(grid[1, 1], **sky)
    ax_inputs = fig.add_subplot(grid[1, 2])

    norm = _stretch(cell.image)
    shown = _image_axes(ax_image, cell.image, "image", norm)
    _colourbar(fig, shown, ax_image, label, norm)
    if cell.n_noise:
        title = f"noise realization {noise_index} (of {cell.n_noise})"
        shown = _image_axes(ax_noise, cell.noise[noise_index], title, norm)
        _colourbar(fig, shown, ax_noise, label, norm)
    else:
        ax_noise.set_title("no noise realization")

    psf = np.clip(cell.psf, cell.psf.max() * 1e-5, None)
    half = cell.psf.shape[0] // 2
    shown = _image_axes(
        ax_psf,
        np.log10(psf),
        "PSF at the cell centre",
        cmap="viridis",
        extent=(-half - 0.5, half + 0.5, -half - 0.5, half + 0.5),
    )
    ax_psf.set_xlabel("x offset [pixels]")
    ax_psf.set_ylabel("y offset [pixels]")
    ax_psf.set_aspect("equal")
    _colourbar(fig, shown, ax_psf, "log10(PSF flux fraction / pixel)")

    categories, present = _mask_categories(cell.mask, mask_bits or MaskBits())
    colours: list[str] = [
        "white",
        *(style.BIT_COLOURS[i % len(style.BIT_COLOURS)] for i in range(len(present))),
    ]
    shown = ax_mask.imshow(
        categories,
        origin="lower",
        cmap=ListedColormap(colours),
        vmin=-0.5,
        vmax=len(present) + 0.5,
        interpolation="nearest",
    )
    ax_mask.set_title("mask bits (first bit set)")
    # the legend of the bits is a discrete colourbar: one labelled step per bit present
    bar = fig.colorbar(shown, ax=ax_mask, shrink=0.85, pad=0.02)
    bar.set_ticks(range(len(present) + 1), labels=["none", *present])
    bar.ax.tick_params(length=0)
    bar.ax.minorticks_off()

    shown = _image_axes(ax_mfrac, cell.mfrac, "masked fraction", cmap="magma")
    shown.set_clim(0.0, max(float(np.nanmax(cell.mfrac)), 1e-3))
    _colourbar(fig, shown, ax_mfrac, "fraction of the weight masked")

    ax_inputs.set_axis_off()
    ax_inputs.set_title("inputs")
    ax_inputs.text(
        0.0,
        1.0,
        _inputs_text(cell),
        transform=ax_inputs.transAxes,
        family="monospace",
        fontsize="small",
        va="top",
        ha="left",
    )
    for ax in (ax_image, ax_noise, ax_mask, ax_mfrac):
        _sky_axes(ax)
        _outline_inner(ax, cell)
    for ax in (ax_noise, ax_mfrac):  # the column's left neighbour names the axis
        ax.coords[1].set_axislabel("")
    return fig


@style.styled
def plot_cell_planes(
    cell: CellCoadd,
    path: str | os.PathLike[str],
    *,
    mask_bits: MaskBits | None = None,
    noise_index: int = 0,
    units: str | None = None,
    zero_point: float | None = None,
) -> str:
    """One cell: image, a noise realization, PSF (log), mask bits, masked fraction and its
    inputs, in a 2 x 3 grid.

    Image panels are on RA/Dec axes (the cell's WCS), the PSF on pixel offsets from its
    centre; every panel has a colourbar with units (``units``, ``zero_point``: the
    coadd metadata's), the mask a legend of its bits. The inner region is outlined.
    """
    figure = cell_planes_figure(
        cell, mask_bits=mask_bits, noise_index=noise_index, units=units, zero_point=zero_point
    )
    return style.save(figure, path)


@style.styled
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
    top = max(float(np.nanmax(used + edge)), 1.0)
    fig = style.figure(11.0, 5.0)
    axes = fig.subplots(1, 2)
    extent = (xs[0] - 0.5, xs[-1] + 0.5, ys[0] - 0.5, ys[-1] + 0.5)
    for ax, values, title, cmap in (
        (axes[0], used, "visits used per cell", "viridis"),
        (axes[1], edge, "visits rejected (a CCD edge crosses the cell)", "magma"),
    ):
        norm = Normalize(0.0, top)
        colormap = colormaps[cmap]
        shown = ax.imshow(values, origin="lower", extent=extent, cmap=colormap, norm=norm)
        for (row, col), value in np.ndenumerate(values):
            red, green, blue, _ = colormap(norm(value))
            luminance = 0.299 * red + 0.587 * green + 0.114 * blue
            ax.text(
                xs[col],
                ys[row],
                f"{value:.0f}",
                ha="center",
                va="center",
                color="black" if luminance > 0.5 else "white",
                fontsize="medium",
                fontweight="bold",
            )
        inner = patch.inner_cell_indices
        x0 = min(i[0] for i in inner) - 0.5
        y0 = min(i[1] for i in inner) - 0.5
        n = patch.metadata.skymap_config.cells_per_patch
        ax.add_patch(
            Rectangle((x0, y0), n, n, fill=False, edgecolor=style.INNER, linestyle="--", lw=2)
        )
        ax.set_title(title)
        ax.set_xlabel("cell x index (tract)")
        ax.set_ylabel("cell y index (tract)")
        ax.set_xticks(xs)
        ax.set_yticks(ys)
        _colourbar(fig, shown, ax, "visits")
    fig.suptitle("inputs per cell (dashed: the patch's inner cells)")
    return style.save(fig, path)
