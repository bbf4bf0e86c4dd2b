"""Ensemble metacal responses, calibrated mean shear and multiplicative bias.

Input catalogues are the outputs of :func:`cellcoadd.shear.metacal.measure_metacal`: for
each metacal type a structured array of :data:`~cellcoadd.shear.metacal.SHAPE_DTYPE`, one
row per object, rows aligned across types (either one such mapping, or a list of
per-object mappings, which :func:`stack_results` concatenates).

Estimators (Sheldon & Huff 2017; paper section 4.2)
----------------------------------------------------
With ``S_t`` the objects selected on the measurements of type ``t`` (``flags == 0`` and the
optional cuts) and ``e`` the ``(g1, g2)`` estimator:

* ``<e> = mean of e_noshear over S_noshear``;
* shear response ``R_ij = mean over S_noshear of (e_i[jp] - e_i[jm]) / (2 step)``, using the
  objects of ``S_noshear`` whose four sheared measurements all succeeded;
* selection response ``R_S_ij = (<e_i[noshear]>_{S_jp} - <e_i[noshear]>_{S_jm}) / (2 step)``:
  the *noshear* shapes averaged over the objects selected on the ``jp`` / ``jm``
  measurements (each set also needs a valid noshear shape). With no failures and no cuts
  it is exactly zero;
* calibrated mean shear ``g = (R + R_S)^-1 <e>``.

Errors are delete-one-block jackknife over objects (contiguous blocks in input order);
objects whose estimates are correlated (ring partners: an object and its 90-degree-rotated
copy) are kept in one block by giving them one group key (:data:`Groups`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cellcoadd.errors import CellCoaddRangeError, ShearError
from cellcoadd.shear.metacal import METACAL_TYPES

Results = Mapping[str, np.ndarray] | Sequence[Mapping[str, np.ndarray]]
#: A selection maps one catalogue (structured array) to a boolean mask of kept objects.
Selection = Callable[[np.ndarray], np.ndarray]
#: Rows a jackknife removes together: an int ``g``, each run of ``g`` consecutive rows; or
#: one integer key per row, non-decreasing, rows of equal key together (ring partners
#: ``2k, 2k + 1`` of a catalogue whose failed objects were dropped: ``index // 2``).
Groups = int | np.ndarray

_SHEARED = (("1p", "1m"), ("2p", "2m"))
# Columns of the per-object sums: count and <e> on noshear (3), count and response sums
# for R (5), then for each of 1p, 1m, 2p, 2m the count and <e_noshear> sums (3 each).
_N_COLUMNS = 3 + 5 + 4 * 3


@dataclass(frozen=True)
class SelectionCuts:
    """The paper's cuts (section 5): ``s2n > s2n_min`` and ``T / T_psf > T_ratio_min``.

    Calling an instance on a catalogue returns the boolean mask of objects that pass the
    cuts and have ``flags == 0``.
    """

    s2n_min: float = 10.0
    T_ratio_min: float = 0.5

    def __call__(self, catalogue: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return (
                (catalogue["flags"] == 0)
                & (catalogue["s2n"] > self.s2n_min)
                & (catalogue["T"] / catalogue["T_psf"] > self.T_ratio_min)
            )


#: Cuts used for metacalibration in the paper: S/N > 10 and T/T_psf > 0.5.
PAPER_CUTS = SelectionCuts()

#: Cuts for ``wmom`` shapes: S/N > 10 and T/T_psf > 1. In a fixed weight a point source's
#: T equals the PSF's (ratio 1 without noise) and a galaxy's is larger, so the paper's
#: 0.5 (meant for adaptive moments) removes nothing: the simulated galaxies' ratios are
#: 0.95-1.64 at S/N 20 (1.06-1.50 at S/N 10^4), and a star's is 1 +- noise. 1 removes
#: everything narrower than the PSF and half the stars at a 5% cost in these galaxies
#: (metadetect's 1.2 removes more stars and ~40% of them).
WMOM_CUTS = SelectionCuts(T_ratio_min=1.0)


def cuts_for_shape(shape: str) -> SelectionCuts:
    """The selection cuts for metacal shapes of kind ``shape`` (``"admom"``: the paper's;
    ``"wmom"``: :data:`WMOM_CUTS`)."""
    return WMOM_CUTS if shape == "wmom" else PAPER_CUTS


@dataclass(frozen=True, eq=False)
class ShearResponse:
    """Ensemble metacal responses.

    Attributes
    ----------
    R : ndarray, shape (2, 2)
        Shear response ``d e_i / d g_j``.
    R_S : ndarray, shape (2, 2)
        Selection response (zero without failures or cuts).
    mean_e : ndarray, shape (2,)
        Mean noshear ellipticity of the selected objects.
    n_selected : int
        Number of objects selected on the noshear measurements.
    """

    R: np.ndarray
    R_S: np.ndarray
    mean_e: np.ndarray
    n_selected: int

    @property
    def total(self) -> np.ndarray:
        """``R + R_S``, the matrix that calibrates the mean ellipticity."""
        return self.R + self.R_S

    @property
    def shear(self) -> np.ndarray:
        """Calibrated mean shear ``(R + R_S)^-1 <e>``, shape (2,)."""
        return np.linalg.solve(self.total, self.mean_e)


def stack_results(results: Results) -> dict[str, np.ndarray]:
    """One catalogue per metacal type, rows aligned across types.

    Parameters
    ----------
    results : mapping or sequence of mappings
        ``{type: structured array}`` (returned as is after checks), or a list of such
        mappings (e.g. one :func:`measure_metacal` result per object), concatenated.

    Raises
    ------
    ValueError
        A metacal type is missing or the types have different lengths.
    """
    if isinstance(results, Mapping):
        stacked = {name: np.asarray(results[name]) for name in METACAL_TYPES if name in results}
    else:
        if len(results) == 0:
            raise ShearError("no results to stack")
        stacked = {
            name: np.concatenate([np.atleast_1d(r[name]) for r in results])
            for name in METACAL_TYPES
            if all(name in r for r in results)
        }
    missing = set(METACAL_TYPES) - set(stacked)
    if missing:
        raise ShearError(
            f"metacal types {sorted(missing)} are missing from the results", value=sorted(missing)
        )
    lengths = {len(cat) for cat in stacked.values()}
    if len(lengths) != 1:
        raise ShearError(
            f"metacal types have different numbers of objects: {sorted(lengths)}",
            value=sorted(lengths),
        )
    return stacked


def _selected(catalogue: np.ndarray, selection: Selection | None) -> np.ndarray:
    valid = (catalogue["flags"] == 0) & np.isfinite(catalogue["g1"]) & np.isfinite(catalogue["g2"])
    if selection is not None:
        valid &= np.asarray(selection(catalogue), dtype=bool)
    return valid


def _contributions(
    catalogues: Mapping[str, np.ndarray], step: float, selection: Selection | None
) -> np.ndarray:
    """Per-object terms whose sums over objects give every ensemble quantity."""
    noshear = catalogues["noshear"]
    e = np.stack([noshear["g1"], noshear["g2"]], axis=1)
    e = np.where(np.isfinite(e), e, 0.0)
    valid_noshear = _selected(noshear, None)
    in_noshear = _selected(noshear, selection)
    sheared_ok = np.ones(len(noshear), dtype=bool)
    for name in METACAL_TYPES[1:]:
        sheared_ok &= _selected(catalogues[name], None)
    with_response = in_noshear & sheared_ok

    terms = np.zeros((len(noshear), _N_COLUMNS))
    terms[:, 0] = in_noshear
    terms[:, 1:3] = e * in_noshear[:, np.newaxis]
    terms[:, 3] = with_response
    for j, (plus, minus) in enumerate(_SHEARED):
        for i, component in enumerate(("g1", "g2")):
            derivative = (catalogues[plus][component] - catalogues[minus][component]) / (2 * step)
            terms[:, 4 + 2 * i + j] = np.where(with_response, derivative, 0.0)
    column = 8
    for plus, minus in _SHEARED:
        for name in (plus, minus):
            in_sheared = _selected(catalogues[name], selection) & valid_noshear
            terms[:, column] = in_sheared
            terms[:, column + 1 : column + 3] = e * in_sheared[:, np.newaxis]
            column += 3
    return terms


def _response_from_sums(sums: np.ndarray, step: float) -> ShearResponse:
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_e = sums[1:3] / sums[0]
        R = sums[4:8].reshape(2, 2) / sums[3]
        R_S = np.zeros((2, 2))
        for j in range(2):
            plus = sums[8 + 6 * j : 11 + 6 * j]
            minus = sums[11 + 6 * j : 14 + 6 * j]
            R_S[:, j] = (plus[1:] / plus[0] - minus[1:] / minus[0]) / (2 * step)
    return ShearResponse(R=R, R_S=R_S, mean_e=mean_e, n_selected=int(round(sums[0])))


def _calibrated_shear(sums: np.ndarray, step: float) -> np.ndarray:
    response = _response_from_sums(sums, step)
    if not np.all(np.isfinite(response.total)) or not np.all(np.isfinite(response.mean_e)):
        return np.full(2, np.nan)
    return response.shear


def group_ranks(n_objects: int, group: Groups) -> np.ndarray:
    """Per row, the rank ``0, 1, ...`` of its group (:data:`Groups`) in row order.

    Raises
    ------
    CellCoaddRangeError
        An int ``group`` below 1.
    ShearError
        Keys that are not one per row or that decrease.
    """
    if isinstance(group, np.ndarray):
        keys = np.asarray(group)
        if keys.shape != (n_objects,) or (n_objects and np.any(np.diff(keys) < 0)):
            raise ShearError(
                f"jackknife group keys must be {n_objects} non-decreasing values, one per "
                f"row, got shape {keys.shape}",
                value=keys.shape,
            )
        return np.concatenate([[0], np.cumsum(np.diff(keys) != 0)]) if n_objects else keys
    if group < 1:
        raise CellCoaddRangeError(f"group must be >= 1, got {group}", value=group, low=1)
    return np.arange(n_objects) // group


def jackknife(
    terms: np.ndarray,
    n_blocks: int,
    estimator: Callable[[np.ndarray], np.ndarray],
    group: Groups = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Estimate from all objects, and its delete-one-block jackknife standard error.

    The rows of a group (:data:`Groups`: each run of ``group`` rows, or rows of equal
    key) always fall in the same block, whatever the number of rows (odd included), so
    correlated rows such as ring partners are never split between blocks: splitting them
    makes the error wrong (a ``c`` the partners cancel gets an error many times too
    large)."""
    n_objects = len(terms)
    ranks = group_ranks(n_objects, group)
    n_groups = int(ranks[-1]) + 1 if n_objects else 0
    n_blocks = min(n_blocks, n_groups)
    if n_blocks < 2:
        raise ShearError(
            f"a jackknife needs at least 2 groups of objects, got {n_groups}", value=n_groups
        )
    labels = ranks * n_blocks // n_groups
    block_sums = np.zeros((n_blocks, terms.shape[1]))
    np.add.at(block_sums, labels, terms)
    total = block_sums.sum(axis=0)
    estimate = estimator(total)
    leave_one_out = np.array([estimator(total - block) for block in block_sums])
    spread = leave_one_out - leave_one_out.mean(axis=0)
    error = np.sqrt((n_blocks - 1) / n_blocks * np.sum(spread**2, axis=0))
    return estimate, error


def _paired_biases(
    sums: np.ndarray, split: int, shear_of: Callable[[np.ndarray], np.ndarray], true_g: float
) -> np.ndarray:
    """``[m1, c1, c2]`` from the summed terms of paired objects (see
    :func:`paired_shear_bias`)."""
    g_plus, g_minus = shear_of(sums[:split]), shear_of(sums[split:])
    m1 = (g_plus[0] - g_minus[0]) / (2.0 * true_g) - 1.0
    return np.array([m1, 0.5 * (g_plus[0] + g_minus[0]), 0.5 * (g_plus[1] + g_minus[1])])


def paired_shear_bias(
    terms: np.ndarray,
    split: int,
    shear_of: Callable[[np.ndarray], np.ndarray],
    true_g: float,
    n_blocks: int,
    group: Groups = 1,
) -> dict[str, float]:
    """``m1, c1, c2`` and their jackknife errors from paired ``+g`` / ``-g`` objects.

    Row ``k`` of ``terms`` holds object ``k``'s summable terms: columns ``[:split]`` for
    its ``(+true_g, 0)`` member, ``[split:]`` for its ``(-true_g, 0)`` member;
    ``shear_of`` turns summed terms into a mean shear. With ``g+-`` the two mean shears,
    ``m1 = (g+_1 - g-_1) / (2 true_g) - 1`` and ``c_i = (g+_i + g-_i) / 2``; errors by
    :func:`jackknife`, a pair's members and each run of ``group`` rows removed together.
    Shared by metacalibration, BFD and AnaCal.
    """

    def biases(sums: np.ndarray) -> np.ndarray:
        return _paired_biases(sums, split, shear_of, true_g)

    estimate, error = jackknife(terms, n_blocks, biases, group)
    names = ("m1", "c1", "c2")
    out = {name: float(value) for name, value in zip(names, estimate, strict=True)}
    out.update({f"{name}_err": float(value) for name, value in zip(names, error, strict=True)})
    return out


def shear_response(
    results: Results, step: float = 0.01, selection: Selection | None = None
) -> ShearResponse:
    """Ensemble shear response ``R`` and selection response ``R_S``.

    Parameters
    ----------
    results : mapping or sequence of mappings
        Metacal measurements; see :func:`stack_results`.
    step : float
        The metacal shear step used to make the images.
    selection : callable, optional
        Cut applied to each metacal catalogue separately, e.g. :data:`PAPER_CUTS`;
        ``flags == 0`` is always required.

    Returns
    -------
    ShearResponse
    """
    catalogues = stack_results(results)
    sums = _contributions(catalogues, step, selection).sum(axis=0)
    return _response_from_sums(sums, step)


def mean_shear(
    results: Results,
    step: float = 0.01,
    selection: Selection | None = None,
    n_blocks: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """Calibrated mean shear ``(R + R_S)^-1 <e>`` and its jackknife error.

    Parameters
    ----------
    results, step, selection
        As for :func:`shear_response`.
    n_blocks : int
        Number of jackknife blocks (at most the number of objects).

    Returns
    -------
    g, g_err : ndarray, shape (2,)
    """
    terms = _contributions(stack_results(results), step, selection)
    return jackknife(terms, n_blocks, lambda sums: _calibrated_shear(sums, step))


def multiplicative_bias(
    plus: Results,
    minus: Results,
    true_g: float = 0.02,
    step: float = 0.01,
    selection: Selection | None = None,
    n_blocks: int = 100,
    group: Groups = 1,
) -> dict[str, float]:
    """Multiplicative and additive shear biases from paired simulations.

    ``plus`` and ``minus`` are the same objects and noise sheared by ``(+true_g, 0)`` and
    ``(-true_g, 0)``; row ``k`` of both is the same object. With ``g+`` and ``g-`` the
    calibrated mean shears (each with its own responses), ``m1 = (g+_1 - g-_1) /
    (2 true_g) - 1`` and ``c_i = (g+_i + g-_i) / 2``: the pairing cancels the shape noise
    in ``m1``. Errors are jackknife over blocks of objects, removing a pair's two members
    together, and the rows of each ``group`` (:data:`Groups`: e.g. ``group=2`` for
    objects and their 90-degree-rotated partners in rows ``2k, 2k + 1``, or the keys
    ``index // 2`` when some rows were dropped) together.

    Returns
    -------
    dict
        ``m1, m1_err, c1, c1_err, c2, c2_err``.
    """
    terms = _paired_terms(plus, minus, step, [selection])
    return paired_shear_bias(
        terms, _N_COLUMNS, lambda sums: _calibrated_shear(sums, step), true_g, n_blocks, group
    )


def _paired_terms(
    plus: Results, minus: Results, step: float, selections: Sequence[Selection | None]
) -> np.ndarray:
    """Per object, for each selection in turn, the summable terms of its ``+g`` member
    then of its ``-g`` member (``2 * _N_COLUMNS`` columns a selection)."""
    plus_cats, minus_cats = stack_results(plus), stack_results(minus)
    if len(plus_cats["noshear"]) != len(minus_cats["noshear"]):
        raise ShearError("plus and minus catalogues must hold the same objects (same length)")
    return np.hstack(
        [
            _contributions(cats, step, selection)
            for selection in selections
            for cats in (plus_cats, minus_cats)
        ]
    )


def bias_by_selection(
    plus: Results,
    minus: Results,
    selections: Mapping[str, Selection | None],
    true_g: float = 0.02,
    step: float = 0.01,
    n_blocks: int = 100,
    group: Groups = 1,
) -> dict[str, dict[str, float]]:
    """``m1`` of the same paired objects under several selections, and each one's paired
    difference from the first.

    Every selection is corrected for its own selection response, as in
    :func:`multiplicative_bias` (whose ``m1`` and error each entry equals). The
    differences share the objects, so their jackknife errors (the same blocks for every
    selection) are much smaller than the biases' own: whether a cut changes ``m1`` can be
    told at a precision no single bias reaches. ``m1_err * sqrt(N)`` (the per-pair
    scatter) tells what a cut costs: the CPU a run needs for a given ``sigma_m`` grows as
    its square.

    Parameters
    ----------
    plus, minus : mapping or sequence of mappings
        The ``(+true_g, 0)`` and ``(-true_g, 0)`` members, row ``k`` of both the same object
        (see :func:`multiplicative_bias`).
    selections : mapping of str to selection or None
        Named cuts (None: ``flags == 0`` only); the first is the reference.
    true_g, step, n_blocks, group
        As in :func:`multiplicative_bias`.

    Returns
    -------
    dict of str to dict
        Per selection ``m1``, ``m1_err`` and ``scatter`` (``m1_err * sqrt(N)``, N the
        pairs); after the first, ``dm1`` and ``dm1_err``: ``m1`` minus the first's.

    Raises
    ------
    ShearError
        Without selections, or when ``plus`` and ``minus`` differ in length.
    """
    if not selections:
        raise ShearError("bias_by_selection needs at least one selection")
    names = list(selections)
    terms = _paired_terms(plus, minus, step, [selections[name] for name in names])
    n_pairs = len(terms)
    width = 2 * _N_COLUMNS

    def shear_of(sums: np.ndarray) -> np.ndarray:
        return _calibrated_shear(sums, step)

    def biases(sums: np.ndarray) -> np.ndarray:
        m1 = np.array(
            [
                _paired_biases(sums[k * width : (k + 1) * width], _N_COLUMNS, shear_of, true_g)[0]
                for k in range(len(names))
            ]
        )
        return np.concatenate([m1, m1[1:] - m1[0]])

    estimate, error = jackknife(terms, n_blocks, biases, group)
    out: dict[str, dict[str, float]] = {}
    for k, name in enumerate(names):
        entry = {
            "m1": float(estimate[k]),
            "m1_err": float(error[k]),
            "scatter": float(error[k] * np.sqrt(n_pairs)),
        }
        if k:
            entry["dm1"] = float(estimate[len(names) + k - 1])
            entry["dm1_err"] = float(error[len(names) + k - 1])
        out[name] = entry
    return out
