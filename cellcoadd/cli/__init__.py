"""Command line interface (thin glue over the library)."""

from cellcoadd.cli.main import main

__all__ = ["main"]
