"""Layouts of other codes: Rubin's ``cell_coadds`` FITS files and lsst-images objects."""
