"""The documentation site builds without a warning, every public name has an entry in it, and the notebooks run.

The build is the one the docs describe (``python -m sphinx -W --keep-going -b html docs docs/_build/html``), run
once into a temporary folder; its objects inventory (``objects.inv``) lists every documented name. The build executes
every notebook of ``notebooks/`` into its page (myst-nb; an error in a cell fails it), so this is also where the
notebooks are tested.
"""

from __future__ import annotations

import importlib
import inspect
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

pytest.importorskip("sphinx")
pytest.importorskip("myst_parser")
pytest.importorskip("myst_nb")

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
NOTEBOOKS = sorted(p.stem for p in (ROOT / "notebooks").glob("*.ipynb"))


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """The HTML build of docs/, fresh (``-E``); fails the test on the first warning, listing them all."""
    out = tmp_path_factory.mktemp("docs") / "html"
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-E", "-W", "--keep-going", "-q", "-b", "html", str(DOCS), str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"the docs build failed or warned:\n{proc.stderr[-6000:]}"
    return out


def read_inventory(path: Path) -> dict[str, set[str]]:
    """``{domain:role: {names}}`` from a Sphinx objects inventory (version 2: four header lines, then zlib)."""
    raw = path.read_bytes()
    header_end = 0
    for _ in range(4):
        header_end = raw.index(b"\n", header_end) + 1
    assert raw.startswith(b"# Sphinx inventory version 2"), raw[:40]
    entries: dict[str, set[str]] = {}
    for line in zlib.decompress(raw[header_end:]).decode().splitlines():
        # name domain:role priority uri display-name (the name itself may hold spaces only for labels)
        name, role = line.split(" ", 2)[:2]
        entries.setdefault(role, set()).add(name)
    return entries


def public_names(modname: str = "egorefine") -> list[tuple[str, bool]]:
    """Every ``module.name`` of egorefine's ``__all__`` and, recursively, of each subpackage it lists, with
    whether the name is a module."""
    module = importlib.import_module(modname)
    names: list[tuple[str, bool]] = []
    for name in module.__all__:
        obj = getattr(module, name)
        full = f"{modname}.{name}"
        if inspect.ismodule(obj):
            names.append((obj.__name__, True))
            names += public_names(obj.__name__)
        else:
            names.append((full, False))
    return names


def test_docs_build_without_warnings(built):
    assert (built / "index.html").is_file()
    for page in ("getting-started", "method", "architecture", "decisions", "benchmarks", "api/index"):
        assert (built / f"{page}.html").is_file(), page


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_pages_hold_their_outputs(built, name):
    # stored without outputs, executed by the build: a page with outputs and figures is a notebook that ran
    page = (built / "notebooks" / f"{name}.html").read_text()
    assert page.count("cell_output") >= 2, name
    assert "<img " in page, f"{name}: no figure among its outputs"
    assert "Traceback" not in page, name


def test_landing_page_shows_the_picture_and_the_example(built):
    page = (built / "index.html").read_text()
    assert "demo_maps" in page and "EgoMotionRefiner" in page and "pip install" in page


def test_every_public_name_has_an_entry(built):
    inventory = read_inventory(built / "objects.inv")
    modules = inventory.get("py:module", set())
    documented = set().union(*(names for role, names in inventory.items() if role.startswith("py:")))
    names = public_names()
    assert len(names) > 100  # the walk reached the subpackages
    missing = [name for name, is_module in names if name not in (modules if is_module else documented)]
    assert not missing, f"public names without an entry in the docs: {missing}"


def test_inventory_reader_sees_entries(built):
    inventory = read_inventory(built / "objects.inv")
    assert "egorefine.refine.EgoMotionRefiner" in inventory["py:class"]
    assert "egorefine.motion.motion_field" in inventory["py:function"]
    assert "method" in inventory["std:doc"]
