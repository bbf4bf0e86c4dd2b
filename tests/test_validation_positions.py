"""Validation where objects really are: with ``object_offset`` each object falls at a
random position of its cell (not on the centre pixel, where ``cell.psf`` was drawn) and is
measured with the PSF the library serves there, ``cell.psf_at``."""

from __future__ import annotations

import numpy as np
import pytest

from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.pipelines.validation import stamp_pairs
from cellcoadd.pipelines.validation.bias_presets import TABLE_OBJECT_OFFSET, row_settings
from cellcoadd.pipelines.validation.shear_validation import validate_shear
from cellcoadd.pipelines.validation.validation_settings import (
    ValidationSettings,
    largest_cell_inner,
    offset_cell,
    stamp_cell,
    stamp_size_for_offset,
)
from cellcoadd.sim import SimConfig

OFFSET = 5.0


def _settings(**kwargs: object) -> ValidationSettings:
    size = stamp_size_for_offset(SimConfig(), 0.2, 5, OFFSET)
    return ValidationSettings(
        object_offset=OFFSET, sim=SimConfig(stamp_size=size), snr=1e4, **kwargs
    )


def test_positions_are_random_in_the_square_and_shared_by_ring_partners():
    settings = _settings(seed=3)
    offsets = np.array([stamp_pairs.object_position(settings, i) for i in range(200)])
    assert np.all(np.abs(offsets) <= OFFSET)
    assert np.all(offsets[::2] == offsets[1::2])  # ring partners: one position
    assert np.abs(offsets[::2]).max() > 0.9 * OFFSET and len(np.unique(offsets[::2, 0])) == 100
    # every sub-pixel phase of the coadd grid
    phases = (offsets[::2] + 0.5) % 1.0
    assert np.histogram(phases[:, 0], bins=4, range=(0, 1))[0].min() > 10
    assert stamp_pairs.object_position(ValidationSettings(), 7) == (0.0, 0.0)


def test_the_moved_cell_keeps_its_size_and_puts_the_object_where_asked():
    settings = _settings()
    centred = stamp_cell(settings)
    assert settings.cell_inner == largest_cell_inner(SimConfig(), 0.2) == 41
    assert settings.build.psf_phase and settings.build.psf_size == 51  # psf_at, full stamp
    ny, nx = centred.outer_bbox.shape
    for dx, dy in [(3.3, -4.7), (-5.0, 5.0), (0.5, 0.0)]:
        cell, x, y = offset_cell(settings, dx, dy)
        assert cell.outer_bbox.shape == centred.outer_bbox.shape
        # the moved tract's tangent point: ~1e-5 px from the aim, the exact (x, y) used
        assert (x, y) == pytest.approx((nx // 2 + dx, ny // 2 + dy), abs=1e-4)
    with pytest.raises(ValueError, match="coadd mode only"):  # ConfigError, wrapped
        ValidationSettings(mode="multi-epoch", object_offset=OFFSET)


def test_objects_are_measured_with_the_psf_served_where_they_are(monkeypatch):
    settings = _settings(seed=5)
    served = []
    psf_at = CellCoadd.psf_at

    def recording(self: CellCoadd, x: float, y: float, **kwargs: object) -> np.ndarray:
        served.append((x, y))
        return psf_at(self, x, y, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(CellCoadd, "psf_at", recording)
    pair = stamp_pairs.measure_pair(settings, 1)
    dx, dy = stamp_pairs.object_position(settings, 1)
    centre = settings.cell_inner // 2 + settings.cell_border
    assert served == [pytest.approx((centre + dx, centre + dy), abs=1e-4)] * 2  # +g and -g
    assert pair.n_inputs == settings.sim.n_epochs
    assert all(pair.plus[t]["flags"][0] == 0 for t in pair.plus)


def test_a_short_run_at_random_positions_is_unbiased_and_the_table_rows_use_them():
    result = validate_shear(
        "coadd", n_objects=4, snr=1e4, seed=2, progress=False, object_offset=OFFSET
    )
    assert result["settings"]["object_offset"] == OFFSET and result["n_used"] == 4
    # 2 rings: a rough error; the precision runs are in docs/validation.md
    assert abs(result["m1"]) < 3 * result["m1_err"] + 1e-3 and result["m1_err"] < 1e-2
    for row in ("metacal-coadd", "bfd-coadd", "anacal-coadd"):
        assert row_settings(row, "high-snr")["object_offset"] == TABLE_OBJECT_OFFSET
    assert "object_offset" not in row_settings("metacal-multi-epoch", "high-snr")
    assert row_settings("metacal-coadd")["object_offset"] == 0.0
