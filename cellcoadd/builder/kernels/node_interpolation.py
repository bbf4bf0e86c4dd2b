"""Separable piecewise-cubic interpolation from the nodes of a coarse grid to every pixel.

The pixel mapping (:mod:`cellcoadd.builder.mapping`) evaluates the exact WCS chain on a
coarse grid and interpolates it to pixels with four Lagrange weights per axis and
position; this is that interpolation, rows first, then columns.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def interpolate_nodes(
    node_values: np.ndarray,
    rows_first: np.ndarray,
    rows_weights: np.ndarray,
    cols_first: np.ndarray,
    cols_weights: np.ndarray,
) -> np.ndarray:
    """Separable interpolation of ``node_values`` (nodes y, nodes x): rows, then columns.

    Parameters
    ----------
    node_values : ndarray, shape (n_nodes_y, n_nodes_x), float64
        Values at the grid nodes.
    rows_first, cols_first : ndarray, shape (n_rows,), (n_cols,), int64
        First of the four nodes each output row (column) uses.
    rows_weights, cols_weights : ndarray, shape (n_rows, 4), (n_cols, 4), float64
        Their weights.

    Returns
    -------
    ndarray, shape (n_rows, n_cols), float64
        ``out[i, j] = sum_m cols_weights[j, m] * (sum_n rows_weights[i, n] *
        node_values[rows_first[i] + n, cols_first[j] + m])``, each four-term sum as
        ``(w0 v0 + w1 v1) + (w2 v2 + w3 v3)``.
    """
    n_rows, n_cols = rows_first.size, cols_first.size
    partial = np.empty((n_rows, node_values.shape[1]))
    for i in range(n_rows):
        j = rows_first[i]
        for k in range(node_values.shape[1]):
            partial[i, k] = (
                rows_weights[i, 0] * node_values[j, k] + rows_weights[i, 1] * node_values[j + 1, k]
            ) + (
                rows_weights[i, 2] * node_values[j + 2, k]
                + rows_weights[i, 3] * node_values[j + 3, k]
            )
    out = np.empty((n_rows, n_cols))
    for i in range(n_rows):
        for col in range(n_cols):
            k = cols_first[col]
            out[i, col] = (
                cols_weights[col, 0] * partial[i, k] + cols_weights[col, 1] * partial[i, k + 1]
            ) + (
                cols_weights[col, 2] * partial[i, k + 2] + cols_weights[col, 3] * partial[i, k + 3]
            )
    return out


__all__ = ["interpolate_nodes"]
