"""Lazy re-exports: a package's public names imported from their home modules on first use,
so that importing the package stays cheap (no numba, GalSim or matplotlib until needed)."""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module
from typing import Any


def lazy_exports(
    package: str,
    namespace: dict[str, Any],
    exports: dict[str, str],
    submodules: tuple[str, ...] = (),
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package`` for ``exports``.

    Parameters
    ----------
    package : str
        The package's name, for error messages.
    namespace : dict
        The package's ``globals()``: a resolved name is stored there, so later look-ups
        do not come back here.
    exports : dict
        Public name -> module that defines it.
    submodules : tuple of str
        Sub-packages reachable as attributes (``package.io``), imported on first use.
    """

    def getattr_(name: str) -> Any:
        module = exports.get(name)
        if module is None and name in submodules:
            value = import_module(f"{package}.{name}")  # the import sets the attribute too
            namespace[name] = value
            return value
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(module), name)
        namespace[name] = value
        return value

    def dir_() -> list[str]:
        return sorted(set(namespace) | set(exports) | set(submodules))

    return getattr_, dir_
