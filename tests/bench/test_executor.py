"""Issue 35, item 2 and "Done when" 5: the benchmarks' trials run through one executor
interface; a Dask LocalCluster gives the same results trial by trial as the process pool
and this process, a worker killed mid-sweep loses no trial and counts none twice, and an
engine that cannot be used is refused saying what to do."""

from __future__ import annotations

import sys

import pytest

from oralnav.bench.executor import (
    LOCAL_CLUSTER_SETTINGS,
    SchedulerError,
    TrialRunner,
    kernel_threads,
    worker_profiles,
)

from .sweep_trials import dask_setting, dying_trial, fit_trial, numba_threads, worker_environ

distributed = pytest.importorskip("distributed", reason="Dask is the extra oralnav[cluster]")

SEEDS = list(range(100, 112))
#: threads Dask keeps for the whole process once used (its offload pool, its event loop
#: thread, the watchers of the worker processes it starts, which go with the cluster):
#: the suite's leaked-thread check (tests/conftest.py) lets these be
LONG_LIVED_THREADS = ("Dask-", "IO loop", "AsyncProcess Dask", "QueueFeederThread")


@pytest.fixture(scope="module")
def cluster():
    """One two-worker LocalCluster for the module's tests (starting one takes seconds)."""
    with TrialRunner("local", workers=2) as runner:
        yield runner


def test_every_engine_gives_the_same_trials(cluster):
    """The same sweep in this process, on a process pool and on a two-worker
    LocalCluster: identical results, trial by trial, in the items' order; each trial is
    reported once as it finishes."""
    with TrialRunner(workers=1) as here:
        want = here.map(fit_trial, SEEDS)
        assert here.name == "this process"
    with TrialRunner(workers=2) as pool:
        assert pool.map(fit_trial, SEEDS) == want
        assert pool.name == "process pool (2 workers)"
    seen = []
    got = cluster.map(fit_trial, SEEDS, on_result=lambda i, r, done, n: seen.append((i, done, n)))
    assert got == want and [r[0] for r in got] == SEEDS
    assert sorted(i for i, _, _ in seen) == list(range(len(SEEDS)))
    assert [d for _, d, _ in seen] == list(range(1, len(SEEDS) + 1))
    assert cluster.name == "dask LocalCluster (2 workers)" and cluster.dashboard


def test_a_worker_killed_mid_sweep_loses_no_trial(cluster, tmp_path):
    """Trial 3 kills its worker process: the scheduler runs it again on a worker that
    lives, and every trial comes back exactly once with the result it would have had."""
    seen = []
    got = cluster.map(dying_trial, [(s, str(tmp_path)) for s in range(8)],
                      on_result=lambda i, r, done, n: seen.append(i))
    assert (tmp_path / "died").exists()  # the worker did die
    assert got == [fit_trial(s) for s in range(8)]
    assert sorted(seen) == list(range(8))


def test_an_engine_that_cannot_be_used_is_refused_clearly(monkeypatch):
    """No Dask installed: what to install; no scheduler at the address: which address,
    and how to start one; a bad worker count: the bound."""
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(SchedulerError, match=r"oralnav\[cluster\]"):
        TrialRunner("local")
    monkeypatch.undo()
    with pytest.raises(SchedulerError, match=r"tcp://127.0.0.1:9.*dask scheduler"):
        TrialRunner("tcp://127.0.0.1:9", connect_timeout=1.0)
    with pytest.raises(ValueError, match="at least 1"):
        TrialRunner(workers=0)


def build_seen_from_worker_thread() -> str:
    """Stands in for ``oralnav_build``: a worker thread reports another build than the
    main thread (as a worker host with another checkout would)."""
    import threading

    return ("0.1.0 (aaaa)" if threading.current_thread() is threading.main_thread()
            else "0.0.9 (bbbb)")


def test_a_worker_of_another_build_is_refused(monkeypatch, caplog):
    """Issue 35, bad input: a cluster whose worker runs another oralnav is refused, the
    message naming both builds (trials of other code would not be the same trials). A
    cluster of the same build whose workers profile their tasks is used, with a warning
    saying how to start them without (the profiler costs a trial about a quarter)."""
    from oralnav.bench import executor

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=":0") as lc:
        monkeypatch.setattr(executor, "oralnav_build", build_seen_from_worker_thread)
        with pytest.raises(SchedulerError, match=r"0\.0\.9 \(bbbb\).*0\.1\.0 \(aaaa\)"):
            TrialRunner(lc.scheduler_address)
        monkeypatch.undo()
        with TrialRunner(lc.scheduler_address) as same:  # the same build is accepted
            assert same.workers == 1
        assert "PROFILE__ENABLED=False" in caplog.text


def test_pool_workers_leave_with_a_killed_sweep(tmp_path):
    """A sweep killed outright (SIGKILL: no cleanup runs) leaves no pool worker behind:
    its workers come from a fork server, not from the sweep, and watch it instead."""
    import os
    import subprocess
    import time

    pid_file = tmp_path / "pids"
    owner = subprocess.Popen([sys.executable, "-c", "from tests.bench.sweep_trials import "
                              f"run_pool_forever; run_pool_forever({str(pid_file)!r})"])
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline, "the pool never started"
            assert owner.poll() is None, "the sweep died on its own"
            time.sleep(0.1)
        workers = [int(p) for p in pid_file.read_text().split()]
        assert workers and owner.pid not in workers
    finally:
        owner.kill()
        owner.wait()

    def alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True

    deadline = time.monotonic() + 10
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(alive(p) for p in workers), "pool workers outlived their sweep"


def test_local_cluster_workers_run_in_the_pools_environment(cluster):
    """Issue 35 target ("the engine must not cost what it saves"): the LocalCluster's
    workers do not get Dask's MALLOC_TRIM_THRESHOLD_ (with it a needle trial took 23.6 s
    against 15.3 s) nor its one-thread settings: they run as the pool's workers do."""
    import os

    here = worker_environ(None)
    for got in cluster.map(worker_environ, [0, 1]):
        assert got["MALLOC_TRIM_THRESHOLD_"] == os.environ.get("MALLOC_TRIM_THRESHOLD_")
        assert got == here


def test_workers_share_the_cores_among_their_kernels(cluster):
    """Issue 36 item 3 (per-trial cost): each of the pool's and the LocalCluster's two
    workers runs its numba kernels on its share of the CPUs (``kernel_threads``, at
    least one), not on a thread per CPU each (twice as many threads as cores: a
    two-worker needle sweep 14 % slower on two cores)."""
    import os

    share = kernel_threads(2)
    assert share == max(1, (os.cpu_count() or 1) // 2)
    with TrialRunner(workers=2) as pool:
        assert pool.map(numba_threads, [0, 1, 2, 3]) == [share] * 4
    assert cluster.map(numba_threads, [0, 1, 2, 3]) == [share] * 4


def test_a_worker_whose_numba_is_preloaded_can_still_compile():
    """Issue 36 item 3 (regression): the fork server preloads `oralnav`'s main module,
    which imports numba, so a worker may start with numba's thread pool sized already
    (here 4). Its start must not name another size in the environment: a kernel whose
    cache a code change made stale compiles in the worker, the compile re-reads the
    environment, and numba then raised "Cannot set NUMBA_NUM_THREADS to a different
    value once the threads have been launched" and stopped every sweep. The worker
    compiles a fresh parallel kernel and runs it on its share of the threads (1)."""
    import os
    import subprocess

    code = """
import os, numba, numpy as np
from oralnav.bench.executor import _worker_start
_worker_start(os.getpid(), 1)

@numba.njit(parallel=True)
def total(x):
    s = 0.0
    for i in numba.prange(x.size):
        s += x[i]
    return s

assert total(np.ones(1000)) == 1000.0
print(numba.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
"""
    env = {**os.environ, "NUMBA_NUM_THREADS": "4"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["1", "4"]


def test_local_cluster_workers_do_not_profile_the_trials(cluster, tmp_path):
    """Issue 35 target (LocalCluster within 10 % of the pool): Dask's statistical profiler
    takes the GIL from the trial every 10 ms (a needle trial 20.0-24.8 s with it against
    17.3-19.7 s without); the LocalCluster's workers run without it and with slower
    housekeeping (its machinery took 12.8 % of a core idle, 2.0 % with it), and so does a
    worker restarted after a crash, with the pool's environment too."""
    import time

    cluster.map(dying_trial, [(s, str(tmp_path)) for s in range(4)])  # one worker dies
    assert (tmp_path / "died").exists()
    client = cluster._client
    deadline = time.monotonic() + 30
    while len(client.scheduler_info()["workers"]) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)  # the nanny restarts the dead worker
    assert list(client.run(worker_profiles).values()) == [False, False]
    assert list(client.run(worker_environ, None).values()) == [worker_environ(None)] * 2
    # the cluster's slower housekeeping (LOCAL_CLUSTER_SETTINGS), on every worker
    for key, value in LOCAL_CLUSTER_SETTINGS.items():
        assert list(client.run(dask_setting, key).values()) == [value] * 2, key
