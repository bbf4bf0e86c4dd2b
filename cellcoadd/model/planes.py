"""The one description of a cell's planes: name, dtype, shape, compression and unit of each.

Every place that handles a cell's planes plane by plane iterates :data:`PLANES` (the FITS
and HDF5 writers and readers, the file-size estimate, stitching, cell comparison, the
``info`` summary), so a plane is added or changed here. Besides its planes a cell stores
its table of inputs, :data:`INPUTS` (see :mod:`cellcoadd.model.inputs`).

Conventions are those of :mod:`cellcoadd.model.cell_coadd`: a cell-grid plane covers the
cell's outer box, ``plane[j, i]`` being tract pixel ``(x_start + i, y_start + j)``; a
per-realization plane has a leading axis of the ``K`` noise realizations; the PSF is an
odd square stamp centred on its central pixel. An optional plane
(:attr:`PlaneSpec.optional`) may be absent from a cell (``None``): all the cells of a patch
have it or none does, as the patch's build configuration says.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cellcoadd.model.psf_phase import MAP_FIELDS, PHASE_SIDE

#: Lossless compression that suits a plane's values. ``"float_bits"`` (float32 planes):
#: keep every IEEE-754 bit pattern (FITS: GZIP_2 float tile compression without
#: quantization, which viewers decode to floats, plus ``CCNFBITS`` listing the non-finite
#: pixels whose bits CFITSIO turns into its one NaN);
#: ``"integer"``: integer tile compression (FITS RICE_1); ``"none"``: stored as is in FITS.
#: HDF5 files shuffle + gzip every dataset when compressed, lossless whatever the kind.
Compression = Literal["float_bits", "integer", "none"]

#: What a plane's values are measured in. ``"flux"``: the patch's pixel unit
#: (``PatchMetadata.units``, ``BUNIT`` and for counts ``MAGZERO``); ``"flux_squared"``: its
#: square (``BUNIT`` of the square); ``"mask_bits"``: named bits (``MP_<NAME>`` keywords);
#: ``"fraction"``: dimensionless in [0, 1]; ``"normalised"``: dimensionless, sums to 1.
UnitKind = Literal["flux", "flux_squared", "mask_bits", "fraction", "normalised"]

#: Name of a cell's inputs table, stored beside its planes (FITS HDU, HDF5 dataset).
INPUTS = "inputs"


@dataclass(frozen=True)
class PlaneSpec:
    """How one plane of a cell is held in memory and stored.

    Attributes
    ----------
    name : str
        Attribute of :class:`~cellcoadd.model.cell_coadd.CellCoadd`, FITS ``PLANE`` /
        EXTNAME suffix (upper-cased), HDF5 dataset name.
    dtype : numpy.dtype
        In-memory dtype (native byte order); files store it little-endian (HDF5) or
        big-endian (FITS).
    per_realization : bool
        One layer per noise realization: shape ``(K, ny, nx)``; none stored when ``K = 0``
        in FITS (no zero-size images there).
    stamp : bool
        A PSF-sized square stamp ``(psf_size, psf_size)`` instead of the outer box.
    compression : Compression
        Lossless compression kind (see :data:`Compression`).
    unit : UnitKind
        Unit kind of the values (see :data:`UnitKind`).
    doc : str
        One line saying what the plane holds.
    layers : int
        A leading axis of this fixed length (0: none), e.g. the 4 corner stamps of
        ``psf_corners``; not combined with ``per_realization``.
    optional : bool
        The plane may be absent (``None`` in memory, nothing stored): cells built without
        it, and files of a format version before it.
    config_flag : str or None
        For an optional plane, the boolean field of
        :class:`~cellcoadd.model.build_config.BuildConfig` that asks a build for it: a
        patch's cells hold the plane exactly when its configuration says so.
    per_input : tuple of int
        One layer of this shape per *used* input (in the order of the cell's used input
        records): shape ``(n_used, *per_input)``; an empty cell has none. Only with
        ``stamp`` (not on the cell grid).
    """

    name: str
    dtype: np.dtype
    per_realization: bool
    stamp: bool
    compression: Compression
    unit: UnitKind
    doc: str
    layers: int = 0
    optional: bool = False
    config_flag: str | None = None
    per_input: tuple[int, ...] = ()

    @property
    def stored_dtype(self) -> np.dtype:
        """:attr:`dtype` in little-endian byte order (as HDF5 files store it)."""
        return self.dtype.newbyteorder("<")

    @property
    def on_cell_grid(self) -> bool:
        """Whether the plane covers the cell's pixels (not a stamp): it can be cut to the
        inner box and stitched over a patch."""
        return not self.stamp

    def shape(
        self, outer_shape: tuple[int, int], n_noise: int, psf_size: int, n_inputs: int = 0
    ) -> tuple[int, ...]:
        """Array shape of the plane for a cell whose outer box has ``outer_shape`` (ny, nx),
        with ``n_noise`` realizations, ``psf_size``-pixel PSF stamps and ``n_inputs`` used
        inputs (:attr:`per_input`)."""
        if self.per_input:
            return (n_inputs, *self.per_input)
        base = (psf_size, psf_size) if self.stamp else tuple(outer_shape)
        if self.layers:
            return (self.layers, *base)
        return (n_noise, *base) if self.per_realization else base


#: The planes of a cell, in storage order (FITS HDUs, HDF5 datasets, cell-index columns).
PLANES: tuple[PlaneSpec, ...] = (
    PlaneSpec(
        "image",
        np.dtype(np.float32),
        per_realization=False,
        stamp=False,
        compression="float_bits",
        unit="flux",
        doc="coadded surface brightness per coadd pixel",
    ),
    PlaneSpec(
        "mask",
        np.dtype(np.int32),
        per_realization=False,
        stamp=False,
        compression="integer",
        unit="mask_bits",
        doc="bit mask, bits named by the patch's MaskBits",
    ),
    PlaneSpec(
        "variance",
        np.dtype(np.float32),
        per_realization=False,
        stamp=False,
        compression="float_bits",
        unit="flux_squared",
        doc="per-pixel variance of the image",
    ),
    PlaneSpec(
        "mfrac",
        np.dtype(np.float32),
        per_realization=False,
        stamp=False,
        compression="float_bits",
        unit="fraction",
        doc="fraction of the coadd weight from masked input pixels",
    ),
    PlaneSpec(
        "noise",
        np.dtype(np.float32),
        per_realization=True,
        stamp=False,
        compression="float_bits",
        unit="flux",
        doc="noise realizations coadded exactly like the image",
    ),
    PlaneSpec(
        "psf",
        np.dtype(np.float64),
        per_realization=False,
        stamp=True,
        compression="none",
        unit="normalised",
        doc="coadd PSF at the cell centre, pixel response included, summing to 1",
    ),
    PlaneSpec(
        "psf_corners",
        np.dtype(np.float64),
        per_realization=False,
        stamp=True,
        compression="none",
        unit="normalised",
        doc="coadd PSF at the 4 corner pixels of the inner box, each summing to 1 (1.4)",
        layers=4,
        optional=True,
        config_flag="psf_corners",
    ),
    PlaneSpec(
        "psf_phase",
        np.dtype(np.float32),
        per_realization=False,
        stamp=True,
        compression="none",
        unit="normalised",
        doc="each used input's effective PSF at the cell centre, oversampled (1.5)",
        optional=True,
        config_flag="psf_phase",
        per_input=(PHASE_SIDE, PHASE_SIDE),
    ),
    PlaneSpec(
        "psf_maps",
        np.dtype(np.float64),
        per_realization=False,
        stamp=True,
        compression="none",
        unit="normalised",
        doc="each used input's phase, affine map, area ratio and weight at the centre (1.5)",
        optional=True,
        config_flag="psf_phase",
        per_input=(len(MAP_FIELDS),),
    ),
)

#: Order of the stamps of ``psf_corners``: the inner box's corner pixels as (x, y) picks of
#: its first and last column and row, ``(x_start, y_start)``, ``(x_stop - 1, y_start)``,
#: ``(x_start, y_stop - 1)``, ``(x_stop - 1, y_stop - 1)``.
CORNER_ORDER: tuple[tuple[int, int], ...] = ((0, 0), (1, 0), (0, 1), (1, 1))


def plane_names() -> tuple[str, ...]:
    """Names of :data:`PLANES`, in storage order."""
    return tuple(spec.name for spec in PLANES)


def grid_plane_names() -> tuple[str, ...]:
    """Names of the planes on the cell grid (:attr:`PlaneSpec.on_cell_grid`): those cut to
    the inner box and stitched."""
    return tuple(spec.name for spec in PLANES if spec.on_cell_grid)


def cell_objects() -> tuple[str, ...]:
    """What a stored cell holds: its planes, then its inputs table."""
    return (*plane_names(), INPUTS)


def required_plane_names() -> tuple[str, ...]:
    """Names of the planes every cell has (not :attr:`PlaneSpec.optional`)."""
    return tuple(spec.name for spec in PLANES if not spec.optional)


def optional_plane_flags() -> dict[str, str]:
    """The :class:`~cellcoadd.model.build_config.BuildConfig` field that asks for each
    optional plane, by plane name: a configuration with all of them true builds every
    optional plane."""
    return {spec.name: spec.config_flag for spec in PLANES if spec.config_flag is not None}


def plane(name: str) -> PlaneSpec:
    """The description of plane ``name`` (KeyError if there is none)."""
    return {spec.name: spec for spec in PLANES}[name]


__all__ = [
    "CORNER_ORDER",
    "INPUTS",
    "PLANES",
    "Compression",
    "PlaneSpec",
    "UnitKind",
    "cell_objects",
    "grid_plane_names",
    "optional_plane_flags",
    "plane",
    "plane_names",
    "required_plane_names",
]
