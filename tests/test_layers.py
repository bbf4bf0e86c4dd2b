"""Imports point downward only (DESIGN.md layers); io and build never import each other."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cellcoadd"
LEVEL = {
    "_version": 0,
    "_lazy": 0,
    "errors": 0,
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
SHEAR = sorted((PACKAGE / "shear").rglob("*.py"))


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


@pytest.mark.parametrize("path", SHEAR, ids=[str(p.relative_to(PACKAGE)) for p in SHEAR])
def test_shear_sees_only_model_and_geometry(path):
    for layer, line in _imported_layers(path):
        assert layer in ("errors", "geometry", "model", "shear"), f"{path}:{line}: {layer}"


def test_no_private_names_cross_modules():
    """A module imports no ``_private`` name of another module (a package's ``__init__``
    may import its own private implementation modules: its public face over them)."""
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cellcoadd"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                private = [n for n in private if not n.startswith("__")]
                if path.name == "__init__.py" and node.module == _module_name(path):
                    private = [n for n in private if not (path.parent / f"{n}.py").is_file()]
                assert not private, f"{path}:{node.lineno}: imports {private} from {node.module}"


SIM = sorted((PACKAGE / "sim").glob("*.py"))


@pytest.mark.parametrize("path", SIM, ids=[p.name for p in SIM])
def test_sim_does_no_file_io(path):
    """Simulations return in-memory results; writing them is the callers' job."""
    for module, line in _imported_modules(path):
        assert module != "cellcoadd.io" and not module.startswith("cellcoadd.io."), (
            f"{path}:{line}: sim imports {module}"
        )


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_graph() -> dict[str, set[str]]:
    """Module -> the cellcoadd modules it imports, type-only imports included (``from
    package import module`` counts as importing the module)."""
    paths = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    target = f"{node.module}.{alias.name}"
                    edges.add(target if target in paths else node.module)
            elif isinstance(node, ast.Import):
                edges.update(alias.name for alias in node.names)
        graph[name] = {edge for edge in edges if edge in paths and edge != name}
    return graph


def test_no_import_cycles():
    """No module imports, even for type checking only, a module that imports it back."""
    graph = _module_graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    cycles = []

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                cycles.append(path[path.index(target) :] + [target])
            elif target not in state:
                visit(target, [*path, target])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("layer", ["model", "sim", "analysis", "shear", "pipelines"])
def test_modules_do_not_re_export(layer):
    """A module's ``__all__`` lists what it defines: names from another module are imported
    from their home (packages' ``__init__`` gather them; error classes may be re-exported
    where they are raised)."""
    for path in sorted((PACKAGE / layer).rglob("*.py")):
        if path.name == "__init__.py":
            continue
        tree = ast.parse(path.read_text())
        imported = {
            alias.asname or alias.name: node.module
            for node in tree.body
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cellcoadd.")
            for alias in node.names
        }
        exported = [
            element.value
            for node in tree.body
            if isinstance(node, ast.Assign)
            and any(getattr(target, "id", None) == "__all__" for target in node.targets)
            and isinstance(node.value, ast.List)
            for element in node.value.elts
            if isinstance(element, ast.Constant)
        ]
        again = [
            name
            for name in exported
            if imported.get(name, "cellcoadd.errors") != "cellcoadd.errors"
        ]
        assert not again, f"{path}: __all__ re-exports {again}"
