"""``oralnav report``: the seeds' experiments in simulation, each beside the paper's figures,
as ``DIR/index.html`` (self-contained) and ``DIR/report.json`` (bench/report/).

    oralnav report --out DIR [--quick] [--force] [--only KEY ...] [--scheduler ADDRESS]
                   [--workers N] [--config FILE] [--list] [--json]

``--config FILE`` reads ``scheduler`` and ``workers`` from the file's ``[report]`` table
(a lab's cluster address kept with its other settings); the options win over it.

Progress and the time left go to stderr. Exit status: 0 the report is complete and no
experiment failed (a missed target is a result, not an error), 1 an experiment failed
(its section says why; the rest is written), 2 bad input (an output folder that holds
something else, an unknown experiment, an unreachable scheduler), 130 interrupted (what
finished is kept; the same command resumes).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["add_parser", "cmd_report"]


def add_parser(sub: argparse._SubParsersAction) -> None:
    rp = sub.add_parser("report", help="the seeds' experiments in one HTML report beside the "
                                       "papers (quick: about 10 min; full: see docs)")
    rp.add_argument("--out", help="folder for index.html, report.json and charts/")
    rp.add_argument("--quick", action="store_true",
                    help="fewer frames, trials and sizes (about 10 minutes on 2 cores)")
    rp.add_argument("--force", action="store_true",
                    help="write over a folder that holds a finished report or other files "
                         "(only report.json, index.html and charts/ are replaced)")
    rp.add_argument("--only", nargs="+", metavar="KEY",
                    help="run these experiments only (a key such as 000/table1, or a seed "
                         "prefix such as 000/); --list shows the keys")
    rp.add_argument("--scheduler", metavar="ADDRESS",
                    help="run Monte Carlo trials on Dask: 'local' starts a LocalCluster, an "
                         "address (tcp://host:8786) joins a running cluster; default a "
                         "local process pool")
    rp.add_argument("--workers", type=int, default=None,
                    help="worker processes for trials (default one per CPU)")
    rp.add_argument("--config", metavar="FILE",
                    help="a TOML file whose [report] table sets scheduler and workers (the "
                         "options above win over it)")
    rp.add_argument("--list", action="store_true", help="list the experiments and exit")
    rp.add_argument("--json", action="store_true",
                    help="print a summary object (key -> verdict) on stdout")
    rp.set_defaults(func=cmd_report)


def _apply_config(args: argparse.Namespace, path: Path) -> None:
    """Fill ``args.scheduler`` and ``args.workers`` from ``path``'s ``[report]`` table
    where the command line left them unset; ValueError naming the file and key."""
    import tomllib

    try:
        doc = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"--config {path}: cannot read it ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"--config {path}: not TOML ({exc})") from None
    table = doc.get("report", {})
    if not isinstance(table, dict):
        raise ValueError(f"--config {path}: [report] must be a table")
    unknown = sorted(set(table) - {"scheduler", "workers"})
    if unknown:
        raise ValueError(f"--config {path}: [report] has unknown keys {unknown}; it takes "
                         "scheduler and workers")
    sched, workers = table.get("scheduler"), table.get("workers")
    if sched is not None and (not isinstance(sched, str) or not sched):
        raise ValueError(f"--config {path}: [report] scheduler must be 'local' or an "
                         f"address such as 'tcp://host:8786', got {sched!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)):
        raise ValueError(f"--config {path}: [report] workers must be a whole number, got "
                         f"{workers!r}")
    if args.scheduler is None:
        args.scheduler = sched
    if args.workers is None:
        args.workers = workers


def _say(msg: str) -> None:
    print(f"oralnav report: {msg}", file=sys.stderr, flush=True)


def cmd_report(args: argparse.Namespace) -> int:
    from oralnav.cli.extras import require_bench_extra

    require_bench_extra()
    from oralnav.bench.executor import SchedulerError, TrialRunner, require_dask
    from oralnav.bench.report.experiments import all_experiments, select
    from oralnav.bench.report.run import ReportError, Settings, run_report

    experiments = all_experiments()
    if args.list:
        for e in experiments:
            q, f = e.estimate_s
            print(f"{e.key:24s} {e.title}  (about {q / 60:.1f} min quick, {f / 60:.1f} min "
                  "full)")
        return 0
    if not args.out:
        _say("error: --out DIR is required (or --list)")
        return 2
    if args.config:
        try:
            _apply_config(args, Path(args.config))
        except ValueError as exc:
            _say(f"error: {exc}")
            return 2
    if args.workers is not None and args.workers < 1:
        _say(f"error: --workers must be at least 1, got {args.workers}")
        return 2
    try:
        chosen = select(experiments, args.only)
        if args.scheduler not in (None, "local"):
            # reach the cluster (and check its workers' version) before anything runs
            with TrialRunner(args.scheduler, args.workers) as runner:
                _say(f"scheduler {args.scheduler}: {runner.name}")
        elif args.scheduler == "local":
            require_dask()
        settings = Settings(quick=args.quick, scheduler=args.scheduler, workers=args.workers,
                            command=" ".join(["oralnav", *sys.argv[1:]]))
        doc = run_report(Path(args.out), chosen, settings, force=args.force, say=_say)
    except (ReportError, SchedulerError, ValueError) as exc:
        _say(f"error: {exc}")
        if args.json:
            print(json.dumps({"error": str(exc), "exit": 2}))
        return 2
    except KeyboardInterrupt:
        _say(f"interrupted: what finished is kept in {args.out}; run the same command "
             "again to resume")
        return 130
    verdicts = {k: v["verdict"] for k, v in doc["experiments"].items()}
    if args.json:
        print(json.dumps({"out": str(args.out), "complete": doc["complete"],
                          "elapsed_s": doc.get("elapsed_s"), "verdicts": verdicts}))
    return 1 if "failed" in verdicts.values() else 0
