"""A tiny survey field for tract-run tests: a sky map of 2 x 2 small patches and small
exposure files (TAN and TAN-SIP WCSs, dithered visits) written by the tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from exposure_factory import make_exposure

from cellcoadd.geometry import SkyMap, SkyMapConfig
from cellcoadd.io.exposures.exposure_io import write_exposure
from cellcoadd.model.build_config import BuildConfig

#: 3 x 3 patches of 2 x 2 cells of 40 px (+5 px borders) at 0.2"/px: a tract of 48"
SKYMAP_CONFIG = SkyMapConfig(
    pixel_scale=0.2, cell_inner=40, cell_border=5, cells_per_patch=2, patches_per_tract=3
)
#: the tract straddles RA 0/360
CENTER = (0.0, -30.0)
BUILD = BuildConfig(n_noise=1, psf_size=15, units="count", zero_point=30.0)


def skymap(patches_per_tract: int = 3) -> SkyMap:
    config = SKYMAP_CONFIG.model_copy(update={"patches_per_tract": patches_per_tract})
    return SkyMap.from_centers([CENTER], config)


def write_field(
    root: Path,
    n_visits: int = 2,
    *,
    patches_per_tract: int = 3,
    shape: tuple[int, int] = (110, 110),
    start_visit: int = 0,
) -> list[Path]:
    """Exposure files covering the tract: per visit, one detector centred on each patch
    (dithered by a few pixels), SIP on odd visits; ``visit{v}-det{d}.fits`` in ``root``.

    An exposure covers its patch's inner cells edge-free and touches only the patches
    next to its own."""
    root.mkdir(parents=True, exist_ok=True)
    tract = skymap(patches_per_tract)[0]
    rng = np.random.default_rng(start_visit)
    paths = []
    for visit in range(start_visit, start_visit + n_visits):
        for detector, patch in enumerate(tract.patches):
            path = root / f"visit{visit}-det{detector}.fits"
            paths.append(_write_on_patch(path, tract, patch, rng, visit, detector, "r", shape))
    return paths


def _write_on_patch(
    path: Path,
    tract,
    patch,
    rng: np.random.Generator,
    visit: int,
    detector: int,
    band: str,
    shape: tuple[int, int],
) -> Path:
    """One exposure centred on ``patch`` (dithered by a few pixels, slightly rotated, SIP
    on odd visits) written to ``path``."""
    box = patch.inner_bbox
    x = (box.x_start + box.x_stop - 1) / 2 + rng.uniform(-3, 3)
    y = (box.y_start + box.y_stop - 1) / 2 + rng.uniform(-3, 3)
    ra, dec = tract.pixel_to_sky(x, y)
    exposure = make_exposure(
        (float(ra[0]), float(dec[0])),
        shape=shape,
        pixel_scale=0.2,
        rotation_deg=float(rng.uniform(0, 2)),
        sip=visit % 2 == 1,
        noise_sigma=1.0,
        visit=visit,
        detector=detector,
        seed=visit * 100 + detector,
        band=band,
    )
    write_exposure(exposure, path, overwrite=True)
    return path


#: two tracts side by side, overlapping by ~4 arcsec (their inner regions meet at RA 0.0045)
SURVEY_CENTERS = ((0.0, -30.0), (0.009, -30.0))


def survey_skymap(patches_per_tract: int = 2) -> SkyMap:
    """Two small tracts of ``patches_per_tract`` squared patches (see :data:`SKYMAP_CONFIG`)."""
    config = SKYMAP_CONFIG.model_copy(update={"patches_per_tract": patches_per_tract})
    return SkyMap.from_centers(list(SURVEY_CENTERS), config)


def write_survey(
    root: Path,
    bands: tuple[str, ...] = ("g", "r"),
    n_visits: int = 2,
    *,
    patches_per_tract: int = 2,
    shape: tuple[int, int] = (110, 110),
) -> list[Path]:
    """Exposure files over both tracts of :func:`survey_skymap` in every band: per band
    and visit, one detector centred on each patch of each tract (dithered, SIP on odd
    visits); ``{band}-visit{v}-det{d}.fits`` in ``root``. Visits are numbered across bands
    (band k has visits ``k * 100 + v``)."""
    root.mkdir(parents=True, exist_ok=True)
    sky = survey_skymap(patches_per_tract)
    paths = []
    for k, band in enumerate(bands):
        rng = np.random.default_rng(k)
        for v in range(n_visits):
            visit = k * 100 + v
            detector = 0
            for tract in sky:
                for patch in tract.patches:
                    path = root / f"{band}-visit{visit}-det{detector}.fits"
                    paths.append(
                        _write_on_patch(path, tract, patch, rng, visit, detector, band, shape)
                    )
                    detector += 1
    return paths
