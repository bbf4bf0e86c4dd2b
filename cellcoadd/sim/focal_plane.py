"""Focal planes: detectors on a flat focal plane, for simulating exposures and counting edges.

One :class:`Detector` type describes a detector's imaging area (its centre on the focal
plane, mm, and its size, pixels) for both users:

* :class:`FocalPlane`, the simulation's small camera (:mod:`cellcoadd.sim.field`): CCDs on
  a regular grid with gaps, each with a WCS for a pointing. Its focal-plane coordinates
  are pixels relative to the boresight, along the CCD axes (its nominal pixel is 1 mm, so
  positions convert exactly); CCD pixel ``(i, j)`` of a detector sits at
  ``(x0 + i, y0 + j)`` with ``(x0, y0)`` from :meth:`Detector.origin_pixels`. The layout is
  symmetric about the boresight. Each CCD's WCS is the focal plane's gnomonic projection
  about the boresight (CRPIX = the boresight in that CCD's pixels), optionally with a
  radial SIP distortion ``x' = x (1 + k r^2)`` about the boresight, so the CCDs of a visit
  fit together exactly as on the sky.
* :class:`FocalPlaneConfig`, a real camera's layout for the edge-rejection statistics
  (:mod:`cellcoadd.analysis.rejection`): axis-aligned rectangular detectors (imaging areas
  only) whose positions in mm are converted to arcsec with the plate scale
  ``pixel_scale / pixel_size``. Over a ~3.5 deg field the gnomonic distortion of a
  flat-sky treatment changes scales by < 0.1 %, negligible for counting detector edges.
  Two builders are provided: :func:`lsst_focal_plane` (189 science CCDs in 21 rafts) and
  :func:`decam_like_focal_plane` (an approximate DES/DECam layout, 62 CCDs); any other
  camera can be described the same way.

The dither patterns that move these focal planes over the sky are in
:mod:`cellcoadd.sim.dither`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from astropy.wcs import WCS, Sip
from pydantic import BaseModel, ConfigDict, Field, model_validator

from cellcoadd.errors import GeometryError
from cellcoadd.geometry.box import Box
from cellcoadd.geometry.wcs_utils import tan_wcs
from cellcoadd.sim.config import FieldConfig

#: Pixel size of the simulation's camera, micron: a nominal 1 mm, so that its detectors'
#: positions in mm are positions in pixels and convert without rounding.
SIM_PIXEL_SIZE_UM = 1000.0


class Detector(BaseModel):
    """One detector's imaging area: an axis-aligned rectangle of ``nx`` x ``ny`` pixels.

    Parameters
    ----------
    name : str
        Detector name (e.g. ``"R22_S11"``).
    x_mm, y_mm : float
        Centre of the imaging area on the focal plane, mm.
    nx, ny : int
        Imaging pixels along x and y.
    id : int
        Detector number (the ``detector`` of the simulation's exposures).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    x_mm: float
    y_mm: float
    nx: int = Field(gt=0)
    ny: int = Field(gt=0)
    id: int = Field(0, ge=0)

    @property
    def box(self) -> Box:
        """The detector's pixels, ``[0, nx) x [0, ny)``."""
        return Box.from_shape((self.ny, self.nx))

    def origin_pixels(self, pixel_size_um: float) -> tuple[float, float]:
        """Focal-plane position of the detector's pixel (0, 0), pixels from the optical axis.

        Parameters
        ----------
        pixel_size_um : float
            Physical pixel size, micron.
        """
        pixel_mm = pixel_size_um / 1000.0
        return (
            self.x_mm / pixel_mm - (self.nx - 1) / 2.0,
            self.y_mm / pixel_mm - (self.ny - 1) / 2.0,
        )


@dataclass(frozen=True)
class FocalPlane:
    """The simulation's camera: CCDs on a regular grid separated by gaps.

    Attributes
    ----------
    detectors : tuple of Detector
        Numbered row by row from the lower left.
    pixel_scale : float
        arcsec/pixel.
    pixel_size_um : float
        Pixel size, micron (the nominal :data:`SIM_PIXEL_SIZE_UM` for simulated CCDs).
    """

    detectors: tuple[Detector, ...]
    pixel_scale: float
    pixel_size_um: float = SIM_PIXEL_SIZE_UM

    @classmethod
    def from_config(cls, config: FieldConfig, pixel_scale: float) -> FocalPlane:
        """The ``n_ccd_x`` x ``n_ccd_y`` grid of ``ccd_nx`` x ``ccd_ny`` CCDs of ``config``."""
        width = config.n_ccd_x * config.ccd_nx + (config.n_ccd_x - 1) * config.ccd_gap
        height = config.n_ccd_y * config.ccd_ny + (config.n_ccd_y - 1) * config.ccd_gap
        pixel_mm = SIM_PIXEL_SIZE_UM / 1000.0
        detectors: list[Detector] = []
        for j in range(config.n_ccd_y):
            for i in range(config.n_ccd_x):
                # focal-plane position of the CCD's pixel (0, 0), pixels from the boresight
                x0 = -(width - 1) / 2.0 + i * (config.ccd_nx + config.ccd_gap)
                y0 = -(height - 1) / 2.0 + j * (config.ccd_ny + config.ccd_gap)
                index = j * config.n_ccd_x + i
                detectors.append(
                    Detector(
                        name=f"ccd{index:02d}",
                        id=index,
                        x_mm=(x0 + (config.ccd_nx - 1) / 2.0) * pixel_mm,
                        y_mm=(y0 + (config.ccd_ny - 1) / 2.0) * pixel_mm,
                        nx=config.ccd_nx,
                        ny=config.ccd_ny,
                    )
                )
        return cls(detectors=tuple(detectors), pixel_scale=pixel_scale)

    def origin_pixels(self, detector: Detector) -> tuple[float, float]:
        """Focal-plane position ``(x0, y0)`` of ``detector``'s pixel (0, 0), pixels."""
        return detector.origin_pixels(self.pixel_size_um)

    def boresight_pixel(self, detector: Detector) -> tuple[float, float]:
        """The boresight in ``detector``'s 0-based pixel coordinates."""
        x0, y0 = self.origin_pixels(detector)
        return (-x0, -y0)

    @property
    def corner_radius(self) -> float:
        """Largest distance from the boresight to a CCD corner pixel, pixels."""
        origins = [(self.origin_pixels(d), d) for d in self.detectors]
        return max(
            math.hypot(x, y)
            for (x0, y0), d in origins
            for x in (x0, x0 + d.nx - 1)
            for y in (y0, y0 + d.ny - 1)
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
        bx, by = self.boresight_pixel(detector)
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


def offset_position(
    ra: float, dec: float, du: np.ndarray, dv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sky position(s) (deg) at tangent-plane offsets ``(du, dv)`` arcsec from (ra, dec).

    ``du`` points West and ``dv`` North (GalSim's sky frame).
    """
    plane = tan_wcs(ra, dec, 0.0, 0.0, np.eye(2))
    out_ra, out_dec = plane.wcs_pix2world(np.atleast_1d(du), np.atleast_1d(dv), 0)
    return np.mod(out_ra, 360.0), out_dec


class FocalPlaneConfig(BaseModel):
    """A camera's detector layout (frozen).

    Parameters
    ----------
    name : str
        Camera name.
    pixel_size_um : float
        Physical pixel size, micron.
    pixel_scale : float
        Plate scale at the pixel, arcsec/pixel.
    field_radius_deg : float
        Radius of the nominal circular field of view, deg; sets the default dither size.
    detectors : tuple of Detector
        Non-overlapping imaging areas; gaps between them are wherever no detector is.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    pixel_size_um: float = Field(gt=0)
    pixel_scale: float = Field(gt=0, description="arcsec/pixel")
    field_radius_deg: float = Field(gt=0)
    detectors: tuple[Detector, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _check_no_overlap(self) -> FocalPlaneConfig:
        bounds = self.bounds_arcsec()
        x_overlap = (bounds[:, None, 0] < bounds[None, :, 1]) & (
            bounds[None, :, 0] < bounds[:, None, 1]
        )
        y_overlap = (bounds[:, None, 2] < bounds[None, :, 3]) & (
            bounds[None, :, 2] < bounds[:, None, 3]
        )
        overlap = x_overlap & y_overlap
        np.fill_diagonal(overlap, False)
        if overlap.any():
            first, second = np.argwhere(overlap)[0]
            raise GeometryError(
                f"detectors {self.detectors[first].name} and {self.detectors[second].name} overlap",
                value=(self.detectors[first].name, self.detectors[second].name),
            )
        return self

    @property
    def arcsec_per_mm(self) -> float:
        """Plate scale, arcsec/mm."""
        return self.pixel_scale / (self.pixel_size_um * 1e-3)

    def bounds_arcsec(self) -> np.ndarray:
        """Detector imaging areas ``[xmin, xmax, ymin, ymax]``, arcsec, shape ``(n_detectors, 4)``.

        Each area is half-open, ``[xmin, xmax) x [ymin, ymax)``.
        """
        centres = np.array([[d.x_mm, d.y_mm] for d in self.detectors]) * self.arcsec_per_mm
        half = 0.5 * np.array([[d.nx, d.ny] for d in self.detectors]) * self.pixel_scale
        return np.column_stack(
            [
                centres[:, 0] - half[:, 0],
                centres[:, 0] + half[:, 0],
                centres[:, 1] - half[:, 1],
                centres[:, 1] + half[:, 1],
            ]
        )

    def min_detector_side_arcsec(self) -> float:
        """Shortest side of any detector, arcsec."""
        return float(min(min(d.nx, d.ny) for d in self.detectors) * self.pixel_scale)

    def outer_radius_arcsec(self) -> float:
        """Distance from the optical axis to the farthest detector corner, arcsec."""
        bounds = self.bounds_arcsec()
        xs, ys = np.abs(bounds[:, :2]).max(axis=1), np.abs(bounds[:, 2:]).max(axis=1)
        return float(np.hypot(xs, ys).max())

    def imaging_area_deg2(self) -> float:
        """Total imaging area, deg^2."""
        bounds = self.bounds_arcsec()
        return (
            float(np.sum((bounds[:, 1] - bounds[:, 0]) * (bounds[:, 3] - bounds[:, 2]))) / 3600**2
        )

    def locator(self) -> DetectorLocator:
        """A fast point -> detector lookup for this layout."""
        return DetectorLocator.from_bounds(self.bounds_arcsec())


@dataclass(frozen=True)
class DetectorLocator:
    """Vectorised point -> detector lookup for axis-aligned, non-overlapping detectors.

    All detector x edges and y edges cut the plane into a grid of tiles, each tile lying in
    exactly one detector or in none; a point is located with two binary searches.

    Attributes
    ----------
    x_edges, y_edges : ndarray
        Sorted unique detector edges, arcsec.
    tile_detector : ndarray, shape (len(x_edges) + 1, len(y_edges) + 1)
        Detector index of each tile, -1 for gaps and outside.
    bounds : ndarray, shape (n_detectors, 4)
        ``[xmin, xmax, ymin, ymax]`` of each detector, arcsec.
    """

    x_edges: np.ndarray
    y_edges: np.ndarray
    tile_detector: np.ndarray
    bounds: np.ndarray

    @classmethod
    def from_bounds(cls, bounds: np.ndarray) -> DetectorLocator:
        """Build the lookup from ``[xmin, xmax, ymin, ymax]`` rows (arcsec)."""
        bounds = np.asarray(bounds, dtype=float)
        x_edges = np.unique(bounds[:, :2])
        y_edges = np.unique(bounds[:, 2:])
        table = np.full((x_edges.size + 1, y_edges.size + 1), -1, dtype=np.int64)
        # Tile k spans [edges[k-1], edges[k]) (searchsorted side="right" convention below).
        x_lo = np.searchsorted(x_edges, bounds[:, 0]) + 1
        x_hi = np.searchsorted(x_edges, bounds[:, 1]) + 1
        y_lo = np.searchsorted(y_edges, bounds[:, 2]) + 1
        y_hi = np.searchsorted(y_edges, bounds[:, 3]) + 1
        for index in range(bounds.shape[0]):
            table[x_lo[index] : x_hi[index], y_lo[index] : y_hi[index]] = index
        return cls(x_edges=x_edges, y_edges=y_edges, tile_detector=table, bounds=bounds)

    def detector_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Index of the detector containing each point ``(x, y)`` (arcsec), -1 if none."""
        ix = np.searchsorted(self.x_edges, x, side="right")
        iy = np.searchsorted(self.y_edges, y, side="right")
        return self.tile_detector[ix, iy]


def lsst_focal_plane(
    ccd_pixels: int = 4096,
    ccd_pitch_mm: float = 42.25,
    raft_pitch_mm: float = 127.0,
    pixel_size_um: float = 10.0,
    pixel_scale: float = 0.2,
    field_radius_deg: float = 1.75,
) -> FocalPlaneConfig:
    """LSST-like focal plane: 21 rafts of 3 x 3 CCDs on a 5 x 5 raft grid without its corners.

    Defaults: square 4096-pixel CCDs of 10 micron pixels at 0.2"/px (40.96 mm = 13.65' per
    side); CCD centres 42.25 mm apart inside a raft and rafts 127 mm apart (the LSST camera's
    mechanical pitches), leaving 1.29 mm (26") of non-imaging gap between CCDs in a raft and
    1.54 mm (31") between rafts; about 9.6 deg^2 of imaging area, 93.6 % fill factor.

    Parameters
    ----------
    ccd_pixels : int
        Imaging pixels along each side of a CCD.
    ccd_pitch_mm, raft_pitch_mm : float
        Centre-to-centre spacing of CCDs within a raft and of rafts, mm.
    pixel_size_um, pixel_scale : float
        Pixel size (micron) and plate scale (arcsec/pixel).
    field_radius_deg : float
        Nominal field radius, deg (3.5 deg across).
    """
    ccd_mm = ccd_pixels * pixel_size_um * 1e-3
    if ccd_pitch_mm < ccd_mm or raft_pitch_mm < 2 * ccd_pitch_mm + ccd_mm:
        raise GeometryError(
            "CCD or raft pitch too small: detectors would overlap",
            value=(ccd_pitch_mm, raft_pitch_mm),
        )
    detectors: list[Detector] = []
    for raft_y in range(5):
        for raft_x in range(5):
            if raft_x in (0, 4) and raft_y in (0, 4):
                continue  # corner positions hold wavefront/guider sensors, not science CCDs
            for ccd_y in range(3):
                for ccd_x in range(3):
                    detectors.append(
                        Detector(
                            name=f"R{raft_y}{raft_x}_S{ccd_y}{ccd_x}",
                            id=len(detectors),
                            x_mm=(raft_x - 2) * raft_pitch_mm + (ccd_x - 1) * ccd_pitch_mm,
                            y_mm=(raft_y - 2) * raft_pitch_mm + (ccd_y - 1) * ccd_pitch_mm,
                            nx=ccd_pixels,
                            ny=ccd_pixels,
                        )
                    )
    return FocalPlaneConfig(
        name="lsst",
        pixel_size_um=pixel_size_um,
        pixel_scale=pixel_scale,
        field_radius_deg=field_radius_deg,
        detectors=tuple(detectors),
    )


def decam_like_focal_plane(
    gap_x_mm: float = 2.3,
    gap_y_mm: float = 3.0,
    field_radius_deg: float = 1.1,
) -> FocalPlaneConfig:
    """Approximate DES/DECam layout: 62 CCDs of 4096 x 2048 15-micron pixels at 0.263"/px.

    Twelve rows of CCDs (long side along x, 18' x 9'), holding 3, 4, 5, 6, 6, 7, 7, 6, 6, 5,
    4, 3 CCDs and centred on the optical axis, form a roughly hexagonal 2.2 deg field. The
    gaps are indicative only; this builder illustrates describing another camera.

    Parameters
    ----------
    gap_x_mm, gap_y_mm : float
        Gaps between neighbouring CCDs along and across rows, mm.
    field_radius_deg : float
        Nominal field radius, deg.
    """
    pixel_mm = 15e-3
    width, height = 4096 * pixel_mm, 2048 * pixel_mm
    row_counts = (3, 4, 5, 6, 6, 7, 7, 6, 6, 5, 4, 3)
    detectors: list[Detector] = []
    for row, count in enumerate(row_counts):
        y_mm = (row - (len(row_counts) - 1) / 2) * (height + gap_y_mm)
        for column in range(count):
            x_mm = (column - (count - 1) / 2) * (width + gap_x_mm)
            detectors.append(
                Detector(
                    name=f"row{row}_ccd{column}",
                    id=len(detectors),
                    x_mm=x_mm,
                    y_mm=y_mm,
                    nx=4096,
                    ny=2048,
                )
            )
    return FocalPlaneConfig(
        name="decam-like",
        pixel_size_um=15.0,
        pixel_scale=0.263,
        field_radius_deg=field_radius_deg,
        detectors=tuple(detectors),
    )
