"""The optional ``bench`` dependencies: what only the benchmarks and the figure commands
(``oralnav bench``, ``oralnav plan ... --figures``) need. pyproject.toml's ``bench`` extra
holds them; ``./dev.sh test`` and ``./dev.sh bench`` install it, a robot PC's daemon runs
without it. A command that needs it and finds it missing says so and exits 2, before any
long work."""

from __future__ import annotations

import importlib.util

#: Packages only the benchmarks and figure commands need: pyproject's ``bench`` extra, which
#: ``./dev.sh test`` and ``./dev.sh bench`` install; a robot PC's daemon runs without them.
BENCH_EXTRA = {"matplotlib": "matplotlib", "fcl": "python-fcl", "threadpoolctl": "threadpoolctl"}


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The message for a command that needs the ``bench`` extra when ``exc`` says one of
    its packages is missing; None for any other missing module (a real error)."""
    top = (exc.name or "").split(".")[0]
    if top not in BENCH_EXTRA:
        return None
    return (f"this command needs {BENCH_EXTRA[top]}, one of the optional 'bench' "
            f"dependencies (benchmarks and figures): pip install 'oralnav[bench]' "
            f"(./dev.sh bench installs them)")


def require_bench_extra() -> None:
    """Refuse at once, before a long run, when the ``bench`` extra is not installed."""
    for module in BENCH_EXTRA:
        if importlib.util.find_spec(module) is None:
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)
