"""Figures: produced, one style, the expected panels, axes, labels and legends; the patch
layout spans every cell's outer region and its zoom shows the corner cell's own boxes."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
from coadd_factory import make_patch
from matplotlib.image import imread
from matplotlib.patches import Rectangle

from cellcoadd import SkyMap, SkyMapConfig
from cellcoadd.geometry.box import Box
from cellcoadd.plots import (
    plot_cell_planes,
    plot_inputs_map,
    plot_patch_layout,
    plot_stitched,
    style,
)
from cellcoadd.plots.coadd import cell_planes_figure
from cellcoadd.plots.layout import patch_layout_figure

CONFIG = SkyMapConfig(cell_inner=60, cell_border=15, cells_per_patch=3)


def _rectangles(ax, colour: str) -> list[tuple[float, float, float, float]]:
    """(x0, y0, width, height) of the outlined rectangles of ``colour`` in ``ax``."""
    rgba = matplotlib.colors.to_rgba(colour)
    return [
        (p.get_x(), p.get_y(), p.get_width(), p.get_height())
        for p in ax.patches
        if isinstance(p, Rectangle) and not p.get_fill() and p.get_edgecolor() == rgba
    ]


def _drawn(box: Box) -> tuple[float, float, float, float]:
    return (box.x_start - 0.5, box.y_start - 0.5, box.nx, box.ny)


@pytest.mark.parametrize("cells_per_patch", [3, 4])
def test_layout_spans_every_outer_region_and_zooms_on_the_corner_cell(cells_per_patch):
    config = CONFIG.model_copy(update={"cells_per_patch": cells_per_patch})
    patch = SkyMap.from_centers([(60.0, -30.0)], config)[0].patch(1, 1)
    with style.rc():
        fig = patch_layout_figure(patch)
    full, zoom = fig.axes
    (x_lo, x_hi), (y_lo, y_hi) = full.get_xlim(), full.get_ylim()
    for cell in patch.cells:  # nothing is clipped at the plot edge
        outer = cell.outer_bbox
        assert x_lo < outer.x_start - 0.5 and outer.x_stop - 0.5 < x_hi, cell.index
        assert y_lo < outer.y_start - 0.5 and outer.y_stop - 0.5 < y_hi, cell.index
    corner = min(patch.cells, key=lambda c: (c.index[1], c.index[0]))
    # the corner cell's own outer and inner boxes are drawn in the zoom, thick, and fit in it
    thick = [p for p in zoom.patches if isinstance(p, Rectangle) and p.get_linewidth() > 2]
    assert {(p.get_x(), p.get_y(), p.get_width(), p.get_height()) for p in thick} == {
        _drawn(corner.outer_bbox),
        _drawn(corner.inner_bbox),
    }
    assert _drawn(corner.outer_bbox) in _rectangles(full, style.OUTER)
    (zx_lo, zx_hi), (zy_lo, zy_hi) = zoom.get_xlim(), zoom.get_ylim()
    outer = corner.outer_bbox
    assert zx_lo < outer.x_start - 0.5 and outer.x_stop - 0.5 < zx_hi
    assert zy_lo < outer.y_start - 0.5 and outer.y_stop - 0.5 < zy_hi
    assert str(corner.index) in zoom.get_title()
    # every cell's inner region outlined once in the full panel
    assert len(_rectangles(full, style.INNER)) == len(patch.cells)
    assert full.get_xlabel() == "tract x [pixels]" and full.get_ylabel() == "tract y [pixels]"
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[:3] == ["patch inner region", "cell inner region", labels[2]]
    assert labels[2].startswith("cell outer region")


def test_layout_png_is_written_at_the_style_resolution(tmp_path):
    patch = SkyMap.from_centers([(60.0, -30.0)], CONFIG)[0].patch(0, 0)
    path = plot_patch_layout(patch, tmp_path / "layout.png")
    height, width, _ = imread(path).shape
    assert (width, height) == (round(13.0 * style.DPI), round(6.9 * style.DPI))
    # the style was the figure's only: the caller's settings are as they were
    assert matplotlib.rcParams["figure.titlesize"] == matplotlib.rcParamsDefault["figure.titlesize"]


@pytest.fixture(scope="module")
def patch():
    return make_patch(CONFIG, n_noise=2, psf_size=15, arbitrary_bits=False, empty=((6, 6),))


def test_cell_planes_grid_has_sky_axes_colourbars_and_a_mask_legend(patch):
    meta = patch.metadata
    cell = patch.cells[(2, 2)]
    with style.rc():
        fig = cell_planes_figure(
            cell, mask_bits=meta.mask_bits, units=meta.units, zero_point=meta.zero_point
        )
    titles = [ax.get_title() for ax in fig.axes]
    panels = ["image", "noise realization 0 (of 2)", "PSF at the cell centre"]
    panels += ["mask bits (first bit set)", "masked fraction", "inputs"]
    assert all(title in titles for title in panels), titles
    by_title = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    for name in ("image", "mask bits (first bit set)", "masked fraction"):
        ax = by_title[name]
        assert ax.coords[0].get_axislabel() == "RA (ICRS)", name  # WCSAxes: sky axes
    assert by_title["image"].coords[1].get_axislabel() == "Dec (ICRS)"
    grid = [ax.get_subplotspec().get_geometry()[:2] for ax in fig.axes if ax.get_subplotspec()]
    assert (2, 3) in grid  # a 2 x 3 grid, not a strip
    # colourbars: image and noise in the coadd's units, PSF, masked fraction, mask bits
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 5
    bar_labels = {ax.get_ylabel() for ax in bars}
    assert "nJy / pixel" in bar_labels and "log10(PSF flux fraction / pixel)" in bar_labels
    # the mask legend names every bit present, in the coadd's names
    present = [n for n in meta.mask_bits.bits if (cell.mask & meta.mask_bits.value(n)).any()]
    mask_bar = [ax for ax in bars if "none" in [t.get_text() for t in ax.get_yticklabels()]]
    assert len(mask_bar) == 1
    assert [t.get_text() for t in mask_bar[0].get_yticklabels()] == ["none", *present]
    inputs_text = by_title["inputs"].texts[0].get_text()
    assert all(f"{r.visit:>7}" in inputs_text for r in cell.inputs)


def test_plots_write_readable_pngs(patch, tmp_path):
    meta = patch.metadata
    cell_png = plot_cell_planes(
        patch.cells[(2, 2)],
        tmp_path / "cell.png",
        mask_bits=meta.mask_bits,
        units=meta.units,
        zero_point=meta.zero_point,
    )
    height, width, _ = imread(cell_png).shape
    assert width > 1200 and 0.4 < height / width < 0.7  # a grid, not a strip
    assert patch.cells[(6, 6)].is_empty
    empty_png = plot_cell_planes(patch.cells[(6, 6)], tmp_path / "empty.png")
    assert imread(empty_png).std() > 0  # the "empty cell" message, not a blank image
    for plot in (plot_stitched, plot_inputs_map):
        image = imread(plot(patch, tmp_path / f"{plot.__name__}.png"))
        assert image.shape[0] > 400 and np.ptp(image) > 0.5
