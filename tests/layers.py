"""Run import-linter's contracts (``[tool.importlinter]`` in pyproject.toml) on this tree.

The card keeps each folder (``control/``, ``daemon/``, ...) at the repository root and maps
it into the ``oralnav`` namespace (pyproject's package-dir). import-linter finds a package's
modules by walking the folder of its root package, and ``oralnav/`` holds only
``__init__.py`` and ``checks.py``, so the contracts run on a *view*: a temporary folder whose
``oralnav/`` links each mapped folder where the installed package has it. Nothing is copied;
the view sees the working tree as it is.

    python -m tests.layers            # what ./dev.sh test runs before pytest
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import tomllib
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_folders(root: Path = ROOT) -> dict[str, Path]:
    """``{dotted subpackage of oralnav: folder}`` for the top-level folders that
    pyproject.toml's ``[tool.setuptools.package-dir]`` maps (``oralnav.control`` ->
    ``control/``); nested subpackages follow their folder."""
    with open(root / "pyproject.toml", "rb") as f:
        mapping = tomllib.load(f)["tool"]["setuptools"]["package-dir"]
    return {name: root / folder for name, folder in mapping.items()
            if name.count(".") == 1}


def build_view(dest: Path, root: Path = ROOT,
               replace: dict[str, Path] | None = None) -> Path:
    """Make ``dest/oralnav`` the installed package's layout out of links into ``root``;
    ``replace`` (``{"drivers": folder}``) links a folder elsewhere instead (a test's
    altered copy). Returns ``dest``, the folder to put first on ``sys.path``."""
    pkg = dest / "oralnav"
    pkg.mkdir(parents=True)
    for f in (root / "oralnav").glob("*.py"):
        (pkg / f.name).symlink_to(f)
    for name, folder in package_folders(root).items():
        leaf = name.split(".", 1)[1]
        (pkg / leaf).symlink_to((replace or {}).get(leaf, folder), target_is_directory=True)
    return dest


def lint_imports(view: Path, root: Path = ROOT,
                 extra: Sequence[str] = ()) -> subprocess.CompletedProcess[str]:
    """Run ``lint-imports`` with pyproject.toml's contracts on ``view`` (no cache: the
    tree changes between runs); the result's stdout lists each contract KEPT or BROKEN."""
    env = dict(os.environ, PYTHONPATH=str(view))
    exe = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(exe), str(root / "pyproject.toml"), "--no-cache", *extra],
                          cwd=view, env=env, capture_output=True, text=True)


def main() -> int:
    """Check the contracts; print import-linter's report when one is broken."""
    with tempfile.TemporaryDirectory(prefix="oralnav-layers-") as tmp:
        res = lint_imports(build_view(Path(tmp)))
    if res.returncode != 0:
        print(res.stdout + res.stderr, file=sys.stderr)
        print("layer rules broken (docs/architecture.md, [tool.importlinter] in "
              "pyproject.toml)", file=sys.stderr)
        return 1
    kept = [ln for ln in res.stdout.splitlines() if ln.startswith("Contracts:")]
    print("lint-imports: " + (kept[0] if kept else "ok"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
