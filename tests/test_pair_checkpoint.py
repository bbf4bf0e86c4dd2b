"""Shear-validation runs that resume: checkpoints lose and repeat no pair, and a run on a
dask.distributed cluster gives what a local run gives."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from cellcoadd.errors import ConfigError
from cellcoadd.pipelines.validation import shear_validation
from cellcoadd.pipelines.validation.shear_validation import PairCatalogue, run_pairs
from cellcoadd.pipelines.validation.validation_settings import ValidationSettings

# single-epoch metacal: the cheapest pair (~0.2 CPU s)
SETTINGS = ValidationSettings(mode="single", method="metacal", seed=5, snr=(10.0, 50.0))


def _equal(a: PairCatalogue, b: PairCatalogue) -> None:
    np.testing.assert_array_equal(a.index, b.index)
    for name in ("noise_sigma", "snr", "n_inputs"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert list(a.plus) == list(b.plus)
    for t in a.plus:
        assert a.plus[t].tobytes() == b.plus[t].tobytes()
        assert a.minus[t].tobytes() == b.minus[t].tobytes()


@pytest.fixture(scope="module")
def fresh() -> PairCatalogue:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return run_pairs(SETTINGS, 6, progress=False)


def test_a_killed_run_resumes_without_losing_or_repeating_pairs(tmp_path, monkeypatch, fresh):
    path = tmp_path / "run.npz"
    measured: list[int] = []
    real = shear_validation.measure_pairs

    def dies_on_the_third_chunk(settings, indices):
        if len(measured) >= 2:
            raise KeyboardInterrupt("killed")
        measured.extend(indices)
        return real(settings, indices)

    monkeypatch.setattr(shear_validation, "measure_pairs", dies_on_the_third_chunk)
    with pytest.raises(KeyboardInterrupt):
        run_pairs(SETTINGS, 6, chunk_size=1, progress=False, checkpoint=path, checkpoint_every=2)
    saved = PairCatalogue.load(path, SETTINGS)
    assert saved.index.tolist() == [0, 1]

    resumed_indices: list[int] = []

    def counting(settings, indices):
        resumed_indices.extend(indices)
        return real(settings, indices)

    monkeypatch.setattr(shear_validation, "measure_pairs", counting)
    resumed = run_pairs(SETTINGS, 6, chunk_size=2, progress=False, checkpoint=path)
    assert sorted(resumed_indices) == [2, 3, 4, 5]  # only what the file lacked
    _equal(resumed, fresh)
    _equal(PairCatalogue.load(path, SETTINGS), fresh)  # the file holds the whole run
    # a later, longer run extends it; a shorter one reads its part
    resumed_indices.clear()
    _equal(run_pairs(SETTINGS, 4, progress=False, checkpoint=path), fresh.select(0, 4))
    assert resumed_indices == []


def test_a_checkpoint_of_other_settings_is_refused(tmp_path, fresh):
    path = tmp_path / "run.npz"
    fresh.save(path, SETTINGS)
    other = SETTINGS.model_copy(update={"seed": 6})
    with pytest.raises(ConfigError, match="other settings"):
        run_pairs(other, 6, progress=False, checkpoint=path)


def test_a_dask_cluster_run_equals_the_local_run(fresh):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster, distributed.Client(cluster) as client:  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            remote = run_pairs(SETTINGS, 6, scheduler=client, chunk_size=2, progress=False)
    _equal(remote, fresh)
