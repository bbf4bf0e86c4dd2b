"""Flat focal-plane models: where a camera's detectors are, for edge-rejection statistics.

A focal plane is a set of axis-aligned rectangular detectors (imaging areas only) on a flat
plane; positions are given in mm and converted to arcsec with the plate scale
``pixel_scale / pixel_size``. Over a ~3.5 deg field the gnomonic distortion of a flat-sky
treatment changes scales by < 0.1 %, negligible for counting detector edges.

Two builders are provided: :func:`lsst_focal_plane` (the default; 189 science CCDs in 21
rafts) and :func:`decam_like_focal_plane` (an approximate DES/DECam layout, 62 CCDs), both
returning a :class:`FocalPlaneConfig` that any other camera can also be described with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator


class Detector(BaseModel):
    """One detector's imaging area: an axis-aligned rectangle.

    Parameters
    ----------
    name : str
        Detector name (e.g. ``"R22_S11"``).
    x_mm, y_mm : float
        Centre of the imaging area on the focal plane, mm.
    nx, ny : int
        Imaging pixels along x and y.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    x_mm: float
    y_mm: float
    nx: int = Field(gt=0)
    ny: int = Field(gt=0)


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
            raise ValueError(
                f"detectors {self.detectors[first].name} and {self.detectors[second].name} overlap"
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
        raise ValueError("CCD or raft pitch too small: detectors would overlap")
    detectors = []
    for raft_y in range(5):
        for raft_x in range(5):
            if raft_x in (0, 4) and raft_y in (0, 4):
                continue  # corner positions hold wavefront/guider sensors, not science CCDs
            for ccd_y in range(3):
                for ccd_x in range(3):
                    detectors.append(
                        Detector(
                            name=f"R{raft_y}{raft_x}_S{ccd_y}{ccd_x}",
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
    detectors = []
    for row, count in enumerate(row_counts):
        y_mm = (row - (len(row_counts) - 1) / 2) * (height + gap_y_mm)
        for column in range(count):
            x_mm = (column - (count - 1) / 2) * (width + gap_x_mm)
            detectors.append(
                Detector(name=f"row{row}_ccd{column}", x_mm=x_mm, y_mm=y_mm, nx=4096, ny=2048)
            )
    return FocalPlaneConfig(
        name="decam-like",
        pixel_size_um=15.0,
        pixel_scale=0.263,
        field_radius_deg=field_radius_deg,
        detectors=tuple(detectors),
    )
