"""One experiment's result as the report shows it, and its verdict computed from what was
measured (issue 35, "honest verdicts": never written by hand).

A :class:`Row` is one figure: the paper's value (a number or words, or ``None`` where the
paper gives none), ours, and optionally a :class:`Target` ours is held to. A row with a
target is ``met`` or ``missed`` from ``ours``; a row whose figure is missing (``None``,
NaN) is ``not measured``, never met. A section's verdict is the worst of its rows':
``failed`` (the experiment raised) > ``missed`` > ``not measured`` > ``met``; a section
whose rows have no target is ``shown`` (a comparison, nothing to pass).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

__all__ = ["VERDICTS", "Row", "Section", "Target", "row_verdict", "section_verdict"]

Verdict = Literal["met", "missed", "not measured", "failed", "shown"]
#: Worst first: a section takes the first of these any of its rows has.
VERDICTS: tuple[Verdict, ...] = ("failed", "missed", "not measured", "met", "shown")


@dataclass(frozen=True)
class Target:
    """What ``ours`` must be: ``<= value`` (``op="<="``) or ``>= value``; ``source`` says
    whose target it is (``"paper"``: the paper's own figure; ``"issue N"``: a project
    target)."""

    op: Literal["<=", ">="]
    value: float
    source: str

    def __post_init__(self) -> None:
        if self.op not in ("<=", ">="):
            raise ValueError(f"Target.op must be '<=' or '>=', got {self.op!r}")
        if not math.isfinite(self.value):
            raise ValueError(f"Target.value must be finite, got {self.value!r}")

    def holds(self, ours: float) -> bool:
        return ours <= self.value if self.op == "<=" else ours >= self.value

    def text(self, unit: str) -> str:
        return f"{self.op} {_num(self.value)} {unit}".rstrip() + f" ({self.source})"


@dataclass(frozen=True)
class Row:
    """One figure of an experiment. ``ours``: what this run measured (``None`` or NaN:
    missing); ``paper``: the paper's figure for the same thing (number or words; ``None``:
    the paper gives none); ``minority``: ours comes from fewer than half the runs it was
    meant to pool (marked in the table)."""

    figure: str
    unit: str
    paper: float | str | None
    ours: float | None
    target: Target | None = None
    note: str = ""
    minority: bool = False

    @property
    def verdict(self) -> Verdict:
        return row_verdict(self)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["ours"] = None if _missing(self.ours) else float(self.ours)  # type: ignore[arg-type]
        d["target"] = None if self.target is None else {
            "op": self.target.op, "value": self.target.value, "source": self.target.source}
        d["verdict"] = self.verdict
        return d


def _missing(x: Any) -> bool:
    return x is None or (isinstance(x, float) and not math.isfinite(x))


def _num(x: float) -> str:
    """A figure in 4 significant digits (no exponent for ordinary magnitudes)."""
    return f"{x:.4g}"


def row_verdict(row: Row) -> Verdict:
    """``not measured`` when ours is missing (whether or not there is a target), else
    ``met``/``missed`` by the target, else ``shown``."""
    if _missing(row.ours):
        return "not measured"
    if row.target is None:
        return "shown"
    return "met" if row.target.holds(float(row.ours)) else "missed"  # type: ignore[arg-type]


def section_verdict(rows: list[Row], error: str | None = None) -> tuple[Verdict, str]:
    """The section's verdict and its one line, from its rows (or the error it raised)."""
    if error is not None:
        return "failed", f"failed: {error}"
    if not rows:
        return "not measured", "not measured: the experiment gave no figure"
    verdicts = [r.verdict for r in rows]
    worst = next(v for v in VERDICTS if v in verdicts)
    targeted = [r for r in rows if r.target is not None]
    if worst == "shown":
        return "shown", f"shown: {len(rows)} figures, no target to pass"
    if worst == "met":
        return "met", f"met: {len(targeted)} of {len(targeted)} targets"
    bad = [r for r in rows if r.verdict == worst]
    first = bad[0]
    if worst == "missed" and first.target:
        what = (f"{first.figure} = {_num(float(first.ours))} {first.unit}, "  # type: ignore[arg-type]
                f"target {first.target.text(first.unit)}")
    else:  # not measured: the note says why, where the experiment knows
        what = first.figure + (f" ({first.note})" if first.note else "")
    more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
    met = sum(r.verdict == "met" for r in targeted)
    tally = f"; {met} of {len(targeted)} targets met" if targeted else ""
    return worst, f"{worst}: {what}{more}{tally}"


@dataclass
class Section:
    """One experiment's section: its rows, charts (file names under the report's
    ``charts/``), free-form data for report.json, and how long it took (s)."""

    key: str
    title: str
    setup: str
    rows: list[Row] = field(default_factory=list)
    charts: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)
    seconds: float | None = None
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """The report.json entry: ``paper`` and ``ours`` keyed by figure, the rows, the
        computed verdict and its line."""
        verdict, line = section_verdict(self.rows, self.error)
        return {"title": self.title, "setup": self.setup,
                "paper": {r.figure: r.paper for r in self.rows},
                "ours": {r.figure: r.as_dict()["ours"] for r in self.rows},
                "rows": [r.as_dict() for r in self.rows], "verdict": verdict,
                "verdict_line": line, "charts": list(self.charts), "data": self.data,
                "seconds": self.seconds, "error": self.error}
