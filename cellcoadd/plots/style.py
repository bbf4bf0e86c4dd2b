"""The one look of cellcoadd's figures: fonts, sizes, colours, resolution.

Every plotting function builds its figure inside :func:`styled` (a ``matplotlib.rc_context``
that is undone on return, so the caller's settings are never changed) and writes it with
:func:`save`. Figures are :class:`matplotlib.figure.Figure` objects made without pyplot: no
global figure state, safe in scripts, tests and worker processes.

The colours have one meaning in every figure: :data:`INNER` outlines cell inner regions,
:data:`OUTER` cell outer regions, :data:`NO_DATA` marks pixels without data, :data:`PATCH`
fills the patch inner region.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, ParamSpec, TypeVar, cast

#: matplotlib settings of every figure (sizes in points, for a figure ~7-14 inches wide)
RC: dict[str, Any] = {
    "font.size": 10.0,
    "axes.titlesize": 11.0,
    "axes.labelsize": 10.0,
    "xtick.labelsize": 9.0,
    "ytick.labelsize": 9.0,
    "legend.fontsize": 9.0,
    "figure.titlesize": 12.0,
    "axes.titlepad": 6.0,
    "image.interpolation": "nearest",
    "image.origin": "lower",
    "savefig.facecolor": "white",
    "figure.facecolor": "white",
    "figure.constrained_layout.h_pad": 0.06,
    "figure.constrained_layout.w_pad": 0.06,
}

#: resolution of written PNGs, dots per inch
DPI = 110

#: cell inner regions
INNER = "tab:cyan"
#: cell outer regions
OUTER = "tab:red"
#: pixels without data (NaN in an image)
NO_DATA = "tab:orange"
#: the patch inner region
PATCH = "0.86"
#: line width of outlines, points
LINE = 0.9
#: colours of mask bits, in order of the bits present
BIT_COLOURS: tuple[str, ...] = tuple(f"C{i}" for i in range(10))

P = ParamSpec("P")
R = TypeVar("R")


@contextmanager
def rc() -> Iterator[None]:
    """``with rc():`` matplotlib settings :data:`RC` for the block, then the caller's."""
    import matplotlib

    with matplotlib.rc_context(cast(Any, RC)):  # matplotlib types its keys as literals
        yield


def styled(function: Callable[P, R]) -> Callable[P, R]:
    """Decorator: run a plotting function with :data:`RC` (fonts are fixed at creation)."""

    @functools.wraps(function)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with rc():
            return function(*args, **kwargs)

    return wrapper


def figure(width: float, height: float, *, compressed: bool = False) -> Any:
    """A new figure of ``width`` x ``height`` inches with constrained layout (no pyplot);
    ``compressed``: the variant that packs grids of fixed-aspect (image) panels."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="compressed" if compressed else "constrained")


def save(fig: Any, path: str | os.PathLike[str], dpi: int = DPI) -> str:
    """Write ``fig`` as a PNG (or the format its name ends with) at ``dpi``, atomically:
    a link at ``path`` is replaced, never written through; returns the path."""
    from cellcoadd.io._files.atomic import atomic_write

    kind = os.path.splitext(os.fspath(path))[1].lstrip(".").lower() or "png"

    def write(temporary: Any) -> None:
        fig.savefig(temporary, dpi=dpi, format=kind)  # the temporary name has no suffix

    atomic_write(path, write, overwrite=True)
    return os.fspath(path)
