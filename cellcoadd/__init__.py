"""cellcoadd: cell-based coadds for weak-lensing shear measurement."""

from cellcoadd._version import __version__

__all__ = ["__version__"]
