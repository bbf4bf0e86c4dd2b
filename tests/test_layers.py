"""Imports point downward only, in the layers listed by ``docs/architecture.md``.

The ``layers`` blocks of that page are the one list of the layers: each names a package,
then its entries from top to bottom, one level per line (``a | b``: one level, never
importing each other; ``a + b``: one unit; ``*``: every plain module not named; ``#``
starts a comment). These tests fail if a module imports upward, if a package or module
exists that the blocks do not list, or if the blocks name something that does not exist.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "cellcoadd"
ARCHITECTURE = ROOT / "docs" / "architecture.md"

_BLOCK = re.compile(r"^```layers[ \t]+(\S+)[ \t]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
_NAME = re.compile(r"^(\*|[A-Za-z_][A-Za-z0-9_]*)$")


@dataclass(frozen=True)
class Block:
    """The order of the entries (sub-packages and modules) of one package."""

    package: tuple[str, ...]  # dotted path below the top package: () for cellcoadd itself
    level: dict[str, int]  # entry -> level, higher is upper
    unit: dict[str, int]  # entry -> unit: entries of one unit may import each other

    def entry(self, name: str) -> str | None:
        """The entry holding ``name`` (``*`` for an unnamed plain module), None if none."""
        if name in self.level:
            return name
        return "*" if "*" in self.level else None


def parse_layers(text: str, top: str = "cellcoadd") -> dict[tuple[str, ...], Block]:
    """The ``layers`` blocks of a Markdown ``text``, by package (parts below ``top``)."""
    blocks: dict[tuple[str, ...], Block] = {}
    for match in _BLOCK.finditer(text):
        dotted, body = match.group(1), match.group(2)
        parts = tuple(dotted.split("."))
        assert parts[0] == top, f"layers block of {dotted}: not inside {top}"
        lines = [line.split("#", 1)[0].strip() for line in body.splitlines()]
        lines = [line for line in lines if line]
        level: dict[str, int] = {}
        unit: dict[str, int] = {}
        for height, line in enumerate(reversed(lines)):
            for group in line.split("|"):
                number = len(set(unit.values()))
                for name in (n.strip() for n in group.split("+")):
                    assert _NAME.match(name), f"layers block of {dotted}: bad entry {name!r}"
                    assert name not in level, f"layers block of {dotted}: {name} twice"
                    level[name], unit[name] = height, number
        assert parts[1:] not in blocks, f"two layers blocks of {dotted}"
        blocks[parts[1:]] = Block(parts[1:], level, unit)
    assert () in blocks, f"no layers block of {top}"
    return blocks


def module_parts(path: Path, package: Path) -> tuple[str, ...]:
    """``io/coadd/fits_format.py`` -> ``("io", "coadd", "fits_format")``; a package's
    ``__init__.py`` keeps its ``__init__``."""
    return path.relative_to(package).with_suffix("").parts


def imported_modules(path: Path, package: Path) -> list[tuple[tuple[str, ...], int]]:
    """The modules of ``package`` that ``path`` imports (parts below it), with line numbers.

    ``from cellcoadd.x import y`` counts as importing ``x.y`` when ``y`` is a module or
    package, else ``x`` itself (a package: its ``__init__``); relative imports are resolved.
    """
    top = package.name
    here = module_parts(path, package)
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name.split(".") for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's own package upward
                base = [top, *here[: len(here) - node.level]]
                module = [*base, *(node.module or "").split(".")] if node.module else base
            else:
                module = (node.module or "").split(".")
            names = []
            for alias in node.names:
                sub = [*module, alias.name]
                is_module = (package.parent.joinpath(*sub).with_suffix(".py")).is_file() or (
                    package.parent.joinpath(*sub, "__init__.py").is_file()
                )
                names.append(sub if is_module else module)
        else:
            continue
        for name in names:
            if name[0] == top:
                found.append((tuple(name[1:]), node.lineno))
    return found


def _target(parts: tuple[str, ...], package: Path) -> tuple[str, ...]:
    """An imported name as module parts: a package is its ``__init__``."""
    if package.joinpath(*parts, "__init__.py").is_file():
        return (*parts, "__init__")
    return parts


def import_violation(
    source: tuple[str, ...], target: tuple[str, ...], blocks: dict[tuple[str, ...], Block]
) -> str | None:
    """Why importing ``target`` from ``source`` (module parts) breaks the layers, if it does.

    Both are followed down the blocks while they share an entry; at the first package where
    they part, the target's entry must be lower than the source's (or of its unit). A
    package's ``__init__`` may import anything inside the package; any other module that
    imports its own package's ``__init__`` imports upward.
    """
    package: tuple[str, ...] = ()
    while (block := blocks.get(package)) is not None:
        depth = len(package)
        src, dst = source[depth], target[depth]
        if src == "__init__":
            return None  # re-exports from inside its own package
        if dst == "__init__":
            where = ".".join(("cellcoadd", *package))
            return f"imports its own package {where} (its __init__ sits above every entry)"
        if src == dst:
            if depth + 1 == len(source) or depth + 1 == len(target):
                return None  # the module itself
            package = (*package, src)  # one sub-package: its own block decides
            continue
        src_entry, dst_entry = block.entry(src), block.entry(dst)
        if src_entry is None or dst_entry is None:
            return None  # reported by the listing test
        if src_entry == dst_entry == "*":
            return None  # two unnamed modules: no order among them
        if src_entry != dst_entry and block.unit[src_entry] == block.unit[dst_entry]:
            return None  # one unit
        if block.level[dst_entry] < block.level[src_entry]:
            return None
        where = ".".join(("cellcoadd", *package))
        return f"in {where}, {src_entry} imports {dst_entry} (not below it)"
    return None  # inside an entry without a block of its own: anything goes


def unlisted(package: Path, blocks: dict[tuple[str, ...], Block]) -> list[str]:
    """What exists in ``package`` that the blocks do not list, and what they list that does
    not exist."""
    problems = []
    for parts, block in blocks.items():
        directory = package.joinpath(*parts)
        if not (directory / "__init__.py").is_file():
            problems.append(f"{directory}: listed, but no such package")
            continue
        modules = {p.stem for p in directory.glob("*.py") if p.name != "__init__.py"}
        packages = {p.parent.name for p in directory.glob("*/__init__.py")}
        for name in sorted(set(block.level) - {"*"} - modules - packages):
            problems.append(f"{directory / name}: listed, but no such module or package")
        for name in sorted(packages - set(block.level)):
            problems.append(f"{directory / name}/: a package the layers do not list")
        if "*" not in block.level:
            for name in sorted(modules - set(block.level)):
                problems.append(f"{directory / name}.py: a module the layers do not list")
    for init in sorted(package.rglob("__init__.py")):
        parts = module_parts(init, package)[:-1]
        if parts and parts[:-1] not in blocks:
            problems.append(f"{init.parent}/: a package inside one the layers do not order")
    return problems


def violations(package: Path, blocks: dict[tuple[str, ...], Block], path: Path) -> list[str]:
    source = module_parts(path, package)
    found = []
    for target, line in imported_modules(path, package):
        problem = import_violation(source, _target(target, package), blocks)
        if problem:
            found.append(f"{path}:{line}: {problem}")
    return found


BLOCKS = parse_layers(ARCHITECTURE.read_text())
MODULES = sorted(PACKAGE.rglob("*.py"))


def test_architecture_lists_every_package_and_module():
    assert unlisted(PACKAGE, BLOCKS) == []
    top = BLOCKS[()]
    assert {"geometry", "model", "io", "builder", "cli"} <= set(top.level)
    assert top.level["io"] == top.level["builder"] and top.unit["io"] != top.unit["builder"]


@pytest.mark.parametrize("path", MODULES, ids=[str(p.relative_to(PACKAGE)) for p in MODULES])
def test_imports_point_downward(path):
    assert violations(PACKAGE, BLOCKS, path) == []


_PATH = re.compile(r"`([\w./]+(?:\.py|/))`")
_PATH_AND_NAME = re.compile(r"`([\w./]+\.py)`,\s+`(\w+)`")


def _defined_names(path: Path) -> set[str]:
    """Names a module defines or imports at its top level, and its classes' methods."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def test_architecture_names_files_and_functions_that_exist():
    """Every file or folder the page names exists (paths from the repository or from
    ``cellcoadd/``), and every "`file.py`, `name`" names something that file defines."""
    text = ARCHITECTURE.read_text()
    missing = [
        token
        for token in sorted(set(_PATH.findall(text)))
        if not ((ROOT / token).exists() or (PACKAGE / token).exists())
    ]
    assert missing == []
    pairs = _PATH_AND_NAME.findall(text)
    assert len(pairs) > 10  # the data path names its functions this way
    for token, name in pairs:
        path = PACKAGE / token if (PACKAGE / token).exists() else ROOT / token
        assert name in _defined_names(path), f"docs/architecture.md: {token} has no {name}"


def _fake_package(tmp_path: Path, files: dict[str, str]) -> Path:
    package = tmp_path / "cellcoadd"
    for name, text in files.items():
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    return package


FAKE_DOC = """
```layers cellcoadd
cli
io | builder   # side by side
model
```

```layers cellcoadd.io
api
coadd
_fits + _files
```
"""


def test_checker_finds_upward_and_sideways_imports(tmp_path):
    """The checks themselves: each kind of break in a small package is reported."""
    files = {
        "__init__.py": "from cellcoadd.cli import main\n",  # the facade may
        "cli/__init__.py": "",
        "cli/main.py": "from cellcoadd.io.api import write\nimport cellcoadd.model.m\n",
        "model/__init__.py": "",
        "model/m.py": "from cellcoadd.builder import b\n",  # upward
        "builder/__init__.py": "from cellcoadd.builder.b import f\n",
        "builder/b.py": "from cellcoadd.io.coadd import fits\n",  # sideways
        "io/__init__.py": "from cellcoadd.io.api import write\n",
        "io/api.py": "from cellcoadd.io.coadd.fits import w\nfrom . import _fits\n",
        "io/coadd/__init__.py": "",
        "io/coadd/fits.py": "from cellcoadd.io._fits.p import c\nfrom ..api import write\n",
        "io/_fits/__init__.py": "",
        "io/_fits/p.py": "from cellcoadd.io._files.a import x\n",  # one unit
        "io/_files/__init__.py": "",
        "io/_files/a.py": "from cellcoadd.io._fits.p import c\nfrom cellcoadd.io import api\n",
    }
    package = _fake_package(tmp_path, files)
    blocks = parse_layers(FAKE_DOC)
    assert unlisted(package, blocks) == []
    found = {
        str(path.relative_to(package)): violations(package, blocks, path)
        for path in sorted(package.rglob("*.py"))
    }
    broken = {name: problems for name, problems in found.items() if problems}
    assert set(broken) == {"model/m.py", "builder/b.py", "io/coadd/fits.py", "io/_files/a.py"}
    assert "model imports builder" in broken["model/m.py"][0]
    assert "builder imports io" in broken["builder/b.py"][0]
    assert "coadd imports api" in broken["io/coadd/fits.py"][0]  # a relative import
    assert "_files imports api" in broken["io/_files/a.py"][0]
    assert all(len(problems) == 1 for problems in broken.values())


def test_checker_finds_unlisted_and_stale_entries(tmp_path):
    files = {
        "__init__.py": "",
        "cli/__init__.py": "",
        "model/__init__.py": "",
        "model/deep/__init__.py": "",  # a sub-package of a package without a block
        "builder/__init__.py": "",
        "plots/__init__.py": "",  # not in the doc
        "stray.py": "",  # a module not in the doc
        "io/__init__.py": "",
        "io/api.py": "",
        "io/_fits/__init__.py": "",
        "io/_files/__init__.py": "",
        "io/extra/__init__.py": "",  # not in the io block; and io/coadd is missing
    }
    package = _fake_package(tmp_path, files)
    problems = "\n".join(unlisted(package, parse_layers(FAKE_DOC)))
    for expected in (
        "plots/: a package the layers do not list",
        "stray.py: a module the layers do not list",
        "extra/: a package the layers do not list",
        "coadd: listed, but no such module or package",
        "deep/: a package inside one the layers do not order",
    ):
        assert expected in problems
    assert problems.count("\n") == 4


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
    allowed = ("numpy", "numba", "llvmlite", "math", "collections", "dataclasses", "__future__")
    for module, line in _imported_modules(path):
        top = module.split(".")[0]
        inside = module.startswith("cellcoadd.builder.kernels") or module in (
            "cellcoadd.errors",  # argument checks raise the library's errors
            "cellcoadd.geometry.box",
        )
        assert top in allowed or inside, f"{path}:{line}: a kernel imports {module}"


def test_numba_only_in_kernels():
    """Every compiled function lives under builder/kernels/: no numba anywhere else."""
    kernels = PACKAGE / "builder" / "kernels"
    for path in PACKAGE.rglob("*.py"):
        if kernels in path.parents:
            continue
        for module, line in _imported_modules(path):
            assert module.split(".")[0] not in ("numba", "llvmlite"), (
                f"{path}:{line}: imports {module} outside builder/kernels"
            )


@pytest.mark.parametrize("path", SHEAR, ids=[str(p.relative_to(PACKAGE)) for p in SHEAR])
def test_shear_sees_only_model_and_geometry(path):
    for target, line in imported_modules(path, PACKAGE):
        layer = target[0] if target else "__init__"
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
