"""The planning figures as PNG (matplotlib, headless): slice fits (the paper's Fig. 7/16),
the objective's contour over d_T and theta_T (Fig. 18/20) and the PSO convergence
(Fig. 18d). Used by ``oralnav plan ... --figures DIR`` and ``oralnav bench planning``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from oralnav.config.loader import atomic_write_bytes
from oralnav.control.planning import polar_curve as pc
from oralnav.control.planning.fpsm import FPSM
from oralnav.control.planning.placement import Placement, PlacementProblem

#: The objective's unit by equation: the paper's distances are in mm, and eq. 14 sums
#: their signed square roots, eq. 21 the distances, eq. 22 their signed squares.
OBJECTIVE_UNITS = {14: "mm^0.5", 21: "mm", 22: "mm^2"}


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())
    return path


def slice_fits(model: FPSM, boundaries: np.ndarray, path: Path,
               title: str = "FPSM slices") -> Path:
    """Each slice's fitted curve (blue) over the tissue boundary seen from its origin (red),
    in millimetres, every panel on the same x and y scale (mm, ticks on the outer panels)
    and one legend for all. ``boundaries`` (M, R): boundary radii on R rays."""
    plt = _figure()
    from matplotlib.lines import Line2D

    m = model.slices
    cols = min(5, m)
    rows = math.ceil(m / cols)
    # shared axes: the slices compare at a glance, and the outer ticks give the scale
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.6 * rows), squeeze=False,
                             sharex=True, sharey=True)
    th = np.linspace(0, 2 * math.pi, boundaries.shape[1], endpoint=False)
    thc = np.linspace(0, 2 * math.pi, 721)
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= m:
            ax.set_axis_off()
            continue
        rb = boundaries[j] * 1e3
        rc = pc.evaluate(model.rho[j], thc) * 1e3
        ax.plot(rb * np.cos(th), rb * np.sin(th), ".", ms=1.0, color="tab:red",
                label="tissue boundary (rays from the slice origin)")
        ax.plot(rc * np.cos(thc), rc * np.sin(thc), "-", lw=1.0, color="tab:blue",
                label="fitted curve (FPSM)")
        ax.plot(0, 0, "+", color="k", label="slice origin")
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.25)
        ax.set_title(f"z = {model.z[j] * 1e3:.1f} mm", fontsize=8)
        if j % cols == 0:
            ax.set_ylabel("y (mm)", fontsize=8)
        if j + cols >= m:         # the lowest panel of its column
            ax.set_xlabel("x (mm)", fontsize=8)
            ax.xaxis.set_tick_params(labelbottom=True)
    handles, labels = axes[0][0].get_legend_handles_labels()
    # one legend above the panels, where it covers none of them; the boundary's dots are
    # drawn larger there than in the panels, to be seen
    handles[0] = Line2D([], [], ls="none", marker=".", ms=6, color="tab:red")
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=3,
               fontsize=8, frameon=False)
    fig.suptitle(title, y=1.06)
    fig.tight_layout()
    out = _save(fig, path)
    plt.close(fig)
    return out


def objective_contour(problem: PlacementProblem, placement: Placement | None, path: Path,
                      n: int = 161, title: str | None = None) -> Path:
    """The objective over the search box (``n`` x ``n`` cells), with the PSO's answer
    marked; d_T in mm, theta_T in degrees, the colour bar in the objective's unit."""
    plt = _figure()
    d, th, F = problem.grid(n, n)
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    # colliding placements reach huge values (a line almost parallel to the slices meets
    # them far outside); the colour scale spans the safe-to-moderate range and saturates
    lo, hi = float(np.min(F)), float(np.quantile(F, 0.75))
    hi = max(hi, lo + 1e-9)
    cs = ax.contourf(d * 1e3, np.degrees(th), np.clip(F, lo, hi),
                     levels=np.linspace(lo, hi, 41), cmap="viridis")
    fig.colorbar(cs, ax=ax, label=f"objective, eq. {problem.s.equation} "
                 f"({OBJECTIVE_UNITS[problem.s.equation]})\nsmaller is safer; the top "
                 "colour: 75th percentile and above")
    k = np.unravel_index(np.argmin(F), F.shape)
    ax.plot(d[k[1]] * 1e3, math.degrees(th[k[0]]), "wx", ms=9, label="grid minimum")
    if placement is not None:
        ax.plot(placement.d_T * 1e3, math.degrees(placement.theta_T), "r+", ms=12, mew=2,
                label="PSO")
    ax.set_xlabel("d_T (mm)")
    ax.set_ylabel("theta_T (deg)")
    if title:
        ax.set_title(title, fontsize=10)
    # below the axes, clear of the contours and of the colour bar
    # (grey, so the white grid-minimum mark shows)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8,
              facecolor="0.75")
    out = _save(fig, path)
    plt.close(fig)
    return out


def convergence(placement: Placement, path: Path) -> Path:
    """The swarm's best objective against the iteration."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6.0, 3.6))
    ax.plot(np.arange(placement.history.size), placement.history, "-", color="tab:blue")
    ax.set_xlabel("iteration")
    ax.set_ylabel("best objective")
    ax.set_title(f"PSO: {placement.iterations} iterations, {placement.time_ms:.1f} ms")
    ax.grid(alpha=0.3)
    out = _save(fig, path)
    plt.close(fig)
    return out
