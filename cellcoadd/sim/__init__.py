"""GalSim simulations of the paper's section 3: isolated stamps and CCD fields.

* :func:`simulate_stamps` / :func:`simulate_stamp_pair`: exponential galaxies observed in
  10 epochs on 48 x 48 stamps at 0.27 arcsec/pixel (matched +g / -g pairs from one seed).
* :func:`simulate_field`: galaxies and stars over a patch, observed by a small focal plane
  of CCDs with gaps, dithered visits, masks and noise.
* :mod:`cellcoadd.sim.focal_plane` and :mod:`cellcoadd.sim.dither`: the focal planes
  (the simulation's camera, LSST- and DECam-like layouts) and the dither patterns, also
  used by the edge-rejection statistics of :mod:`cellcoadd.analysis`.

Results stay in memory (:class:`~cellcoadd.model.exposure.Exposure` objects and truth
tables); :mod:`cellcoadd.pipelines.simulation_files` writes them to files.

All distributions are in :class:`SimConfig` (paper defaults); every random number comes
from an explicitly seeded generator.
"""

from cellcoadd.geometry.wcs_utils import tan_wcs  # its home; re-exported for convenience
from cellcoadd.sim.config import (
    FieldConfig,
    GalaxyConfig,
    PsfConfig,
    SimConfig,
    WcsVariationConfig,
)
from cellcoadd.sim.dither import dither_offsets
from cellcoadd.sim.field import (
    DEMO_PATCH,
    DEMO_SKYMAP_CONFIG,
    FieldSimulation,
    demo_skymap,
    simulate_field,
)
from cellcoadd.sim.focal_plane import Detector, FocalPlane
from cellcoadd.sim.galaxies import (
    GalaxyProperties,
    draw_ellipticities,
    draw_galaxy_properties,
    draw_source,
    exponential_galaxy,
)
from cellcoadd.sim.psf import PsfParameters, draw_psf_parameters, moffat_psf
from cellcoadd.sim.stamps import (
    EpochTruth,
    StampObject,
    StampTruth,
    simulate_object,
    simulate_sheared,
    simulate_stamp_pair,
    simulate_stamps,
    stamps_truth_tables,
)

__all__ = [
    "DEMO_PATCH",
    "DEMO_SKYMAP_CONFIG",
    "Detector",
    "EpochTruth",
    "FieldConfig",
    "FieldSimulation",
    "FocalPlane",
    "GalaxyConfig",
    "GalaxyProperties",
    "PsfConfig",
    "PsfParameters",
    "SimConfig",
    "StampObject",
    "StampTruth",
    "WcsVariationConfig",
    "demo_skymap",
    "dither_offsets",
    "draw_ellipticities",
    "draw_galaxy_properties",
    "draw_psf_parameters",
    "draw_source",
    "exponential_galaxy",
    "moffat_psf",
    "simulate_field",
    "simulate_object",
    "simulate_sheared",
    "simulate_stamp_pair",
    "simulate_stamps",
    "stamps_truth_tables",
    "tan_wcs",
]
