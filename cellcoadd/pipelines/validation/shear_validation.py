"""Shear-bias validation on the paper's stamp simulations (section 3, Table 1).

:func:`validate_shear` simulates ``n_objects`` objects, each as a matched pair sheared by
``+g`` and ``-g`` (same galaxy, PSFs, shifts, WCSs and noise), measures both members
with metacalibration (or BFD, AnaCal), on the cell coadd of their 10 epochs built by the
real builder (``mode="coadd"``), on all epochs jointly in their own pixels
(``mode="multi-epoch"``, the paper's reference) or on the first epoch alone
(``mode="single"``), and returns the multiplicative and additive biases

``m1 = (g+_1 - g-_1) / (2 g_true) - 1``,  ``c_i = (g+_i + g-_i) / 2``,

with ``g+-`` the calibrated mean shears ``(R + R_S)^-1 <e>`` under the paper's cuts
(S/N > 10, T/T_psf > 0.5; T/T_psf > 1 for ``wmom`` shapes,
:data:`~cellcoadd.shear.response.WMOM_CUTS`) and jackknife errors over objects, a pair's
two members removed together (:func:`cellcoadd.shear.multiplicative_bias`). What one object goes
through is described in :mod:`cellcoadd.pipelines.validation.stamp_pairs`.

Objects run in chunks on any ``concurrent.futures`` executor (a local process pool for
``workers > 1``, or a dask.distributed cluster); object ``i`` depends only on
``(seed, i)``, so the results do not depend on the executor, the number of workers or the
chunking.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from concurrent.futures import Executor, as_completed
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from tqdm.auto import tqdm

from cellcoadd.errors import CellCoaddRangeError, CellCoaddValueError, ConfigError, ShearError
from cellcoadd.execution.executors import resolve_executor
from cellcoadd.pipelines.validation.anacal_validation import summarize_anacal
from cellcoadd.pipelines.validation.bfd_validation import summarize_bfd
from cellcoadd.pipelines.validation.bias_presets import choose_bfd
from cellcoadd.pipelines.validation.bias_table import (
    summary_fields,
)
from cellcoadd.pipelines.validation.stamp_pairs import PairCatalogue, measure_pair
from cellcoadd.pipelines.validation.validation_settings import (
    BFD_OVERSAMPLE,
    Method,
    Mode,
    ValidationSettings,
    check_method_mode,
    stamp_cell,
    stamp_size_for_offset,
)
from cellcoadd.shear.metacal import ReconvolutionKind
from cellcoadd.shear.response import (
    Groups,
    bias_by_selection,
    cuts_for_shape,
    multiplicative_bias,
    shear_response,
)
from cellcoadd.shear.shapes import WMOM_FWHM
from cellcoadd.sim.config import SimConfig

#: Keys of :func:`validate_shear`'s result that are always JSON-serialisable.
RESULT_KEYS: tuple[str, ...] = (
    "m1",
    "m1_err",
    "c1",
    "c1_err",
    "c2",
    "c2_err",
    "n_objects",
    "n_used",
    "cpu_seconds",
    "mode",
    "method",
    "settings",
)


def measure_pairs(settings: ValidationSettings, indices: Sequence[int]) -> PairCatalogue:
    """:func:`~cellcoadd.pipelines.validation.stamp_pairs.measure_pair` for each index, as a
    catalogue (one task of a parallel run)."""
    cell = stamp_cell(settings)
    return PairCatalogue.from_pairs([measure_pair(settings, index, cell) for index in indices])


def run_pairs(
    settings: ValidationSettings,
    n_objects: int,
    *,
    first_index: int = 0,
    workers: int = 1,
    executor: Executor | None = None,
    scheduler: object | None = None,
    chunk_size: int | None = None,
    progress: bool = True,
    checkpoint: str | os.PathLike[str] | None = None,
    checkpoint_every: int = 1000,
) -> PairCatalogue:
    """Measure objects ``first_index`` to ``first_index + n_objects - 1``.

    Arguments are those of :func:`validate_shear`; ``first_index`` lets a long run be
    split into index ranges whose catalogues :meth:`PairCatalogue.concatenate` joins.

    With ``checkpoint`` (a file path), the pairs measured so far are written there
    (:meth:`PairCatalogue.save`) each time ``checkpoint_every`` more have finished, and at
    the end; a run started with an existing checkpoint of the same settings measures only
    the objects of its range the file lacks, so a killed run resumes without losing or
    measuring twice any pair, and gives the catalogue an uninterrupted run gives. Pairs
    of the file outside the range are kept in it but not returned.

    Returns
    -------
    PairCatalogue
        Ordered by object index, identical whatever the executor and chunking.
    """
    if n_objects < 1 or first_index < 0:
        raise CellCoaddValueError(
            f"need n_objects >= 1 and first_index >= 0, got {n_objects}, {first_index}",
            value=(n_objects, first_index),
        )
    if workers < 1:
        raise CellCoaddRangeError(f"workers must be >= 1, got {workers}", value=workers, low=1)
    if checkpoint_every < 1:
        raise ConfigError(
            f"checkpoint_every must be >= 1, got {checkpoint_every}", value=checkpoint_every
        )
    stop = first_index + n_objects
    done: list[PairCatalogue] = []
    if checkpoint is not None and os.path.exists(checkpoint):
        done.append(PairCatalogue.load(checkpoint, settings))
    have = set(done[0].index.tolist()) if done else set()
    todo = [i for i in range(first_index, stop) if i not in have]
    pool, release = resolve_executor(executor, workers, scheduler) if todo else (None, None)
    if chunk_size is None:
        # several chunks per worker keep the pool busy and the progress bar moving
        slots = 1 if pool is None else 4 * max(workers, 2)
        chunk_size = int(np.clip(np.ceil(max(len(todo), 1) / slots), 1, 25))
    chunks = [todo[a : a + chunk_size] for a in range(0, len(todo), chunk_size)]
    bar = tqdm(
        total=n_objects,
        initial=n_objects - len(todo),
        desc=f"shear bias ({settings.mode})",
        unit="pair",
        disable=not progress,
    )
    since_saved = 0

    def finished(catalogue: PairCatalogue) -> None:
        nonlocal since_saved
        done.append(catalogue)
        bar.update(len(catalogue))
        since_saved += len(catalogue)
        if checkpoint is not None and since_saved >= checkpoint_every:
            done[:] = [PairCatalogue.concatenate(done)]
            done[0].save(checkpoint, settings)
            since_saved = 0

    try:
        if pool is None:
            for chunk in chunks:
                finished(measure_pairs(settings, chunk))
        else:
            futures = [pool.submit(measure_pairs, settings, chunk) for chunk in chunks]
            for future in as_completed(futures):
                finished(future.result())
    finally:
        bar.close()
        if release is not None:
            release()
    result = PairCatalogue.concatenate(done)
    if checkpoint is not None and since_saved:
        result.save(checkpoint, settings)
    return result.select(first_index, stop)


def summarize(settings: ValidationSettings, catalogue: PairCatalogue) -> dict[str, Any]:
    """Biases and diagnostics of a catalogue of pairs (the result of :func:`validate_shear`)."""
    if len(catalogue) < 2:
        raise ShearError(
            f"a bias needs at least 2 pairs, got {len(catalogue)}", value=len(catalogue)
        )
    if settings.method == "bfd":
        return summarize_bfd(settings, catalogue, _group(settings, catalogue))
    if settings.method == "anacal":
        return summarize_anacal(settings, catalogue, _group(settings, catalogue))
    plus, minus = catalogue.plus, catalogue.minus
    cuts = cuts_for_shape(settings.shape)
    bias = multiplicative_bias(
        plus,
        minus,
        true_g=settings.sim.shear[0],
        step=settings.step,
        selection=cuts,
        group=_group(settings, catalogue),
    )
    kept_plus = cuts(plus["noshear"])
    kept_minus = cuts(minus["noshear"])
    response = shear_response(plus, step=settings.step, selection=cuts)
    s2n = plus["noshear"]["s2n"][np.isfinite(plus["noshear"]["s2n"])]
    cpu = float(catalogue.cpu_seconds.sum())
    return {
        **bias,
        **summary_fields(settings, catalogue, kept_plus, kept_minus, cpu),
        "R11": float(response.R[0, 0]),
        "R22": float(response.R[1, 1]),
        "R_S11": float(response.R_S[0, 0]),
        "s2n_median": float(np.median(s2n)) if s2n.size else float("nan"),
    }


def cut_comparison(
    settings: ValidationSettings, catalogue: PairCatalogue
) -> dict[str, dict[str, float]]:
    """``m1`` of a metacal catalogue without cuts, with each of its shape's cuts alone and
    with both (the run's own), and each one's paired difference from no cuts (see
    :func:`~cellcoadd.shear.response.bias_by_selection`).

    Keys: ``"none"`` (``flags == 0`` only), ``"S/N > s"``, ``"T/T_psf > t"`` and
    ``"both"``. What tells whether a cut biases ``m1`` (``dm1`` against its error) and
    what it costs (``scatter``: the CPU for a given ``sigma_m`` grows as its square).

    Raises
    ------
    ShearError
        For a BFD or AnaCal catalogue (their selections are not these cuts).
    """
    if settings.method != "metacal":
        raise ShearError(f"cut_comparison is for metacal catalogues, not {settings.method}")
    cuts = cuts_for_shape(settings.shape)
    selections = {
        "none": None,
        f"S/N > {cuts.s2n_min:g}": replace(cuts, T_ratio_min=-np.inf),
        f"T/T_psf > {cuts.T_ratio_min:g}": replace(cuts, s2n_min=-np.inf),
        "both": cuts,
    }
    return bias_by_selection(
        catalogue.plus,
        catalogue.minus,
        selections,
        true_g=settings.sim.shear[0],
        step=settings.step,
        group=_group(settings, catalogue),
    )


def _group(settings: ValidationSettings, catalogue: PairCatalogue) -> Groups:
    """Rows removed together by the jackknife: ring partners (objects ``2k, 2k + 1``,
    keyed ``index // 2``), whatever the number of objects (odd: the last alone) and
    whichever objects were dropped; each row alone without ring partners, or with a
    single ring (no jackknife of one block: a 2-object run still gets a rough error)."""
    keys = np.asarray(catalogue.index, dtype=np.int64) // 2
    if settings.rotated_partners and len(np.unique(keys)) >= 2:
        return keys
    return 1


def validate_shear(
    mode: Mode = "coadd",
    n_objects: int = 200,
    snr: float | tuple[float, float] | None = None,
    seed: int = 0,
    workers: int = 1,
    step: float = 0.01,
    progress: bool = True,
    *,
    executor: Executor | None = None,
    scheduler: object | None = None,
    chunk_size: int | None = None,
    sim: SimConfig | None = None,
    shear: float | None = None,
    coadd_pixel_scale: float = 0.2,
    reconvolution_psf: ReconvolutionKind = "gauss",
    return_measurements: bool = False,
    compare_cuts: bool = False,
    method: Method = "metacal",
    shape: Literal["admom", "wmom"] = "admom",
    wmom_fwhm: float = WMOM_FWHM,
    rotated_partners: bool | None = None,
    bfd_templates: int | None = None,
    bfd_template_sample: Literal["independent", "targets"] | None = None,
    bfd_oversample: int = BFD_OVERSAMPLE,
    bfd_mirror: bool = False,
    checkpoint: str | os.PathLike[str] | None = None,
    checkpoint_every: int = 1000,
    object_offset: float = 0.0,
) -> dict[str, Any]:
    """Measure the multiplicative and additive shear biases of metacal or BFD on cell coadds.

    Parameters
    ----------
    mode : {"coadd", "single", "multi-epoch"}
        ``"coadd"``: measure the cell coadd of each object's epochs, built with
        :func:`cellcoadd.builder.build_cell`. ``"multi-epoch"``: all epochs jointly in
        their own pixels (metacal: per-epoch metacal images with one common reconvolution
        PSF and a joint shape; BFD: the sum of the epochs' moments; see
        :mod:`cellcoadd.pipelines.validation.epoch_measurements`). ``"single"``: the first epoch
        alone (metacal, BFD, AnaCal).
    n_objects : int
        Number of objects (each simulated as a +g / -g pair).
    snr : float or (float, float), optional
        Fixed target S/N or a range drawn uniformly per object; the optimal S/N of the
        measured noise-free data sets the pixel noise (see
        :mod:`cellcoadd.pipelines.validation.stamp_pairs`). None: the simulation's noise level.
    seed : int
        Seed of the run.
    workers : int
        Local processes (ignored when ``executor`` or ``scheduler`` is given).
    step : float
        Metacal shear step.
    progress : bool
        Show a progress bar.
    executor : concurrent.futures.Executor, optional
        Where to run the chunks of objects.
    scheduler : str or distributed.Client, optional
        A dask.distributed scheduler address (or client) to run the chunks on.
    chunk_size : int, optional
        Objects per task (default: a few tasks per worker, at most 25 objects).
    sim : SimConfig, optional
        Simulation settings (default: the paper's, :class:`~cellcoadd.sim.SimConfig`).
    shear : float, optional
        Input shear ``g1`` of the pairs (``g2 = 0``), replacing ``sim.shear`` (default
        0.02, the paper's); ``m1`` is measured against it. BFD's high-S/N check takes
        1e-3 (docs/validation.md).
    coadd_pixel_scale : float
        Coadd pixel scale, arcsec (0.2, the LSST-like default of cellcoadd; 0.27 puts
        the coadd on the exposures' nominal scale); the cell size follows
        (:func:`~cellcoadd.pipelines.validation.validation_settings.largest_cell_inner`).
    reconvolution_psf : {"gauss", "fitgauss", "dilate"}
        Metacal reconvolution PSF.
    return_measurements : bool
        Also return the per-object :class:`PairCatalogue` under ``"measurements"``.
    compare_cuts : bool
        Metacal: also :func:`cut_comparison` of the pairs under ``"cut_comparison"``.
    method : {"metacal", "bfd", "anacal"}
        Shear method (AnaCal: FPFS, coadd or single mode; BFD: noise level fixed per run,
        see :mod:`cellcoadd.pipelines.validation.stamp_pairs`).
    shape : {"admom", "wmom"}
        Metacal shape: adaptive moments or fixed-weight Gaussian moments.
    wmom_fwhm : float
        FWHM (arcsec) of the ``wmom`` weight.
    rotated_partners : bool, optional
        Make objects ``2k + 1`` the 90-degree-rotated partners of objects ``2k`` (the mean
        intrinsic shape then cancels in ``c``). None: yes, but for BFD above S/N 50.
    bfd_templates : int, optional
        Independent deep templates of the BFD prior. None: chosen from the S/N
        (:func:`~cellcoadd.pipelines.validation.bias_presets.choose_bfd`: 1600 at S/N
        up to 50).
    bfd_template_sample : {"independent", "targets"}, optional
        BFD templates from an independent sample, or the targets themselves unsheared
        (the high-S/N check; see :class:`~cellcoadd.pipelines.ValidationSettings`).
        None: chosen from the S/N (the targets above S/N 50, with no ring partners and
        ``shear`` 1e-3 unless given; independent ones up to 50).
    bfd_oversample : int
        k-space oversampling of the BFD moments (default
        :data:`~cellcoadd.pipelines.validation.validation_settings.BFD_OVERSAMPLE`, 4: accurate
        shear derivatives for small galaxies; 1, the stamp's own FFT grid, biases m1 by
        a few per cent; see ``docs/validation.md``).
    bfd_mirror : bool
        Add each template copy's mirror image to the BFD prior (off: on the simulated
        population it changes m1, c1, c2 by < 5e-5 at twice the cost of P, Q, R; see
        ``docs/validation.md``, "Mirror images in the prior").
    checkpoint : path-like, optional
        File the measured pairs are saved to every ``checkpoint_every`` pairs; an
        existing one of the same settings is resumed (see :func:`run_pairs`).
    checkpoint_every : int
        Pairs between checkpoints.
    object_offset : float
        Coadd mode: objects at random positions within ``object_offset`` coadd pixels of
        their cell's centre along each axis, measured with ``psf_at`` there (0: on the
        centre pixel); the default stamps are enlarged so that the cell keeps its size
        (see :class:`~cellcoadd.pipelines.ValidationSettings`).

    Returns
    -------
    dict
        ``m1, m1_err, c1, c1_err, c2, c2_err`` (jackknife 1-sigma errors), ``n_objects``,
        ``n_used`` (pairs whose two noshear measurements pass the cuts; ``n_used_plus``,
        ``n_used_minus`` for each member), ``cpu_seconds`` (summed over workers),
        ``wall_seconds``, ``mode``, ``settings`` (JSON-able), diagnostics (``R11``,
        ``R22``, ``R_S11``, ``s2n_median``, ``noise_sigma_median``,
        ``incomplete_coadds``: coadds missing an epoch) and the paper's value
        (``paper_m1``, ``paper_m1_err``; NaN where Table 1 has no row).

    Raises
    ------
    ConfigError
        A method and mode that do not run together (AnaCal in multi-epoch mode; the
        ``"dilate"`` reconvolution PSF in multi-epoch metacal); BFD settings that give a
        wrong ``m1`` at this S/N (independent templates above S/N 50; see
        :func:`~cellcoadd.pipelines.validation.bias_presets.choose_bfd`).
    """
    if n_objects < 2:
        raise CellCoaddRangeError(
            f"a bias needs at least 2 objects, got n_objects = {n_objects}", value=n_objects, low=2
        )
    check_method_mode(method, mode, reconvolution_psf)
    if method == "bfd":
        bfd = choose_bfd(
            snr,
            template_sample=bfd_template_sample,
            templates=bfd_templates,
            rotated_partners=rotated_partners,
            shear=shear,
        )
        bfd_template_sample, bfd_templates = bfd.template_sample, bfd.templates
        rotated_partners, shear = bfd.rotated_partners, bfd.shear
    if sim is None:
        sim = SimConfig()
        if object_offset > 0.0:  # room for the moved cell, which keeps its size
            border = ValidationSettings.model_fields["cell_border"].default
            size = stamp_size_for_offset(sim, coadd_pixel_scale, border, object_offset)
            sim = sim.model_copy(update={"stamp_size": size})
    if shear is not None:
        sim = SimConfig.model_validate({**sim.model_dump(), "shear": (shear, 0.0)})
    settings = ValidationSettings(
        mode=mode,
        seed=seed,
        snr=snr,
        step=step,
        reconvolution_psf=reconvolution_psf,
        sim=sim,
        coadd_pixel_scale=coadd_pixel_scale,
        method=method,
        shape=shape,
        wmom_fwhm=wmom_fwhm,
        rotated_partners=True if rotated_partners is None else rotated_partners,
        bfd_templates=100 if bfd_templates is None else bfd_templates,
        bfd_template_sample=bfd_template_sample or "independent",
        bfd_oversample=bfd_oversample,
        bfd_mirror=bfd_mirror,
        object_offset=object_offset,
    )
    start = time.perf_counter()
    measured = run_pairs(
        settings,
        n_objects,
        workers=workers,
        executor=executor,
        scheduler=scheduler,
        chunk_size=chunk_size,
        progress=progress,
        checkpoint=checkpoint,
        checkpoint_every=checkpoint_every,
    )
    result = summarize(settings, measured)
    result["wall_seconds"] = time.perf_counter() - start
    if compare_cuts:
        result["cut_comparison"] = cut_comparison(settings, measured)
    if return_measurements:
        result["measurements"] = measured
    return result


__all__ = [
    "RESULT_KEYS",
    "cut_comparison",
    "measure_pairs",
    "run_pairs",
    "summarize",
    "validate_shear",
]
