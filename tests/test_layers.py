"""Issue 31, the layer rules as executable contracts: import-linter keeps every contract of
pyproject.toml on this tree, and breaks the right one when a driver imports the math layer
(the deliberately wrong import the issue asks to be shown failing)."""

from __future__ import annotations

import shutil
from pathlib import Path

from tests.layers import ROOT, build_view, lint_imports, package_folders


def test_the_tree_keeps_every_layer_contract(tmp_path):
    """issue 31: lint-imports passes on the tree as committed (each contract KEPT)."""
    res = lint_imports(build_view(tmp_path / "view"))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "BROKEN" not in res.stdout
    assert "0 broken" in res.stdout


def test_a_driver_importing_control_breaks_the_layers(tmp_path):
    """issue 31: lint-imports fails, naming the contract and the import, when a driver
    module imports ``oralnav.control`` (drivers know no math)."""
    drivers = tmp_path / "drivers"
    shutil.copytree(ROOT / "drivers", drivers,
                    ignore=shutil.ignore_patterns("__pycache__"))
    clock = drivers / "clock.py"
    clock.write_text(clock.read_text() + "\nfrom oralnav.control.geometry import invert  # wrong\n")
    res = lint_imports(build_view(tmp_path / "view", replace={"drivers": drivers}))
    assert res.returncode != 0
    out = res.stdout
    assert "drivers: no math, safety, simulator or configuration BROKEN" in out
    assert "oralnav.drivers.clock -> oralnav.control.geometry" in out


def test_the_view_maps_every_installed_folder(tmp_path):
    """issue 31: the view the contracts run on links each folder pyproject maps, so no
    layer escapes the check."""
    view = build_view(tmp_path / "view")
    folders = package_folders()
    assert {"oralnav.control", "oralnav.daemon", "oralnav.drivers", "oralnav.realtime",
            "oralnav.sim", "oralnav.cli"} <= set(folders)
    for name, folder in folders.items():
        link = view / "oralnav" / name.split(".", 1)[1]
        assert link.resolve() == Path(folder).resolve()


def test_every_package_folder_is_installed():
    """issue 31: each folder with an ``__init__.py`` under the mapped folders is a package
    pyproject installs (a subpackage left out would be missing from a built wheel)."""
    import tomllib

    with open(ROOT / "pyproject.toml", "rb") as f:
        listed = set(tomllib.load(f)["tool"]["setuptools"]["packages"])
    found = {"oralnav"}
    for name, folder in package_folders().items():
        for init in Path(folder).rglob("__init__.py"):
            rel = init.parent.relative_to(folder)
            found.add(".".join([name, *rel.parts]))
    assert found == listed


def _modules_with_code() -> set[str]:
    """Repository paths of the installed modules that hold more than a docstring."""
    import ast

    out = set()
    for _, folder in sorted(package_folders().items()):
        for f in Path(folder).rglob("*.py"):
            body = ast.parse(f.read_text()).body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value,
                                                                     ast.Constant):
                body = body[1:]
            if body:
                out.add(f.relative_to(ROOT).as_posix())
    return out


def test_the_architecture_map_matches_the_tree():
    """issue 31: docs/architecture.md's map names every module that holds code, one line
    each, and names no module that does not exist."""
    import re

    doc = (ROOT / "docs" / "architecture.md").read_text()
    section = doc.split("## Map: one line per module", 1)[1].split("\n## ", 1)[0]
    named = re.findall(r"^- `([\w/]+\.py)`: ", section, flags=re.M)
    assert len(named) == len(set(named)), "a module is named twice"
    missing = _modules_with_code() - set(named)
    assert not missing, f"modules missing from the map: {sorted(missing)}"
    stale = {p for p in named if not (ROOT / p).is_file()}
    assert not stale, f"the map names modules that do not exist: {sorted(stale)}"


def test_every_path_the_architecture_page_names_exists():
    """issue 31: the page's other sections ("where to find", the frame's path, the
    contracts) name only files and folders that exist."""
    import re

    doc = (ROOT / "docs" / "architecture.md").read_text()
    paths = set(re.findall(r"`([a-z_]+/[\w/]*(?:\.py|/))`", doc))
    assert len(paths) > 40
    missing = sorted(p for p in paths if not (ROOT / p).exists())
    assert not missing, f"docs/architecture.md names paths that do not exist: {missing}"
