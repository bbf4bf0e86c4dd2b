"""Reading and writing patch coadds: one API for the FITS and HDF5 layouts.

The layout follows the file name: ``.fits`` and ``.fits.fz`` (fitsio), ``.h5`` and
``.hdf5`` (h5py). Writes are atomic (:func:`cellcoadd.io._files.atomic.atomic_write`): the file is
written to a hidden temporary file in the target directory
(``.<name>.tmp-<host>-<pid>-<random>``), flushed to disk and renamed over the target, so
readers see either the previous file or the complete new one. A process killed mid-write
leaves such a temporary file behind; the next write of the same target removes it (see
:mod:`cellcoadd.io._files.atomic`). A write that does not fit on the disk is refused before it
starts, and one that fills the disk midway raises ``OSError(ENOSPC)`` naming the target and leaves
no file behind (except that HDF5 2.0 may crash the process instead; see
``docs/reliability.md``).

Files are reproducible: the same patch gives byte-identical files (CFITSIO's time-stamped
checksum comments are replaced by fixed ones; HDF5 objects carry no timestamps).

Every read verifies checksums by default and raises
:class:`~cellcoadd.errors.CellCoaddFormatError` for anything that is not an intact
cellcoadd file of a supported major version.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Literal

import numpy as np

from cellcoadd.errors import (
    CellCoaddIncompatibleValuesError,
    CellCoaddTypeError,
    CellCoaddValueError,
    ConfigError,
)
from cellcoadd.io._files.atomic import atomic_write, exists_error
from cellcoadd.io._files.disk_space import check_free_space
from cellcoadd.io._files.path_gate import gate_read
from cellcoadd.io._files.read_checks import reading_errors
from cellcoadd.io._fits.cfitsio_messages import clear_cfitsio_messages
from cellcoadd.io._fits.checksums import stabilise_fits_checksums
from cellcoadd.io.coadd.coadd_file import CoaddFile
from cellcoadd.io.coadd.fits_format import (
    FitsCoaddFile,
    check_fits_path,
    write_fits,
    write_fits_cells,
)
from cellcoadd.io.coadd.hdf5_format import Hdf5CoaddFile, write_hdf5, write_hdf5_cells
from cellcoadd.io.foreign.cell_coadds_layout import (
    check_writable as check_cell_coadds_writable,
)
from cellcoadd.io.foreign.cell_coadds_layout import is_cell_coadds_file, write_cell_coadds
from cellcoadd.io.foreign.cell_coadds_reader import CellCoaddsFile
from cellcoadd.model import planes
from cellcoadd.model.cell_coadd import CellCoadd
from cellcoadd.model.patch_coadd import PatchCoadd, PatchMetadata, check_patch_cell

Compression = Literal["none", "lossless"]
FileFormat = Literal["fits", "hdf5"]
#: Layouts chosen explicitly (``write(..., layout=...)``); None follows the file name.
Layout = Literal["cell_coadds"]

#: File name endings -> layout, longest first so ``.fits.fz`` wins over ``.fz``.
SUPPORTED_EXTENSIONS: dict[str, FileFormat] = {
    ".fits.fz": "fits",
    ".fits": "fits",
    ".hdf5": "hdf5",
    ".h5": "hdf5",
}

_WRITERS: dict[FileFormat, Callable[..., None]] = {"fits": write_fits, "hdf5": write_hdf5}
_READERS: dict[FileFormat, type[FitsCoaddFile] | type[Hdf5CoaddFile]] = {
    "fits": FitsCoaddFile,
    "hdf5": Hdf5CoaddFile,
}


def file_format(path: str | os.PathLike[str]) -> FileFormat:
    """Layout implied by the name of ``path`` (ValueError naming the supported endings)."""
    name = os.fspath(path).lower()
    for ending, layout in SUPPORTED_EXTENSIONS.items():
        if name.endswith(ending):
            return layout
    raise CellCoaddValueError(
        f"{os.fspath(path)}: unsupported file name; use one of {', '.join(SUPPORTED_EXTENSIONS)}",
        path=path,
        allowed=tuple(SUPPORTED_EXTENSIONS),
    )


def _use_compression(path: str, compression: str | None) -> bool:
    tile_compressed_name = path.lower().endswith(".fits.fz")
    if compression is None:
        return tile_compressed_name
    if compression not in ("none", "lossless"):
        raise CellCoaddValueError(
            f"compression must be None, 'none' or 'lossless' (pixels are never quantised), "
            f"got {compression!r}",
            value=compression,
            allowed=(None, "none", "lossless"),
        )
    if compression == "none" and tile_compressed_name:
        raise CellCoaddIncompatibleValuesError(
            f"{path}: .fits.fz files are tile compressed; use a .fits name instead",
            path=path,
            values={"compression": compression},
        )
    return compression == "lossless"


def write(
    patch_coadd: PatchCoadd,
    path: str | os.PathLike[str],
    *,
    compression: Compression | None = None,
    overwrite: bool = False,
    layout: Layout | None = None,
) -> Path:
    """Write a patch coadd atomically.

    Parameters
    ----------
    patch_coadd : PatchCoadd
        What to write.
    path : path-like
        Target; its ending selects the layout (see :data:`SUPPORTED_EXTENSIONS`).
    compression : {None, "none", "lossless"}
        ``"lossless"``: tile compression (FITS) or shuffle + gzip (HDF5), bit-exact.
        ``None``: lossless for ``.fits.fz`` names, uncompressed otherwise.
    overwrite : bool
        Replace an existing file (FileExistsError otherwise).
    layout : {None, "cell_coadds"}
        ``"cell_coadds"``: the LSST pipelines' ``lsst.cell_coadds`` FITS layout (a ``.fits``
        name, no compression; see ``docs/format.md``). None: our layout, by file name.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    FileExistsError
        ``path`` exists and ``overwrite`` is false.
    OSError
        ``errno.ENOSPC`` when the file does not fit on the disk (checked before writing,
        and detected if the disk fills up during the write); nothing is left behind and a
        previous file at ``path`` is unchanged.
    """
    if not isinstance(patch_coadd, PatchCoadd):
        raise CellCoaddTypeError(
            f"expected a PatchCoadd, got {type(patch_coadd).__name__}", allowed=PatchCoadd
        )
    target = Path(os.fspath(path))
    file_kind = file_format(target)
    compress = _use_compression(str(target), compression)
    writer = _WRITERS[file_kind]
    if layout is not None:
        writer = _foreign_writer(target, file_kind, layout, compress)
        check_cell_coadds_writable(patch_coadd, str(target))

    def prepare(temporary: Path) -> None:
        if file_kind == "fits":
            check_fits_path(str(temporary))
        check_free_space(target, _estimated_size(patch_coadd))

    def write_file(temporary: Path) -> None:
        writer(patch_coadd, str(temporary), compress=compress)
        if layout is not None:  # our own writers leave complete checksums
            stabilise_fits_checksums(temporary)

    return atomic_write(
        target,
        write_file,
        overwrite=overwrite,
        prepare=prepare,
        on_failure=clear_cfitsio_messages if file_kind == "fits" else None,
    )


def write_cells(
    metadata: PatchMetadata,
    cells: Iterable[CellCoadd],
    path: str | os.PathLike[str],
    *,
    compression: Compression | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a patch coadd given as its metadata and its cells, taking the cells as they come.

    The file is byte for byte the one :func:`write` makes of
    ``PatchCoadd(metadata, cells)``, but each cell is written and let go before the next
    is taken (a few are held at once), so a patch is written while it is built (e.g.
    :func:`cellcoadd.builder.stream_patch`) without being held whole. Options, atomicity
    and errors are those of :func:`write` (our own layouts only).

    Parameters
    ----------
    metadata : PatchMetadata
        The patch's metadata.
    cells : iterable of CellCoadd
        Every cell of the patch (:attr:`PatchMetadata.all_cell_indices`), in sorted
        ``(cx, cy)`` order, each as :class:`~cellcoadd.model.patch_coadd.PatchCoadd` checks
        its cells and with the geometry of the sky map (boxes and WCS).

    Raises
    ------
    InvalidCoaddError
        A cell is invalid, out of order, missing or extra; nothing is left at ``path``.
    """
    target = Path(os.fspath(path))
    file_kind = file_format(target)
    compress = _use_compression(str(target), compression)
    geometry = metadata.geometry
    indices = sorted(metadata.all_cell_indices)
    allowed = set(indices)
    present = metadata.cell_plane_names  # as built: every cell holds these planes

    def checked() -> Iterator[CellCoadd]:
        for cell in cells:
            check_patch_cell(metadata, cell.index, cell, allowed)
            yield cell
            del cell  # written: not held here while the next one comes

    def prepare(temporary: Path) -> None:
        if file_kind == "fits":
            check_fits_path(str(temporary))
        check_free_space(target, _estimated_cells_size(metadata, len(indices)))

    def write_file(temporary: Path) -> None:
        if file_kind == "fits":
            identities = [geometry.tract.cell(*index) for index in indices]
            write_fits_cells(
                metadata, identities, checked(), str(temporary), compress=compress,
                present=present,
            )  # fmt: skip
        else:
            write_hdf5_cells(
                metadata, indices, checked(), str(temporary), compress=compress, present=present
            )

    return atomic_write(
        target,
        write_file,
        overwrite=overwrite,
        prepare=prepare,
        on_failure=clear_cfitsio_messages if file_kind == "fits" else None,
    )


def _foreign_writer(
    target: Path, file_kind: FileFormat, layout: str, compress: bool
) -> Callable[..., None]:
    """The writer of an explicitly chosen ``layout`` (ValueError if the name does not fit)."""
    if layout != "cell_coadds":
        raise CellCoaddValueError(
            f"unknown layout {layout!r}; use None or 'cell_coadds'",
            value=layout,
            allowed=(None, "cell_coadds"),
        )
    if file_kind != "fits" or str(target).lower().endswith(".fz"):
        raise CellCoaddIncompatibleValuesError(
            f"{target}: the cell_coadds layout needs a .fits file name",
            path=target,
            values={"layout": layout},
        )
    if compress:
        raise CellCoaddIncompatibleValuesError(
            f"{target}: the cell_coadds layout is not compressed",
            path=target,
            values={"layout": layout, "compress": compress},
        )
    return write_cell_coadds


def _estimated_size(patch_coadd: PatchCoadd) -> int:
    """Upper estimate (bytes) of the uncompressed file holding ``patch_coadd``.

    Pixel bytes plus generous per-plane allowances for FITS headers and padding (two
    2880-byte blocks each) or HDF5 object headers; compressed files are smaller.
    """
    per_plane = 2 * 2880 + 2880
    total = 8 * 2880 + len(patch_coadd.metadata.model_dump_json())
    for cell in patch_coadd.values():
        held = cell.plane_names
        total += sum(getattr(cell, name).nbytes for name in held)
        total += (len(held) + 1) * per_plane  # the planes and the inputs table
        total += 128 * len(cell.inputs) + 4096  # inputs table rows, identity JSON
    return total


def _estimated_cells_size(metadata: PatchMetadata, n_cells: int) -> int:
    """Upper estimate (bytes) of the uncompressed file of ``n_cells`` cells of ``metadata``
    (as :func:`_estimated_size`, with room for 64 input records per cell)."""
    per_plane = 2 * 2880 + 2880
    total = 8 * 2880 + len(metadata.model_dump_json())
    config = metadata.skymap_config
    side = config.cell_inner + 2 * config.cell_border
    pixels = sum(
        int(np.prod(spec.shape((side, side), metadata.n_noise, metadata.psf_size)))
        * spec.dtype.itemsize
        for spec in planes.PLANES
    )
    per_cell = pixels + len(planes.cell_objects()) * per_plane + 128 * 64 + 4096
    return total + n_cells * per_cell


def open(
    path: str | os.PathLike[str],
    *,
    verify: bool = True,
    legacy_zero_point: float | None = None,
    skymap: str | None = None,
) -> CoaddFile:
    """Open a patch file lazily: ``.metadata``, ``.cell_indices``, ``.read_cell(index)``,
    ``.read_inputs()``; use as a context manager or call ``.close()``.

    Parameters
    ----------
    verify : bool
        Verify checksums of what is read (FITS CHECKSUM/DATASUM, HDF5 metadata SHA-256;
        HDF5 Fletcher-32 checksums are always verified by the library).
    legacy_zero_point : float, optional
        For ``lsst.cell_coadds`` files in ``legacy`` units (counts) that do not record
        their zero point: the AB zero point to read them at (they are refused without
        it). Refused for other files.
    skymap : str, optional
        For ``lsst.cell_coadds`` files: the name of the sky map their cells are on
        (``lsst_cells_v1``, ``lsst_cells_v2``, ``DC2_cells_v1``...; see
        :meth:`~cellcoadd.geometry.SkyMap.named`), for a file whose ``SKYMAP`` keyword
        names none cellcoadd knows; checked against the file's grid and WCS. Unknown
        names are refused with the list of known ones; refused for other files.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    CellCoaddFormatError
        ``path`` is not an intact cellcoadd patch file of a supported major version.

    A ``.fits`` file in the LSST ``lsst.cell_coadds`` layout is recognised by its headers
    and opened as such (``format_name == "cell_coadds"``).
    """
    name = os.fspath(path)
    layout = file_format(name)
    gate_read(name, what="coadd file", fits=layout == "fits")
    with _fresh_cfitsio_messages(layout):
        if layout == "fits" and is_cell_coadds_file(name):  # the LSST layout, by its headers
            return CellCoaddsFile(
                name, verify=verify, legacy_zero_point=legacy_zero_point, skymap=skymap
            )
        if legacy_zero_point is not None:
            raise ConfigError(f"{name}: legacy_zero_point applies to lsst.cell_coadds files only")
        if skymap is not None:
            raise ConfigError(
                f"{name}: skymap applies to lsst.cell_coadds files only (cellcoadd's own "
                "files store their sky map)"
            )
        return _READERS[layout](name, verify=verify)


@contextmanager
def _fresh_cfitsio_messages(layout: FileFormat) -> Iterator[None]:
    """Start and leave FITS reads with an empty CFITSIO message stack.

    A damaged file leaves undecodable messages there even when the failure is detected
    by our own checks; the next fitsio error anywhere in the process (another reader's,
    or the caller's own) would then fail to decode them.
    """
    if layout != "fits":
        yield
        return
    clear_cfitsio_messages()
    try:
        yield
    finally:
        clear_cfitsio_messages()


def read(
    path: str | os.PathLike[str],
    *,
    verify: bool = True,
    legacy_zero_point: float | None = None,
    skymap: str | None = None,
) -> PatchCoadd:
    """Read a whole patch coadd (see :func:`open` for the options and errors)."""
    with (
        _fresh_cfitsio_messages(file_format(path)),
        open(path, verify=verify, legacy_zero_point=legacy_zero_point, skymap=skymap) as coadd_file,
    ):
        cells = {index: coadd_file.read_cell(index) for index in coadd_file.cell_indices}
        with reading_errors(coadd_file.path, "assembling the patch"):
            return PatchCoadd(coadd_file.metadata, cells)


def read_cell(
    path: str | os.PathLike[str], index: tuple[int, int], *, verify: bool = True
) -> CellCoadd:
    """Read one cell, touching only that cell's data (KeyError if the file lacks it)."""
    with _fresh_cfitsio_messages(file_format(path)), open(path, verify=verify) as coadd_file:
        return coadd_file.read_cell(index)


def convert(
    source: str | os.PathLike[str],
    destination: str | os.PathLike[str],
    *,
    compression: Compression | None = None,
    overwrite: bool = False,
    layout: Layout | None = None,
    legacy_zero_point: float | None = None,
    skymap: str | None = None,
) -> Path:
    """Copy a patch file into another layout or compression, losslessly.

    ``layout="cell_coadds"`` writes the LSST ``lsst.cell_coadds`` layout (see :func:`write`);
    such a source is recognised by its headers (``legacy_zero_point``, ``skymap``: see
    :func:`open`).
    """
    file_format(destination)  # fail on a bad name before reading anything
    if Path(os.fspath(destination)).exists() and not overwrite:
        raise exists_error(destination)
    return write(
        read(source, legacy_zero_point=legacy_zero_point, skymap=skymap),
        destination,
        compression=compression,
        overwrite=overwrite,
        layout=layout,
    )
