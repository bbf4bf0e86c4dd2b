"""A small focal plane of CCDs with gaps, its per-CCD WCSs, and dither patterns.

Focal-plane coordinates are pixels relative to the boresight, along the CCD axes; CCD
pixel ``(i, j)`` of a detector sits at ``(x0 + i, y0 + j)``. The layout is symmetric about
the boresight. Each CCD's WCS is the focal plane's gnomonic projection about the
boresight (CRPIX = the boresight in that CCD's pixels), optionally with a radial SIP
distortion ``x' = x (1 + k r^2)`` about the boresight, so the CCDs of a visit fit together
exactly as on the sky.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from astropy.wcs import WCS, Sip

from cellcoadd.geometry.box import Box
from cellcoadd.sim.config import FieldConfig
from cellcoadd.sim.stamps import tan_wcs

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class Detector:
    """One CCD: its id, size and position in the focal plane.

    Attributes
    ----------
    id : int
        Detector number.
    x0, y0 : float
        Focal-plane position of the CCD's pixel (0, 0), pixels from the boresight.
    nx, ny : int
        Size, pixels.
    """

    id: int
    x0: float
    y0: float
    nx: int
    ny: int

    @property
    def boresight_pixel(self) -> tuple[float, float]:
        """The boresight in this CCD's 0-based pixel coordinates."""
        return (-self.x0, -self.y0)

    @property
    def box(self) -> Box:
        return Box.from_shape((self.ny, self.nx))


@dataclass(frozen=True)
class FocalPlane:
    """CCDs on a regular grid separated by gaps, at one nominal pixel scale.

    Attributes
    ----------
    detectors : tuple of Detector
        Numbered row by row from the lower left.
    pixel_scale : float
        arcsec/pixel.
    """

    detectors: tuple[Detector, ...]
    pixel_scale: float

    @classmethod
    def from_config(cls, config: FieldConfig, pixel_scale: float) -> FocalPlane:
        """The ``n_ccd_x`` x ``n_ccd_y`` grid of ``ccd_nx`` x ``ccd_ny`` CCDs of ``config``."""
        width = config.n_ccd_x * config.ccd_nx + (config.n_ccd_x - 1) * config.ccd_gap
        height = config.n_ccd_y * config.ccd_ny + (config.n_ccd_y - 1) * config.ccd_gap
        detectors = []
        for j in range(config.n_ccd_y):
            for i in range(config.n_ccd_x):
                detectors.append(
                    Detector(
                        id=j * config.n_ccd_x + i,
                        x0=-(width - 1) / 2.0 + i * (config.ccd_nx + config.ccd_gap),
                        y0=-(height - 1) / 2.0 + j * (config.ccd_ny + config.ccd_gap),
                        nx=config.ccd_nx,
                        ny=config.ccd_ny,
                    )
                )
        return cls(detectors=tuple(detectors), pixel_scale=pixel_scale)

    @property
    def corner_radius(self) -> float:
        """Largest distance from the boresight to a CCD corner pixel, pixels."""
        return max(
            math.hypot(x, y)
            for d in self.detectors
            for x in (d.x0, d.x0 + d.nx - 1)
            for y in (d.y0, d.y0 + d.ny - 1)
        )

    def detector_wcs(
        self,
        detector: Detector,
        boresight: tuple[float, float],
        rotation_deg: float = 0.0,
        sip_k: float = 0.0,
    ) -> WCS:
        """WCS of ``detector`` for a pointing at ``boresight`` (ra, dec deg).

        ``rotation_deg`` turns the focal plane on the sky (counter-clockwise from
        x -> West); ``sip_k`` (1/pixel^2) adds the radial SIP distortion.
        """
        theta = math.radians(rotation_deg)
        c, s = math.cos(theta), math.sin(theta)
        jacobian = self.pixel_scale * np.array([[c, -s], [s, c]])
        bx, by = detector.boresight_pixel
        wcs = tan_wcs(boresight[0], boresight[1], bx, by, jacobian)
        if sip_k != 0.0:
            wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
            a = np.zeros((4, 4))
            b = np.zeros((4, 4))
            a[3, 0] = a[1, 2] = sip_k  # x r^2 = x^3 + x y^2
            b[2, 1] = b[0, 3] = sip_k  # y r^2 = x^2 y + y^3
            wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
            wcs.wcs.set()
        return wcs


def dither_offsets(config: FieldConfig, n_visits: int, rng: np.random.Generator) -> np.ndarray:
    """Pointing offsets ``(du, dv)`` in arcsec, shape (n_visits, 2).

    ``random``: uniform over the disk of radius ``dither_radius``; ``spiral``: a Vogel
    (sunflower) spiral that fills the same disk evenly, starting at a random angle;
    ``none``: zeros.
    """
    radius = config.dither_radius
    if config.dither == "none" or n_visits == 0:
        return np.zeros((n_visits, 2))
    if config.dither == "random":
        # one row per visit, so the first visits do not depend on how many follow
        uniform = rng.uniform(size=(n_visits, 2))
        r = radius * np.sqrt(uniform[:, 0])
        phi = 2.0 * np.pi * uniform[:, 1]
    else:
        k = np.arange(n_visits)
        r = radius * np.sqrt((k + 0.5) / n_visits)
        phi = rng.uniform(0.0, 2.0 * np.pi) + k * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), r * np.sin(phi)])


def offset_position(
    ra: float, dec: float, du: np.ndarray, dv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sky position(s) (deg) at tangent-plane offsets ``(du, dv)`` arcsec from (ra, dec).

    ``du`` points West and ``dv`` North (GalSim's sky frame).
    """
    plane = tan_wcs(ra, dec, 0.0, 0.0, np.eye(2))
    out_ra, out_dec = plane.wcs_pix2world(np.atleast_1d(du), np.atleast_1d(dv), 0)
    return np.mod(out_ra, 360.0), out_dec
