"""The jackknife never splits ring partners (any number of objects, odd included), and its
errors then agree with the scatter of many independent runs."""

from __future__ import annotations

import numpy as np
import pytest

from cellcoadd.errors import ShearError
from cellcoadd.shear.response import group_ranks, paired_shear_bias

TRUE_G = 0.02


def _shear_of(sums: np.ndarray) -> np.ndarray:
    """Mean shear of summed ``(e1, e2, R11, R22)`` terms, as AnaCal's."""
    return sums[0:2] / sums[2:4]


def _ring_terms(rng: np.random.Generator, n_objects: int) -> np.ndarray:
    """Paired terms of ``n_objects`` objects, objects ``2k, 2k + 1`` ring partners: the
    second's intrinsic shape is the first's turned by 90 degrees (``-e``), so shape noise
    cancels in each ring (``c``); their noise is shared in part, so their ``m`` errors are
    correlated (as two renderings of one galaxy on one noise field)."""
    n_rings = -(-n_objects // 2)
    shape = np.repeat(rng.normal(0.0, 0.25, (n_rings, 2)), 2, axis=0) * np.tile(
        [[1.0], [-1.0]], (n_rings, 1)
    )
    shared = np.repeat(rng.normal(0.0, 0.02, (n_rings, 2)), 2, axis=0)
    own = rng.normal(0.0, 0.01, (2 * n_rings, 2))
    response = 1.0 + np.repeat(rng.normal(0.0, 0.3, n_rings), 2) + 0.5 * shape[:, 0]
    noise_m = np.repeat(rng.normal(0.0, 0.004, n_rings), 2) + rng.normal(0.0, 0.002, 2 * n_rings)
    members = []
    for sign in (1.0, -1.0):
        e1 = shape[:, 0] + response * sign * TRUE_G + shared[:, 0] + own[:, 0] + sign * noise_m
        e2 = shape[:, 1] + shared[:, 1] + own[:, 1]
        members.append(np.stack([e1, e2, response, response], axis=1))
    return np.hstack(members)[:n_objects]


def _run(terms: np.ndarray, group) -> dict[str, float]:
    return paired_shear_bias(terms, 4, _shear_of, TRUE_G, n_blocks=100, group=group)


def test_ring_partners_stay_together_whatever_the_number_of_rows():
    assert group_ranks(5, 2).tolist() == [0, 0, 1, 1, 2]  # odd: the last alone
    # failed objects dropped (index 3 and 6 missing): partners keyed by index // 2
    index = np.array([0, 1, 2, 4, 5, 7, 8])
    assert group_ranks(len(index), index // 2).tolist() == [0, 0, 1, 2, 2, 3, 4]
    with pytest.raises(ShearError, match="non-decreasing"):
        group_ranks(3, np.array([1, 0, 2]))
    with pytest.raises(ShearError, match="non-decreasing"):
        group_ranks(3, np.array([0, 1]))


def test_jackknife_errors_with_99_objects_match_the_scatter_of_independent_runs():
    """N = 99 (odd): the errors with ring partners kept together equal the direct
    estimate (the scatter of 400 independent runs) within their statistical precision;
    those that split partners (each row alone) are far off for ``c1``."""
    rng = np.random.default_rng(2024)
    n_objects, n_runs = 99, 400
    index = np.arange(n_objects)
    runs = [_ring_terms(rng, n_objects) for _ in range(n_runs)]
    kept = [_run(terms, index // 2) for terms in runs]
    for name in ("m1", "c1", "c2"):
        direct = np.std([run[name] for run in kept], ddof=1)
        estimated = np.sqrt(np.mean([run[f"{name}_err"] ** 2 for run in kept]))
        # 400 runs: the direct scatter is known to ~4%, the jackknife's mean better
        assert estimated == pytest.approx(direct, rel=0.12), name
    # split partners: m1_err too low (their errors are correlated), c1_err far too high
    split = [_run(terms, 1) for terms in runs[:100]]
    direct = {name: np.std([run[name] for run in kept], ddof=1) for name in ("m1", "c1")}
    assert np.sqrt(np.mean([run["m1_err"] ** 2 for run in split])) < 0.85 * direct["m1"]
    assert np.mean([run["c1_err"] for run in split]) > 4 * direct["c1"]
