"""Our own patch-coadd formats.

The FITS and HDF5 layouts, their fast writers and their lazy per-cell readers.
"""
