"""What an experiment of the report gets to run with, and how the registry describes one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from oralnav.bench.report.section import Section

__all__ = ["Context", "Experiment"]


def _quiet(_msg: str) -> None:
    pass


@dataclass(frozen=True)
class Context:
    """An experiment's settings and services.

    Attributes:
        quick: the short run (``oralnav report --quick``: fewer frames, trials, sizes).
        charts: the folder its charts go in (the report's ``charts/``).
        scheduler: where Monte Carlo trials run (``bench/executor.py``'s ``scheduler``:
            ``None`` a local process pool, ``"local"`` a Dask LocalCluster, or an address).
        workers: processes for the trials (``None``: one per CPU).
        say: a progress line for stderr (the runner prefixes the experiment's key).
        trials: the folder where long experiments keep each finished trial, so that an
            interrupted report resumes them (``None``: nothing kept).
    """

    quick: bool
    charts: Path
    scheduler: str | None = None
    workers: int | None = None
    say: Callable[[str], None] = field(default=_quiet)
    trials: Path | None = None

    def trial_store(self, key: str) -> Path | None:
        """Where experiment ``key`` keeps its finished trials (``trials/<key with _>``),
        or ``None`` when this run keeps none."""
        return None if self.trials is None else self.trials / key.replace("/", "_")

    def chart(self, key: str, name: str) -> Path:
        """Where experiment ``key``'s chart ``name`` goes: ``charts/<key with _>_<name>.png``
        (unique per experiment, so no two experiments overwrite each other's files)."""
        return self.charts / f"{key.replace('/', '_')}_{name}.png"


@dataclass(frozen=True)
class Experiment:
    """One experiment of the report.

    Attributes:
        key: ``"<seed>/<figure>"``, e.g. ``"000/table1"``.
        title: the section's heading.
        run: measures and returns the section (raises on failure; the runner turns the
            error into a failed section).
        estimate_s: (quick, full) seconds on the 2-core development machine, for the
            progress line's time left. The full ones are the first end-to-end run's
            times (2026-11-27, 49.7 min in all) plus about 30 % for a slower day.
    """

    key: str
    title: str
    run: Callable[[Context], Section]
    estimate_s: tuple[float, float]
