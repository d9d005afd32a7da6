"""The report's experiments in the order the report shows them, keyed like ``"000/table1"``
(seed number / the paper's table or figure; ``stability/...`` for the failure sweeps)."""

from __future__ import annotations

from importlib import import_module

from oralnav.bench.report.context import Experiment

__all__ = ["MODULES", "all_experiments", "select"]

#: The modules holding the experiments, in report order; each exposes ``EXPERIMENTS``.
MODULES = ("seed000", "seed002", "seed004", "stability")


def all_experiments() -> tuple[Experiment, ...]:
    """Every experiment, in report order (keys unique)."""
    out: list[Experiment] = []
    for name in MODULES:
        out += import_module(f"oralnav.bench.report.{name}").EXPERIMENTS
    keys = [e.key for e in out]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise RuntimeError(f"report experiments: keys used twice: {dup}")
    return tuple(out)


def select(experiments: tuple[Experiment, ...], only: list[str] | None
           ) -> tuple[Experiment, ...]:
    """The experiments ``only`` names (a key, or a prefix ending in ``/`` such as
    ``"000/"``), in report order; all when ``only`` is empty. An unknown name is a
    ValueError listing the keys."""
    if not only:
        return experiments
    keys = [e.key for e in experiments]
    for name in only:
        if not any(k == name or (name.endswith("/") and k.startswith(name)) for k in keys):
            raise ValueError(f"no experiment {name!r}; have {', '.join(keys)} (or a seed "
                             "prefix such as '000/')")
    return tuple(e for e in experiments
                 if any(e.key == n or (n.endswith("/") and e.key.startswith(n)) for n in only))
