"""Imports point downward only (DESIGN.md layers); io and build never import each other."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cellcoadd"
LEVEL = {
    "_version": 0,
    "geometry": 0,
    "model": 1,
    "io": 2,
    "build": 2,
    "sim": 3,
    "analysis": 4,
    "shear": 5,
    "plots": 6,
    "demo": 7,
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
