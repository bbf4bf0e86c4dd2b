"""``python -m cellcoadd`` runs the same command line as ``cellcoadd``."""

from cellcoadd.cli import main

if __name__ == "__main__":
    main()
