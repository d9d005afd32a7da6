"""Issue 31, dependencies by job: a command that needs the optional ``bench`` dependencies
(matplotlib, python-fcl, threadpoolctl) and finds one missing says which and how to install
it, exits 2, and does no work first; the daemon's own modules never import them (the
``bench-extra`` contract in pyproject.toml, checked by tests/test_layers.py)."""

from __future__ import annotations

import sys

import pytest

from oralnav.cli.extras import BENCH_EXTRA, missing_extra
from oralnav.cli.main import run
from tests.helpers import ROOT


@pytest.mark.parametrize("module", sorted(BENCH_EXTRA))
def test_a_bench_command_without_the_extra_names_it_and_does_nothing(module, tmp_path,
                                                                      monkeypatch, capsys):
    """issue 31: `oralnav bench ...` refuses at once (exit 2) naming the missing package
    and the extra, and writes nothing."""
    monkeypatch.setitem(sys.modules, module, None)  # find_spec answers None: not installed
    out = tmp_path / "out"
    assert run(["bench", "navigation", "--quick", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert BENCH_EXTRA[module] in err and "pip install 'oralnav[bench]'" in err
    assert not out.exists()


def test_plan_figures_without_the_extra_refuse_before_planning(tmp_path, monkeypatch, capsys):
    """issue 31: `oralnav plan place --figures` needs matplotlib: refused before the PSO
    runs; without --figures the same command does not need the extra."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    scene = ROOT / "config" / "examples" / "cylinder_case.toml"
    figures = tmp_path / "figures"
    assert run(["plan", "place", "--scene", str(scene), "--figures", str(figures)]) == 2
    assert "matplotlib" in capsys.readouterr().err
    assert not figures.exists()


def test_other_missing_modules_are_not_blamed_on_the_extra():
    """issue 31: only the extra's own packages get the install hint."""
    assert missing_extra(ModuleNotFoundError("x", name="numpy")) is None
    assert "python-fcl" in missing_extra(ModuleNotFoundError("x", name="fcl.collision"))
