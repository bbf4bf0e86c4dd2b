"""Imports point downward only (DESIGN.md layers); io and build never import each other."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cellcoadd"
LEVEL = {
    "_version": 0,
    "_lazy": 0,
    "errors": -1,  # the exception classes import nothing of cellcoadd: every layer may raise them
    "geometry": 0,
    "model": 1,
    "io": 2,
    "builder": 2,
    "sim": 3,
    "analysis": 4,
    "shear": 5,
    "plots": 6,
    "pipelines": 7,
    "cli": 8,
    "__main__": 9,
}


def _layer(module_path: Path) -> str:
    return module_path.relative_to(PACKAGE).parts[0].removesuffix(".py")


def _imported_layers(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "cellcoadd" and len(parts) > 1:
                yield parts[1], node.lineno


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


@pytest.mark.parametrize("path", MODULES, ids=[str(p.relative_to(PACKAGE)) for p in MODULES])
def test_imports_point_downward(path):
    own = _layer(path)
    for layer, line in _imported_layers(path):
        assert layer in LEVEL, f"{path}:{line}: unknown layer {layer}"
        if layer == own:
            continue
        assert LEVEL[layer] < LEVEL[own], f"{path}:{line}: {own} imports {layer} (upward)"


KERNELS = sorted((PACKAGE / "builder" / "kernels").glob("*.py"))
SHEAR = sorted((PACKAGE / "shear").glob("*.py"))


def _imported_modules(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, node.lineno
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno


@pytest.mark.parametrize("path", KERNELS, ids=[p.name for p in KERNELS])
def test_kernels_do_no_io(path):
    """Numerical kernels: numpy, numba, llvmlite and each other; no files, no astropy."""
    allowed = ("numpy", "numba", "llvmlite", "math", "collections", "__future__")
    for module, line in _imported_modules(path):
        top = module.split(".")[0]
        inside = module.startswith("cellcoadd.builder.kernels") or module in (
            "cellcoadd.geometry.box",
        )
        assert top in allowed or inside, f"{path}:{line}: a kernel imports {module}"


@pytest.mark.parametrize("path", SHEAR, ids=[p.name for p in SHEAR])
def test_shear_sees_only_model_and_geometry(path):
    for layer, line in _imported_layers(path):
        assert layer in ("errors", "geometry", "model", "shear"), f"{path}:{line}: {layer}"


def test_no_private_names_cross_modules():
    """A module imports no ``_private`` name of another module."""
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cellcoadd"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                private = [n for n in private if not n.startswith("__")]
                assert not private, f"{path}:{node.lineno}: imports {private} from {node.module}"


SIM = sorted((PACKAGE / "sim").glob("*.py"))


@pytest.mark.parametrize("path", SIM, ids=[p.name for p in SIM])
def test_sim_does_no_file_io(path):
    """Simulations return in-memory results; writing them is the callers' job."""
    for module, line in _imported_modules(path):
        assert module != "cellcoadd.io" and not module.startswith("cellcoadd.io."), (
            f"{path}:{line}: sim imports {module}"
        )
