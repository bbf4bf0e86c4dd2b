"""Compile the builder's numba kernels once, on a tiny patch, before a real build.

The kernels are compiled on first use and cached on disk by numba (``cache=True``):
the first build after an install spends tens of seconds compiling, later ones load the
cache in about a second. Without a warm-up that compilation happens inside the first
cells of a patch (in every worker process at once), so a progress bar sits at 0 % with
an ETA of many minutes. :func:`warm_up_kernels` compiles them in this process first, on
a 3 x 3-cell patch of one small simulated exposure (the same code path, so the same
specialisations), which ``make demo`` and ``cellcoadd demo`` run and announce.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

from cellcoadd.errors import PsfStampWarning
from cellcoadd.geometry import SkyMap, SkyMapConfig
from cellcoadd.model.build_config import BuildConfig

#: a tract of one patch of one 32-pixel cell (plus its border cells)
_TINY_SKYMAP = SkyMapConfig(
    pixel_scale=0.2, cell_inner=32, cell_border=4, cells_per_patch=1, patches_per_tract=1
)


def kernels_cached() -> bool:
    """Whether numba's on-disk cache of the builder kernels looks populated.

    A heuristic (numba's index files next to the kernel sources, or under
    ``NUMBA_CACHE_DIR``): True means a build will load, not compile, its kernels.
    """
    import os

    from cellcoadd.builder import kernels

    source_dir = Path(kernels.__file__).parent
    candidates = [source_dir / "__pycache__"]
    user_dir = os.environ.get("NUMBA_CACHE_DIR")
    if user_dir:  # numba then writes to <user dir>/<source folder name>_<hash>/
        candidates = sorted(Path(user_dir).glob(f"{source_dir.name}_*"))
    names = ("accumulate", "input_planes", "lanczos", "noise")
    for folder in candidates:
        if all(any(folder.glob(f"{name}.*.nbi")) for name in names):
            return True
    return False


#: How long the first build after an install compiles the kernels, as the README, the
#: tutorial and ``cellcoadd demo`` say it (measured: ``warm_up_kernels()`` on a cold cache
#: in a fresh clone, 11.6 s on an idle 2-core machine; 37.9 s on a busy one).
COMPILE_TIME = "about 12 s on an idle 2-core machine, up to 40 s on a busy one"


def warm_up_kernels(config: BuildConfig | None = None) -> float:
    """Compile (or load from the disk cache) every builder kernel; return the seconds taken.

    Builds a 3 x 3-cell patch of 32-pixel cells from one 128 x 128-pixel simulated CCD
    with a masked column and cosmic rays, serially in this process, with ``config``
    (default ``BuildConfig()``). Under a second when the cache is warm; on a cold cache
    :data:`COMPILE_TIME`.
    """
    from cellcoadd.builder import build_patch
    from cellcoadd.sim import FieldConfig, SimConfig, simulate_field

    start = time.perf_counter()
    skymap = SkyMap.from_centers([(60.0, -30.0)], _TINY_SKYMAP)
    field = FieldConfig(
        n_ccd_x=1,
        n_ccd_y=1,
        ccd_nx=128,
        ccd_ny=128,
        dither="none",
        galaxy_density=0.0,
        star_density=100.0,
        bad_columns=2.0,
        cosmic_rays=3.0,
    )
    sim = simulate_field(SimConfig(field=field), skymap, 0, (0, 0), 1, seed=0)
    with warnings.catch_warnings():  # the tiny cells' PSF stamps are no one's concern
        warnings.simplefilter("ignore", PsfStampWarning)
        build_patch(skymap[0].patch(0, 0), sim.exposures, config or BuildConfig(), progress=False)
    return time.perf_counter() - start


__all__ = ["COMPILE_TIME", "kernels_cached", "warm_up_kernels"]
