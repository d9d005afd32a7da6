"""Trials for the executor tests: module-level, so Dask's worker processes import them."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def fit_trial(seed: int) -> tuple[int, float, float]:
    """A small Monte Carlo trial, a pure function of its seed: a line fitted to 200 noisy
    points; (seed, slope, intercept)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, 200)
    y = 0.7 * x + 0.1 + rng.normal(0, 0.05, 200)
    slope, intercept = np.polyfit(x, y, 1)
    return seed, float(slope), float(intercept)


def dying_trial(item: tuple[int, str]) -> tuple[int, float, float]:
    """``fit_trial``, except that trial 3 kills its worker process the first time it runs
    (a marker file in the folder given says it did)."""
    seed, folder = item
    marker = Path(folder) / "died"
    if seed == 3 and not marker.exists():
        marker.write_text(str(os.getpid()))
        os._exit(1)
    return fit_trial(seed)


def pid_then_wait(seconds: float) -> int:
    """This worker's process id, after ``seconds`` of waiting (keeps a worker busy)."""
    import time

    time.sleep(seconds)
    return os.getpid()


def run_pool_forever(pid_file: str) -> None:
    """Start a two-worker pool, write its workers' ids to ``pid_file``, then block on
    long trials until killed (the owner a test kills)."""
    from oralnav.bench.executor import TrialRunner

    with TrialRunner(workers=2) as pool:
        pids = set(pool.map(pid_then_wait, [0.2, 0.2, 0.2, 0.2]))
        Path(pid_file).write_text(" ".join(str(p) for p in sorted(pids)))
        pool.map(pid_then_wait, [600.0, 600.0])


def worker_environ(_item: object) -> dict[str, str | None]:
    """What a worker's environment says of malloc's trim threshold and thread counts."""
    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS",
                                           "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}



def numba_threads(_item: object) -> int:
    """How many threads this process's numba kernels run on (run on a worker)."""
    import numba

    return numba.get_num_threads()


def dask_setting(key: str) -> object:
    """This process's Dask setting ``key`` (run on a worker)."""
    import dask

    return dask.config.get(key)
