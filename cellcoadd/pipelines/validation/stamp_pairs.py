"""One object of the shear-bias validation: simulate a +g/-g pair, coadd, measure.

The paper's stamp simulations (section 3, :mod:`cellcoadd.sim.stamps`) give each object
``n_epochs`` exposures with their own PSF, sub-pixel shift and WCS. For object ``i`` of a
run with seed ``s``:

1. both members of the pair (shear ``+g`` and ``-g``) are simulated noise free from the
   same seed, so they hold the same galaxy, PSFs, shifts and WCSs;
2. the pixel noise level ``sigma`` is the simulation's (``SimConfig.noise_sigma``), or,
   when a target S/N is asked for, ``sigma = sqrt(sum I^2) / snr`` with ``I`` the
   noise-free pixels of the ``+g`` member that are measured (all epochs in coadd and
   multi-epoch modes, the first epoch in single mode): the optimal matched-filter S/N of
   the measured data. A range ``(lo, hi)`` draws the target uniformly per object;
3. the same noise fields (unit normals from a generator keyed by ``(s, i)``, scaled by
   ``sigma``) are added to both members;
4. ``coadd`` mode builds cell ``(0, 0)`` of a one-cell sky map centred on the objects
   with the real builder (:func:`cellcoadd.builder.build_cell`, seed ``s``: noise
   realizations keyed by ``(s, epoch, i)``, hence the same for both members) and runs
   metacalibration on it through :func:`~cellcoadd.shear.observation.to_observation`;
   ``single`` mode runs metacalibration on the first epoch alone, with its PSF drawn at
   the object through the epoch's local WCS (pixel response included) and its own noise
   realization (same ``sigma``, independent of the image noise); ``multi-epoch`` mode
   measures all epochs jointly in their own pixels, each with its own PSF drawn that way
   and its own noise realization (the first one is single mode's):
   :mod:`cellcoadd.pipelines.validation.epoch_measurements`.

**Positions in the cell** (``object_offset``, coadd mode): by default the objects sit on
the cell-centre pixel, where ``cell.psf`` was drawn, so the measurement cannot see how the
PSF differs elsewhere in the cell. With ``object_offset = W`` each object's cell is moved
so that the object falls at a random position ``(dx, dy)``, uniform in ``[-W, W]^2`` coadd
pixels, from the centre pixel (any sub-pixel phase; generator keyed by ``(s, i)``, ring
partners sharing it) and is measured there with the PSF the library serves at that
position, :meth:`~cellcoadd.model.cell_coadd.CellCoadd.psf_at` (the centroid guess and
BFD's centre at the object too).

**Ring partners** (``rotated_partners``, default): objects ``2k`` and ``2k + 1`` are the
same galaxy, PSFs, shifts and WCSs with the intrinsic ellipticity of ``2k + 1`` turned by
90 degrees (``e -> -e``), so the mean intrinsic shape cancels in ``c`` over each partner
pair; both have the target S/N of object ``2k`` and their own noise fields and coadd noise
realizations (keyed by their own index).

**Methods.** ``method="metacal"`` measures metacalibration shapes, adaptive moments
(``shape="admom"``) or moments in a fixed Gaussian weight of FWHM ``wmom_fwhm``
(``shape="wmom"``). ``method="bfd"`` measures the BFD moments of the coadd (or the first
epoch, or the sum of the epochs' moments) with their covariance from the cell's noise
realization (white noise of the known level in single and multi-epoch modes); the
template prior and the shear are made from all the objects (:func:`bfd_templates`,
:func:`cellcoadd.pipelines.validation.shear_validation.summarize`). BFD needs one moment
covariance for all targets, so its noise level is the same for every object:
``sigma = S_ref / snr``, ``S_ref`` the median ``sqrt(sum I^2)`` of the template sample,
``snr`` the geometric mean of the target range (the median object has that S/N).
``method="anacal"`` measures FPFS shapes and their analytic shear responses through AnaCal
(:mod:`cellcoadd.shear.anacal_adapter`) with the same noise realization and measured
variance as metacal (coadd mode), or on the first epoch with its own noise realization
and the known variance (single mode).

Everything about object ``i`` depends only on ``(s, i)`` and the settings, so any split
of a run over processes gives identical results.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcoadd.builder import build_cell
from cellcoadd.errors import BfdError, CellCoaddValueError, ConfigError, PsfStampWarning
from cellcoadd.geometry.tract import Cell
from cellcoadd.io._files.atomic import atomic_write
from cellcoadd.model.build_config import BuildConfig
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.exposure import Exposure
from cellcoadd.pipelines.validation.epoch_measurements import (
    BFD_DTYPE,
    EpochGeometry,
    bfd_epoch_sum,
    bfd_measurement,
    common_psf,
    epoch_psf_image,
    measure_multi_epoch,
    measure_single_epoch,
)
from cellcoadd.pipelines.validation.validation_settings import (
    ValidationSettings,
    offset_cell,
    stamp_cell,
)
from cellcoadd.shear import anacal_adapter, bfd
from cellcoadd.shear.metacal import METACAL_TYPES, measure_metacal
from cellcoadd.shear.observation import observation_jacobian, to_observation
from cellcoadd.shear.shapes import SHAPE_DTYPE, empty_record
from cellcoadd.sim.stamps import StampObject, simulate_object, simulate_sheared

#: ``flags`` bit of a measurement that could not be made because the coadd is empty.
NO_COADD = 1 << 8

# Third entry of the per-object generator keys (the simulation itself uses (seed, index)).
_EPOCH_NOISE_STREAM = 1
_SINGLE_NOISE_STREAM = 2
_SNR_STREAM = 3
_TEMPLATE_STREAM = 4
_POSITION_STREAM = 5
#: Template objects used for the BFD noise level (median signal).
_REFERENCE_TEMPLATES = 50


@dataclass(frozen=True, eq=False)
class PairMeasurement:
    """Metacal measurements of one object sheared by ``+g`` and by ``-g``.

    Attributes
    ----------
    index : int
        Object index.
    plus, minus : dict of str to ndarray
        For each metacal type, a length-1 array of
        :data:`~cellcoadd.shear.metacal.SHAPE_DTYPE`; for BFD, ``{"bfd": ...}`` a length-1
        array of :data:`BFD_DTYPE`.
    noise_sigma : float
        Pixel noise standard deviation of the epochs, counts.
    snr : float
        Target optimal S/N (NaN when the simulation's noise level was kept).
    n_inputs : int
        Epochs used in the coadd (1 in single mode, all in multi-epoch mode).
    cpu_seconds : float
        CPU time spent on this object (simulation, coaddition, measurement).
    """

    index: int
    plus: dict[str, np.ndarray]
    minus: dict[str, np.ndarray]
    noise_sigma: float
    snr: float
    n_inputs: int
    cpu_seconds: float


@dataclass(frozen=True, eq=False)
class PairCatalogue:
    """Measurements of many pairs as compact arrays (about 0.8 kB per pair).

    Attributes
    ----------
    index : ndarray of int64
        Object indices, increasing.
    plus, minus : dict of str to ndarray
        For each metacal type, the :data:`~cellcoadd.shear.metacal.SHAPE_DTYPE` rows of the
        ``+g`` and ``-g`` members, aligned with ``index`` (what
        :func:`~cellcoadd.shear.multiplicative_bias` takes); for BFD the
        :data:`~cellcoadd.pipelines.validation.epoch_measurements.BFD_DTYPE` rows under ``"bfd"``.
    noise_sigma, snr, n_inputs, cpu_seconds : ndarray
        Per object, as in :class:`~cellcoadd.pipelines.validation.stamp_pairs.PairMeasurement`.
    """

    index: np.ndarray
    plus: dict[str, np.ndarray]
    minus: dict[str, np.ndarray]
    noise_sigma: np.ndarray
    snr: np.ndarray
    n_inputs: np.ndarray
    cpu_seconds: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    @classmethod
    def from_pairs(cls, pairs: Sequence[PairMeasurement]) -> PairCatalogue:
        """Stack single-object measurements."""
        keys = list(pairs[0].plus) if pairs else list(METACAL_TYPES)
        return cls(
            index=np.array([pair.index for pair in pairs], dtype=np.int64),
            plus={t: _rows([pair.plus[t] for pair in pairs]) for t in keys},
            minus={t: _rows([pair.minus[t] for pair in pairs]) for t in keys},
            noise_sigma=np.array([pair.noise_sigma for pair in pairs], dtype=np.float64),
            snr=np.array([pair.snr for pair in pairs], dtype=np.float64),
            n_inputs=np.array([pair.n_inputs for pair in pairs], dtype=np.int64),
            cpu_seconds=np.array([pair.cpu_seconds for pair in pairs], dtype=np.float64),
        )

    def select(self, start: int, stop: int) -> PairCatalogue:
        """The pairs with ``start <= index < stop``."""
        keep = (self.index >= start) & (self.index < stop)
        if keep.all():
            return self
        return PairCatalogue(
            index=self.index[keep],
            plus={t: rows[keep] for t, rows in self.plus.items()},
            minus={t: rows[keep] for t, rows in self.minus.items()},
            noise_sigma=self.noise_sigma[keep],
            snr=self.snr[keep],
            n_inputs=self.n_inputs[keep],
            cpu_seconds=self.cpu_seconds[keep],
        )

    @classmethod
    def concatenate(cls, catalogues: Sequence[PairCatalogue]) -> PairCatalogue:
        """Join catalogues (e.g. chunks or index ranges of a run), ordered by index."""
        index = np.concatenate([c.index for c in catalogues])
        order = np.argsort(index, kind="stable")
        keys = list(catalogues[0].plus)

        def join(name: str) -> np.ndarray:
            return np.concatenate([getattr(c, name) for c in catalogues])[order]

        return cls(
            index=index[order],
            plus={t: np.concatenate([c.plus[t] for c in catalogues])[order] for t in keys},
            minus={t: np.concatenate([c.minus[t] for c in catalogues])[order] for t in keys},
            noise_sigma=join("noise_sigma"),
            snr=join("snr"),
            n_inputs=join("n_inputs"),
            cpu_seconds=join("cpu_seconds"),
        )

    def save(self, path: str | os.PathLike[str], settings: ValidationSettings) -> None:
        """Write the catalogue and the settings that made it to ``path`` (a NumPy ``.npz``
        archive, written atomically: a run killed while writing leaves the previous one).
        """
        arrays: dict[str, np.ndarray] = {
            "settings": np.array(settings.model_dump_json()),
            "types": np.array(list(self.plus)),
            "index": self.index,
            "noise_sigma": self.noise_sigma,
            "snr": self.snr,
            "n_inputs": self.n_inputs,
            "cpu_seconds": self.cpu_seconds,
        }
        for name in self.plus:
            arrays[f"plus/{name}"] = self.plus[name]
            arrays[f"minus/{name}"] = self.minus[name]

        def write(temporary: Path) -> None:
            with temporary.open("wb") as stream:
                np.savez(stream, **arrays)  # type: ignore[arg-type]  # names as keywords

        atomic_write(path, write, overwrite=True)

    @classmethod
    def load(cls, path: str | os.PathLike[str], settings: ValidationSettings) -> PairCatalogue:
        """The catalogue :meth:`save` wrote to ``path``.

        Raises
        ------
        ConfigError
            When the file was written by a run with other settings (its pairs would
            not belong to this run).
        """
        with np.load(path, allow_pickle=False) as archive:
            stored = ValidationSettings.model_validate_json(str(archive["settings"]))
            if stored != settings:
                raise ConfigError(
                    f"{os.fspath(path)}: checkpoint of a run with other settings; remove it "
                    "or resume with the settings it was written with"
                )
            types = [str(t) for t in archive["types"]]
            return cls(
                index=archive["index"],
                plus={t: archive[f"plus/{t}"] for t in types},
                minus={t: archive[f"minus/{t}"] for t in types},
                noise_sigma=archive["noise_sigma"],
                snr=archive["snr"],
                n_inputs=archive["n_inputs"],
                cpu_seconds=archive["cpu_seconds"],
            )


def _rows(records: list[np.ndarray]) -> np.ndarray:
    """Records of one kind of many pairs, joined (no pairs: empty metacal rows)."""
    return np.concatenate(records) if records else np.zeros(0, dtype=SHAPE_DTYPE)


def _generator(settings: ValidationSettings, index: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([settings.seed, int(index), stream]))


def _partner(settings: ValidationSettings, index: int) -> tuple[int, bool]:
    """The object whose galaxy ``index`` shows, and whether its shape is turned by 90 deg."""
    if settings.rotated_partners:
        return index - index % 2, index % 2 == 1
    return index, False


def _target_snr(settings: ValidationSettings, index: int) -> float:
    if settings.snr is None:
        return float("nan")
    low, high = settings.snr
    base, _ = _partner(settings, index)
    return float(_generator(settings, base, _SNR_STREAM).uniform(low, high))


def _measured_signal(settings: ValidationSettings, obj: StampObject) -> float:
    epochs = obj.exposures[:1] if settings.mode == "single" else obj.exposures
    return float(np.sqrt(sum(np.sum(np.square(e.image)) for e in epochs)))


def _noise_sigma(settings: ValidationSettings, obj: StampObject, snr: float) -> float:
    if not np.isfinite(snr):
        return float(settings.sim.noise_sigma)
    if settings.method == "bfd":
        return bfd_noise_sigma(settings)
    return _measured_signal(settings, obj) / snr


def template_seed(settings: ValidationSettings) -> int:
    """Seed of the BFD template sample (independent of the targets' objects)."""
    state = np.random.SeedSequence([settings.seed, _TEMPLATE_STREAM]).generate_state(1)
    return int(state[0])


def _template_object(settings: ValidationSettings, index: int) -> StampObject:
    return simulate_object(
        settings.sim, template_seed(settings), index, (0.0, 0.0), add_noise=False
    )


def _unsheared_target(settings: ValidationSettings, index: int) -> StampObject:
    """Target ``index`` of the run without shear (a template of ``"targets"`` priors)."""
    base, turn = _partner(settings, index)
    obj = simulate_object(
        settings.sim, settings.seed, base, (0.0, 0.0), add_noise=False, rotate_shape=turn
    )
    return _as_object(obj, index)


@functools.lru_cache(maxsize=8)
def _reference_signal(settings_json: str) -> float:
    settings = ValidationSettings.model_validate_json(settings_json)
    n = min(_REFERENCE_TEMPLATES, settings.bfd_templates)
    return float(np.median([_measured_signal(settings, _template_object(settings, j))
                            for j in range(n)]))  # fmt: skip


def bfd_noise_sigma(settings: ValidationSettings) -> float:
    """The pixel noise of every object of a BFD run (see the module docstring)."""
    if settings.snr is None:
        return float(settings.sim.noise_sigma)
    reference = _reference_signal(settings.model_dump_json())
    return reference / float(np.sqrt(settings.snr[0] * settings.snr[1]))


def _with_noise(obj: StampObject, noise: np.ndarray, sigma: float) -> list[Exposure]:
    return [
        exposure.replace(image=exposure.image + sigma * plane, variance=sigma**2)
        for exposure, plane in zip(obj.exposures, noise, strict=True)
    ]


def _failed(settings: ValidationSettings, flags: int) -> dict[str, np.ndarray]:
    if settings.method == "bfd":
        record = np.zeros(1, dtype=BFD_DTYPE)
        record["flags"] = flags
        return {"bfd": record}
    if settings.method == "anacal":
        return {"anacal": anacal_adapter.empty_anacal_record(flags)}
    return {name: empty_record(flags) for name in METACAL_TYPES}


def _build_stamp_cell(
    cell: Cell, exposures: list[Exposure], config: BuildConfig, seed: int
) -> CellCoadd:
    """The stamp cell's coadd. The stamp cell holds a 51-pixel PSF stamp at most, which
    loses 1e-4 to 5e-4 of the simulator's Moffat PSFs (docs/validation.md): known, so the
    builder's warning, which would come with every object, is not repeated."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PsfStampWarning)
        return build_cell(cell, exposures, config, seed=seed)


def object_position(settings: ValidationSettings, index: int) -> tuple[float, float]:
    """Offset ``(dx, dy)``, coadd pixels, of object ``index`` from its cell's centre pixel
    (``(0, 0)`` unless ``settings.object_offset``; ring partners share it)."""
    if settings.object_offset <= 0.0:
        return 0.0, 0.0
    base, _ = _partner(settings, index)
    limit = settings.object_offset
    dx, dy = _generator(settings, base, _POSITION_STREAM).uniform(-limit, limit, 2)
    return float(dx), float(dy)


def _measure_coadd(
    settings: ValidationSettings,
    cell: Cell,
    exposures: list[Exposure],
    position: tuple[float, float] | None = None,
) -> tuple[dict[str, np.ndarray], int]:
    """Build and measure one member; ``position``: the object's array position in the
    cell, measured with ``psf_at`` there (None: on the centre pixel, with ``cell.psf``)."""
    coadd = _build_stamp_cell(cell, exposures, settings.build, settings.seed)
    if coadd.is_empty:
        return _failed(settings, NO_COADD), 0
    obs = to_observation(coadd, noise_index=settings.noise_index)
    jac = obs["jacobian"]
    centre = (jac["col0"], jac["row0"])
    if position is not None:
        obs["psf"]["image"] = coadd.psf_at(*position)
        centre = position
    if settings.method == "bfd":
        measured = bfd_measurement(
            settings, obs["image"], obs["psf"]["image"], observation_jacobian(obs),
            centre, noise_images=[obs["noise"]],
        )  # fmt: skip
        return measured, coadd.n_used
    if settings.method == "anacal":
        record = anacal_adapter.measure_fpfs(
            obs["image"], obs["psf"]["image"], obs["noise"], observation_jacobian(obs),
            obs["meta"]["noise_variance"], centre, sigma_arcsec=settings.anacal_sigma,
        )  # fmt: skip
        return {"anacal": record}, coadd.n_used
    result = measure_metacal(
        obs["image"],
        obs["psf"]["image"],
        obs["noise"],
        observation_jacobian(obs),
        noise_sigma=float(np.sqrt(obs["meta"]["noise_variance"])),
        step=settings.step,
        psf=settings.reconvolution_psf,
        guess_centroid=centre,
        shape=settings.shape,
        weight_fwhm=settings.wmom_fwhm,
    )
    return result, coadd.n_used


def _as_object(obj: StampObject, index: int) -> StampObject:
    """``obj`` as object ``index`` (its exposures' detector, which keys the builder's noise
    realizations)."""
    if obj.index == index:
        return obj
    exposures = [e.replace(detector=int(index)) for e in obj.exposures]
    return dataclasses.replace(obj, index=int(index), exposures=exposures)


def bfd_templates(
    settings: ValidationSettings, sigma: float, indices: Sequence[int] | None = None
) -> list[bfd.KData]:
    """Fourier data of the BFD prior's deep templates.

    ``settings.bfd_templates`` objects of an independent sample (:func:`template_seed`),
    simulated with the run's settings but unsheared, with pixel noise ``sigma / 100``,
    coadded into the stamp cell by the builder (``coadd`` mode), taken from their first
    epoch (``single`` mode) or with their epochs' Fourier data summed (``multi-epoch``
    mode), exactly as the targets; templates that cannot be measured are skipped.

    With ``settings.bfd_template_sample == "targets"`` the templates are instead the
    targets ``indices`` themselves, unsheared (same galaxies, PSFs, shifts and WCSs, their
    own template noise): the prior is then exactly the targets' population, the limit in
    which BFD can be checked at high S/N (see ``docs/validation.md``).
    """
    cell = stamp_cell(settings) if settings.mode == "coadd" else None
    weight = bfd.KSigmaWeight(sigma=settings.bfd_sigma)
    size = settings.sim.stamp_size
    seed = template_seed(settings)
    if settings.bfd_template_sample == "targets":
        if indices is None:
            raise CellCoaddValueError("templates from the targets need the targets' indices")
        objects = [_unsheared_target(settings, int(i)) for i in indices]
    else:
        objects = [_template_object(settings, j) for j in range(settings.bfd_templates)]
    out = []
    for obj in objects:
        j = obj.index
        rng = np.random.default_rng(np.random.SeedSequence([seed, j, _EPOCH_NOISE_STREAM]))
        noise = rng.standard_normal((len(obj.exposures), size, size))
        exposures = _with_noise(obj, noise, sigma / 100.0)
        try:
            if cell is not None:
                coadd = _build_stamp_cell(cell, exposures, settings.build, seed)
                if coadd.is_empty:
                    continue
                obs = to_observation(coadd, noise_index=settings.noise_index)
                jac = obs["jacobian"]
                data = bfd.fourier_data(
                    obs["image"], obs["psf"]["image"], observation_jacobian(obs),
                    weight=weight, centre=(jac["col0"], jac["row0"]),
                    oversample=settings.bfd_oversample,
                )  # fmt: skip
            elif settings.mode == "multi-epoch":
                geometry = EpochGeometry.of(obj, settings.build.stamp_size)
                data = bfd_epoch_sum(settings, exposures, geometry, None)
            else:
                x, y = obj.epochs[0].position
                centre = (int(round(x)), int(round(y)))
                exposure = exposures[0]
                psf = epoch_psf_image(exposure, *centre, settings.build.stamp_size)
                data = bfd.fourier_data(
                    exposure.image, psf, exposure.local_jacobian(*centre), weight=weight,
                    centre=centre, oversample=settings.bfd_oversample,
                )  # fmt: skip
        except bfd.BfdError:
            continue
        if bfd.measure_moments(data).converged:
            out.append(data)
    if not out:
        raise BfdError("no usable BFD template")
    return out


def measure_pair(
    settings: ValidationSettings, index: int, cell: Cell | None = None
) -> PairMeasurement:
    """Simulate object ``index`` sheared by ``+g`` and ``-g`` and measure both members.

    See the module docstring for the procedure. ``cell`` is :func:`stamp_cell` of the
    settings (made here when not given; pass it to reuse it across objects).
    """
    start = time.process_time()
    if settings.mode == "coadd" and cell is None:
        cell = stamp_cell(settings)
    g1, g2 = settings.sim.shear
    base, turn = _partner(settings, index)
    plus, minus = (
        _as_object(obj, index)
        for obj in simulate_sheared(
            settings.sim, settings.seed, base, [(g1, g2), (-g1, -g2)], add_noise=False,
            rotate_shape=turn,
        )
    )  # fmt: skip
    snr = _target_snr(settings, index)
    sigma = _noise_sigma(settings, plus, snr)
    size = settings.sim.stamp_size
    noise = _generator(settings, index, _EPOCH_NOISE_STREAM).standard_normal(
        (len(plus.exposures), size, size)
    )
    if settings.mode != "coadd":
        # metacal's (and AnaCal's) own noise realizations, independent of the image
        # noise; the first epoch's is the same in single and multi-epoch modes
        n_planes = 1 if settings.mode == "single" else len(plus.exposures)
        own_noise = _generator(settings, index, _SINGLE_NOISE_STREAM).standard_normal(
            (n_planes, size, size)
        )
    if settings.mode == "multi-epoch":  # the same epochs' geometry and PSFs in both members
        geometry = EpochGeometry.of(plus, settings.build.stamp_size)
        reconv = common_psf(settings, geometry) if settings.method == "metacal" else None
    position = None
    if settings.mode == "coadd" and settings.object_offset > 0.0:
        cell, *at = offset_cell(settings, *object_position(settings, index))
        position = (at[0], at[1])
    results = []
    n_inputs = 1
    for obj in (plus, minus):
        exposures = _with_noise(obj, noise, sigma)
        if settings.mode == "coadd":
            assert cell is not None  # made above
            measured, n_inputs = _measure_coadd(settings, cell, exposures, position)
        elif settings.mode == "multi-epoch":
            measured = measure_multi_epoch(settings, exposures, geometry, sigma, own_noise, reconv)
            n_inputs = len(exposures)
        else:
            measured = measure_single_epoch(
                settings, obj, exposures[0], sigma, sigma * own_noise[0]
            )
        results.append(measured)
    return PairMeasurement(
        index=int(index),
        plus=results[0],
        minus=results[1],
        noise_sigma=sigma,
        snr=snr,
        n_inputs=n_inputs,
        cpu_seconds=time.process_time() - start,
    )


__all__ = [
    "NO_COADD",
    "PairCatalogue",
    "PairMeasurement",
    "bfd_noise_sigma",
    "bfd_templates",
    "measure_pair",
    "object_position",
]
