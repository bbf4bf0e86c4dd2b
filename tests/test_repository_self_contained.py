"""The tests and benchmarks read nothing outside the repository.

``make test`` must pass in a fresh clone on its own. The real DECam CCD the survey tests
use (GalSim's test data, BSD-3-Clause) is committed in ``tests/data/des`` and named
through ``conftest.DES_DATA``; no file under ``tests/`` or ``benchmarks/`` may name the
development folder's data directory beside the clone or climb above the repository root
from its own location, which would make a test fail or skip wherever that folder is
missing.
"""

from __future__ import annotations

import re
from pathlib import Path

from conftest import DES_DATA, DES_HEADER, DES_PSF

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("tests", "benchmarks")
#: the data folder beside the clone (either separator), or its two names joined by ``/``
#: or ``,`` in code.
SHARED_DATA = re.compile(r"""shared[/\\]data|["']shared["']\s*[/,]\s*["']data["']""")
PARENTS = re.compile(r"parents\[(\d+)\]")


def _text_files() -> list[Path]:
    files = []
    for top in SCANNED:
        for path in sorted((ROOT / top).rglob("*")):
            if not path.is_file() or "__pycache__" in path.parts:
                continue
            if path.resolve() == Path(__file__).resolve():
                continue
            try:
                path.read_text(encoding="utf-8")
            except UnicodeDecodeError:  # FITS headers, PSFEx models: data, not references
                continue
            files.append(path)
    return files


def test_no_file_names_a_shared_data_folder():
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _text_files()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if SHARED_DATA.search(line)
    ]
    assert not found, "test data outside the repository (use conftest.DES_DATA):\n" + "\n".join(
        found
    )


def test_no_file_climbs_above_the_repository_root():
    """``Path(__file__).resolve().parents[k]`` with ``k`` past the root leaves the clone."""
    found = []
    for path in _text_files():
        depth = len(path.relative_to(ROOT).parts)  # parents[depth - 1] is the root
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if any(int(k) >= depth for k in PARENTS.findall(line)):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, "a path above the repository root:\n" + "\n".join(found)


def test_the_des_files_are_in_the_repository_with_their_licence():
    assert DES_DATA.resolve().is_relative_to(ROOT)
    for path in (DES_HEADER, DES_PSF, DES_DATA / "LICENSE-GalSim", DES_DATA / "README.md"):
        assert path.is_file() and path.stat().st_size > 0, path
    assert "GalSim" in (DES_DATA / "LICENSE-GalSim").read_text()


def test_the_guard_sees_what_it_guards_against():
    """The patterns match the forms that were in use, so the checks above can fail."""
    folder = "sh" + "ared"  # spelled apart: this file names no such folder itself
    for line in (
        f'DES_DATA = Path(__file__).resolve().parents[2] / "{folder}" / "data" / "des"',
        f'DES_PSF = Path("/work/{folder}/data/des/DECam_00154912_12_psfcat.psf")',
        f"real DECam CCD header (``../{folder}/data/des``)",
        f'os.path.join("..", "{folder}", "data")',
    ):
        assert SHARED_DATA.search(line), line
    assert not SHARED_DATA.search("a shared mapping; data in tests/data/des")
    assert PARENTS.findall("Path(__file__).resolve().parents[2]") == ["2"]
