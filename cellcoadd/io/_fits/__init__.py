"""FITS plumbing shared by every FITS reader and writer (private).

CFITSIO paths and messages, checksums, raw header parsing, direct HDU writes and exact WCS
cards.
"""
