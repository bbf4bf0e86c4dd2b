"""Simulations to files: the exposure files, truth tables and descriptions of a run.

The simulations (:mod:`cellcoadd.sim`) return in-memory results; these functions write
them, for ``cellcoadd simulate`` and ``cellcoadd demo``. Each refuses to replace an
existing file unless ``overwrite`` is set (raising :class:`FileExistsError`). Every file
is written atomically (:func:`cellcoadd.io._files.atomic.atomic_write`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from astropy.table import Table

from cellcoadd.io._files.atomic import atomic_write, atomic_write_text
from cellcoadd.io.exposures.exposure_io import write_exposure
from cellcoadd.sim.field import FieldSimulation
from cellcoadd.sim.stamps import StampObject, stamps_truth_tables


def write_field_simulation(
    simulation: FieldSimulation,
    directory: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    exposures: bool = True,
) -> list[Path]:
    """Write a field simulation's exposures and description into ``directory``.

    Exposure files are ``visit{visit:04d}-det{detector:02d}.fits``, followed by
    ``skymap.json``, ``simulation.json`` (configuration, seed, tract, patch: see
    :meth:`FieldSimulation.description`), ``truth.fits`` and ``visits.fits``.

    Parameters
    ----------
    simulation : FieldSimulation
        Output of :func:`cellcoadd.sim.simulate_field`.
    directory : path
        Output folder, created if missing.
    overwrite : bool
        Replace existing files.
    exposures : bool
        Write the exposure files (the bulk of the output); False writes only the four
        small description files.

    Returns
    -------
    list of Path
        The written files, in that order.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for exposure in simulation.exposures if exposures else []:
        name = f"visit{exposure.visit:04d}-det{exposure.detector:02d}.fits"
        paths.append(write_exposure(exposure, out / name, overwrite=overwrite))
    for name, text in (
        ("skymap.json", simulation.skymap.to_json()),
        ("simulation.json", json.dumps(simulation.description(), indent=2) + "\n"),
    ):
        paths.append(atomic_write_text(out / name, text, overwrite=overwrite))
    for name, table in (("truth.fits", simulation.truth), ("visits.fits", simulation.visits)):
        paths.append(_write_table(table, out / name, overwrite))
    return paths


def write_stamps(
    objects: list[StampObject], directory: str | os.PathLike[str], *, overwrite: bool = False
) -> list[Path]:
    """Write stamp objects as ``object{index:05d}/epoch{epoch:02d}.fits`` exposures plus
    ``truth.fits`` and ``epochs.fits`` (see :func:`cellcoadd.sim.stamps_truth_tables`).

    Parameters
    ----------
    objects : list of StampObject
        Output of :func:`cellcoadd.sim.simulate_stamps` (or of several
        :func:`cellcoadd.sim.simulate_object` calls).
    directory : path
        Output folder, created if missing.
    overwrite : bool
        Replace existing files.

    Returns
    -------
    list of Path
        The written files: the exposures, then the two tables.
    """
    out = Path(directory)
    paths = []
    for obj in objects:
        folder = out / f"object{obj.index:05d}"
        folder.mkdir(parents=True, exist_ok=True)
        for epoch, exposure in enumerate(obj.exposures):
            path = folder / f"epoch{epoch:02d}.fits"
            paths.append(write_exposure(exposure, path, overwrite=overwrite))
    out.mkdir(parents=True, exist_ok=True)
    for name, table in zip(
        ("truth.fits", "epochs.fits"), stamps_truth_tables(objects), strict=True
    ):
        paths.append(_write_table(table, out / name, overwrite))
    return paths


def _write_table(table: Table, path: Path, overwrite: bool) -> Path:
    def write(temporary: Path) -> None:
        table.write(temporary, format="fits")

    return atomic_write(path, write, overwrite=overwrite)
