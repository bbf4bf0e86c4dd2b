"""Package version (kept in one place; read by metadata written to files)."""

__version__ = "0.1.0"
