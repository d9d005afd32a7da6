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
    in millimetres. ``boundaries`` (M, R): boundary radii on R rays."""
    plt = _figure()
    m = model.slices
    cols = min(5, m)
    rows = math.ceil(m / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.6 * rows), squeeze=False)
    th = np.linspace(0, 2 * math.pi, boundaries.shape[1], endpoint=False)
    thc = np.linspace(0, 2 * math.pi, 721)
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        ax.set_axis_off()
        if j >= m:
            continue
        rb = boundaries[j] * 1e3
        rc = pc.evaluate(model.rho[j], thc) * 1e3
        ax.plot(rb * np.cos(th), rb * np.sin(th), ".", ms=1.0, color="tab:red")
        ax.plot(rc * np.cos(thc), rc * np.sin(thc), "-", lw=1.0, color="tab:blue")
        ax.plot(0, 0, "+", color="k")
        ax.set_aspect("equal")
        ax.set_title(f"z = {model.z[j] * 1e3:.1f} mm", fontsize=8)
    fig.suptitle(title)
    out = _save(fig, path)
    plt.close(fig)
    return out


def objective_contour(problem: PlacementProblem, placement: Placement | None, path: Path,
                      n: int = 161) -> Path:
    """The objective over the search box, with the PSO's answer marked."""
    plt = _figure()
    d, th, F = problem.grid(n, n)
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    # colliding placements reach huge values (a line almost parallel to the slices meets
    # them far outside); the colour scale spans the safe-to-moderate range and saturates
    lo, hi = float(np.min(F)), float(np.quantile(F, 0.75))
    hi = max(hi, lo + 1e-9)
    cs = ax.contourf(d * 1e3, np.degrees(th), np.clip(F, lo, hi),
                     levels=np.linspace(lo, hi, 41), cmap="viridis")
    fig.colorbar(cs, ax=ax, label=f"objective (eq. {problem.s.equation})")
    k = np.unravel_index(np.argmin(F), F.shape)
    ax.plot(d[k[1]] * 1e3, math.degrees(th[k[0]]), "wx", ms=9, label="grid minimum")
    if placement is not None:
        ax.plot(placement.d_T * 1e3, math.degrees(placement.theta_T), "r+", ms=12, mew=2,
                label="PSO")
    ax.set_xlabel("d_T (mm)")
    ax.set_ylabel("theta_T (deg)")
    ax.legend(loc="upper right", fontsize=8)
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
