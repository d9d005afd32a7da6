"""Where a benchmark's independent trials run: in this process, a local process pool, or a
Dask distributed cluster, behind one interface (issue 35, "sweeps on an existing
distributed engine").

A trial is a pure function of its item (a seed and its settings): the same item gives the
same result whichever engine ran it, so a sweep's figures do not depend on where it ran.
:class:`TrialRunner` picks the engine from ``scheduler``:

- ``None``: the embedded default, no service to start: a ``ProcessPoolExecutor`` of
  ``workers`` processes (default one per CPU), or this process alone for one worker;
- ``"local"``: a Dask ``LocalCluster`` of ``workers`` single-threaded worker processes
  started here (its dashboard shows the sweep while it runs);
- an address (``tcp://host:8786`` or ``host:8786``): the Dask scheduler of a cluster
  started with ``dask scheduler`` and ``dask worker ADDRESS`` on each host (docs in
  bench/README.md, "Sweeps on a cluster").

Dask is the optional extra ``oralnav[cluster]``; without it a scheduler other than the
default is refused saying what to install. On a cluster a worker that dies mid-sweep
loses no trial: the scheduler runs its trials again elsewhere, and each comes back once.
"""

from __future__ import annotations

import copy
import logging
import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["SchedulerError", "TrialRunner"]

#: (index of the item, its result, trials done so far, trials in all)
OnResult = Callable[[int, Any, int, int], None]
#: s to reach a cluster's scheduler before giving up
CONNECT_TIMEOUT_S = 10.0
#: What Dask's nanny sets in a worker's environment that a LocalCluster here leaves out,
#: so that its workers run as the pool's do (see TrialRunner.__init__; for a cluster
#: started by hand, bench/README.md "Sweeps on a cluster" says how)
NANNY_ENV_DROPPED = ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                     "OPENBLAS_NUM_THREADS")
#: The Dask setting of a worker's statistical profiler, off on the LocalCluster started
#: here (see TrialRunner.__init__; bench/README.md "Sweeps on a cluster" for one by hand)
WORKER_PROFILER = "distributed.worker.profile.enabled"
#: Dask settings of the LocalCluster started here. Its own machinery (the nannies'
#: memory polls every 100 ms, the system monitors every 500 ms, each event loop's 20 ms
#: tick) took 12.8 % of a core with its two workers idle in a task, 2.0 % with these: on
#: two cores that is CPU the trials lose. The price: memory limits act within 1 s, and the
#: dashboard's system plots update every 5 s.
LOCAL_CLUSTER_SETTINGS: dict[str, Any] = {
    WORKER_PROFILER: False,
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.admin.tick.interval": "500ms",
}
#: How the local pool starts its workers (see TrialRunner.__init__)
_START_METHOD = ("forkserver" if "forkserver" in multiprocessing.get_all_start_methods()
                 else "spawn")


class SchedulerError(RuntimeError):
    """The engine asked for cannot be used (Dask missing, a scheduler unreachable); the
    message says what to do."""


def _dask() -> Any:
    try:
        import distributed
    except ImportError:
        raise SchedulerError("a Dask scheduler needs Dask distributed: pip install "
                             "'oralnav[cluster]' (or run without --scheduler: a local "
                             "process pool)") from None
    return distributed


def kernel_threads(workers: int) -> int:
    """Threads each of ``workers`` processes on this machine gives its compiled kernels
    (numba's prange loops: the needle tracker's particle scores): the CPUs shared out,
    at least one. Each worker starting a thread per CPU put twice as many threads as
    cores on a 2-core machine, and its two-worker needle sweep took 14 % longer (20
    trials, 62.6 s against 52.5 s with one thread each; OpenCV's own threads cost
    nothing measurable)."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _worker_start(owner: int, threads: int) -> None:
    """A pool worker's start: its kernels get ``threads`` threads
    (:func:`kernel_threads`), and it exits once process ``owner`` (the sweep's) is gone.
    A fork server's workers are not the sweep's children, so a sweep killed outright
    (SIGTERM, SIGKILL) would otherwise leave them waiting for work forever."""
    numba = sys.modules.get("numba")
    if numba is None:
        # read by numba when it is first imported, which no trial has done yet here
        os.environ["NUMBA_NUM_THREADS"] = str(threads)
    else:
        # imported already (the fork server preloads the main module, and `oralnav`'s
        # imports numba): its pool's size is fixed, and every compile re-reads the
        # environment and raises once the threads run if it names another size (a
        # kernel whose cache a code change made stale stopped every sweep so). The
        # environment keeps numba's size; the share is the threads a kernel may use.
        size = numba.config.NUMBA_NUM_THREADS
        os.environ["NUMBA_NUM_THREADS"] = str(size)
        numba.set_num_threads(min(threads, size))
    _leave_with(owner)


def _leave_with(owner: int) -> None:
    """Exit this process once process ``owner`` is gone (a watcher thread)."""
    import threading

    def watch() -> None:
        while True:
            time.sleep(1.0)
            try:
                os.kill(owner, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:  # alive, another user's: not ours to judge
                pass

    threading.Thread(target=watch, name="owner-watch", daemon=True).start()


def require_dask() -> None:
    """Raise :class:`SchedulerError` saying what to install when Dask is missing."""
    _dask()


def oralnav_build() -> str:
    """This process's oralnav: its version and commit. Workers must all run the same one,
    since a trial's result is a function of the code as much as of its seed."""
    from oralnav import __version__
    from oralnav.bench.machine import commit

    return f"{__version__} ({commit()})"


def worker_profiles(_item: object = None, dask_worker: Any = None) -> bool:
    """On a Dask worker (as a task, or through ``Client.run``, which passes
    ``dask_worker``): whether its statistical profiler samples the running trials
    (``WORKER_PROFILER``), which costs a needle trial about a quarter of its time."""
    if dask_worker is None:
        from distributed import get_worker

        dask_worker = get_worker()
    return "profile" in dask_worker.periodic_callbacks


class TrialRunner:
    """Runs trials on the engine named by ``scheduler`` (module docstring) with
    ``workers`` processes where it starts them (default one per CPU). A context manager:
    leaving it stops what it started (never a cluster it only connected to)."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None, *,
                 connect_timeout: float | None = None) -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.scheduler = scheduler
        self.workers = workers or os.cpu_count() or 1
        self._pool: ProcessPoolExecutor | None = None
        self._client: Any = None
        self._cluster: Any = None
        if scheduler is None:
            if self.workers > 1:
                # workers come from a fork server, never from this process: once a
                # numba kernel (the needle tracker) has started OpenMP threads here, a
                # forked child aborts ("fork() called from a process already using GNU
                # OpenMP"), and a report runs such kernels between its sweeps
                self._pool = ProcessPoolExecutor(
                    max_workers=self.workers,
                    mp_context=multiprocessing.get_context(_START_METHOD),
                    initializer=_worker_start,
                    initargs=(os.getpid(), kernel_threads(self.workers)))
            return
        distributed = _dask()
        if scheduler == "local":
            import dask

            # Dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_=65536 (and one
            # BLAS/OpenMP thread): the fixed trim threshold also stops glibc raising its
            # mmap threshold, so every image-sized buffer a trial allocates is mapped and
            # faulted in afresh: a needle trial took 23.6 s against 15.3 s (3.5 M page
            # faults against 0.2 M). The workers get the pool's environment instead.
            environ = {k: v for k, v in
                       dask.config.get("distributed.nanny.pre-spawn-environ").items()
                       if k not in NANNY_ENV_DROPPED}
            environ["NUMBA_NUM_THREADS"] = str(kernel_threads(self.workers))  # as the pool's
            # The worker's statistical profiler walks the running trial's stack every
            # 10 ms from the event loop's thread, and each walk takes the GIL from the
            # trial: a needle trial took 20.0-24.8 s with it and 17.3-19.7 s without, the
            # pool's 18.1-19.0 s (seed 10001, one worker, alternated). The dashboard's
            # profile page is the price.
            with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                                  **LOCAL_CLUSTER_SETTINGS}):
                # each nanny gets a whole copy of these settings: it keeps only a
                # shallow merge of the global ones, which the end of this block would
                # undo for a worker it restarts (one restarted after a crash profiled)
                self._cluster = distributed.LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    silence_logs=logging.WARNING, config=copy.deepcopy(dask.config.config))
            self._client = distributed.Client(self._cluster)
        else:
            connect_timeout = connect_timeout or CONNECT_TIMEOUT_S
            try:
                self._client = distributed.Client(scheduler, timeout=connect_timeout)
            except (OSError, TimeoutError) as exc:
                raise SchedulerError(f"cannot reach the Dask scheduler at {scheduler!r} "
                                     f"within {connect_timeout:g} s ({exc}); start one "
                                     "with `dask scheduler` and workers with `dask worker "
                                     "ADDRESS`") from None
            self.workers = len(self._client.scheduler_info().get("workers", {}))
            self._check_builds()

    def _check_builds(self) -> None:
        """Refuse a cluster whose workers run another oralnav than this process."""
        mine = oralnav_build()
        theirs = self._client.run(oralnav_build)
        other = {addr: b for addr, b in theirs.items() if b != mine}
        if other:
            self.close()
            listed = ", ".join(f"{a} runs {b}" for a, b in sorted(other.items()))
            raise SchedulerError(f"the cluster at {self.scheduler!r} has workers with another "
                                 f"oralnav: {listed}; this process runs {mine}. Install the "
                                 "same commit on every worker and restart them")
        profiling = sorted(a for a, on in self._client.run(worker_profiles).items() if on)
        if profiling:
            log.warning("%d of the cluster's workers run Dask's profiler, which slows a "
                        "needle trial by about a quarter: start them with "
                        "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False (%s)",
                        len(profiling), ", ".join(profiling))

    @property
    def name(self) -> str:
        """The engine in words, for a benchmark's record of how it ran."""
        if self._client is not None:
            where = "LocalCluster" if self._cluster is not None else self.scheduler
            return f"dask {where} ({self.workers} workers)"
        if self._pool is not None:
            return f"process pool ({self.workers} workers)"
        return "this process"

    @property
    def dashboard(self) -> str | None:
        """The Dask dashboard's address, where there is one."""
        return None if self._client is None else self._client.dashboard_link

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any],
            on_result: OnResult | None = None) -> list[Any]:
        """``[fn(item) for item in items]``, run on the engine; ``on_result`` is called
        as each trial finishes (in the order they finish). ``fn`` must be importable
        by the workers (a module-level function of an installed package). A trial that
        raises stops the sweep with its error."""
        items = list(items)
        results: list[Any] = [None] * len(items)
        done = 0

        def finished(i: int, value: Any) -> None:
            nonlocal done
            results[i] = value
            done += 1
            if on_result is not None:
                on_result(i, value, done, len(items))

        if self._client is not None:
            distributed = _dask()
            # pure=False: each trial a task of its own, never a result reused from
            # another sweep that happened to have an equal item
            futures = self._client.map(fn, items, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            try:
                for fut in distributed.as_completed(futures):
                    finished(index[fut.key], fut.result())
            finally:
                self._client.cancel(futures)
        elif self._pool is not None:
            futs = {self._pool.submit(fn, item): i for i, item in enumerate(items)}
            try:
                for fut in as_completed(futs):
                    finished(futs[fut], fut.result())
            finally:
                for fut in futs:
                    fut.cancel()
        else:
            for i, item in enumerate(items):
                finished(i, fn(item))
        return results

    def close(self) -> None:
        """Stop the pool or the cluster started here; disconnect from a remote one."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> TrialRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
