"""The report's chart conventions (issue 35 item 4): every axis labelled with its quantity
and unit, one quantity per axis, legends placed outside the data, and a hollow mark on any
point computed from a minority of the runs it was meant to pool."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["MINORITY_LABEL", "legend_outside", "mark_minority", "plt", "save"]

MINORITY_LABEL = "from a minority of runs"


def plt() -> Any:
    """matplotlib's pyplot on the file-only backend (no display on a robot PC or CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as pyplot

    return pyplot


def legend_outside(ax: Any, **kw: Any) -> None:
    """The legend to the right of the axes, where it covers no data."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
              fontsize=8, **kw)


def mark_minority(ax: Any, xs: Sequence[float], ys: Sequence[float],
                  minority: Sequence[bool], color: str = "black") -> None:
    """Ring the points of ``xs, ys`` whose ``minority`` flag is set (a figure pooled from
    fewer than half the runs), labelled once for the legend."""
    pts = [(x, y) for x, y, m in zip(xs, ys, minority, strict=True) if m]
    if pts:
        ax.scatter(*zip(*pts, strict=True), s=140, facecolors="none", edgecolors=color,
                   linewidths=1.2, label=MINORITY_LABEL, zorder=5)


def save(fig: Any, path: Path) -> str:
    """Write ``fig`` as PNG at ``path`` (its folder made), close it; the file's name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt().close(fig)
    return path.name
