"""One run of the report: the output folder, the experiments in order with progress and the
time left on stderr, ``report.json`` and ``index.html`` rewritten after every experiment.

The folder's states (issue 35, "bad input"):

- absent or empty: a new report;
- holding an unfinished report (``report.json`` with ``"complete": false``) of the same
  commit and the same ``quick``: the run resumes, keeping every experiment that finished
  (a failed one runs again);
- anything else (a finished report, one of other settings, other files): refused with
  :class:`ReportError` unless ``force``, which starts over (only the report's own files
  are replaced: ``report.json``, ``index.html``, ``charts/``, ``trials/``).

Within an experiment, the needle Monte Carlo keeps each finished trial under ``trials/``
as it comes in, so a resumed run reruns only the trials that had not finished.

An experiment that raises becomes a failed section naming its error; the others still run.
Ctrl-C stops the run with what finished already written; running the same command again
resumes.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from oralnav.bench.machine import commit, describe
from oralnav.bench.report.context import Context, Experiment
from oralnav.bench.report.page import write_page
from oralnav.bench.report.section import Section
from oralnav.config.loader import atomic_write_text

__all__ = ["CHARTS", "INDEX", "REPORT_JSON", "ReportError", "Settings", "run_report"]

REPORT_JSON = "report.json"
INDEX = "index.html"
CHARTS = "charts"
#: Finished trials of the long experiments, kept so that an interrupted run resumes them
TRIALS = "trials"


class ReportError(RuntimeError):
    """The report cannot run as asked (the output folder's state); the message says why
    and what to do."""


@dataclass(frozen=True)
class Settings:
    """How the report runs: ``quick`` sizes, where Monte Carlo trials run
    (``scheduler``, ``workers``: see bench/executor.py) and the command line to record."""

    quick: bool = False
    scheduler: str | None = None
    workers: int | None = None
    command: str = ""


def _say(msg: str) -> None:
    print(f"report: {msg}", file=sys.stderr, flush=True)


def _kept(out: Path, settings: Settings, head: str, force: bool) -> dict[str, Any]:
    """The finished sections to keep from an interrupted run in ``out`` (empty for a new
    report); raises :class:`ReportError` where the folder may not be written."""
    if not out.exists():
        return {}
    if not out.is_dir():
        raise ReportError(f"--out {out}: exists and is not a folder")
    if not any(out.iterdir()):
        return {}
    doc_path = out / REPORT_JSON
    doc = None
    if doc_path.is_file():
        try:
            doc = json.loads(doc_path.read_text())
        except (OSError, ValueError):
            doc = None  # unreadable: treated as a folder of other files
    if (isinstance(doc, dict) and doc.get("complete") is False
            and doc.get("commit") == head
            and doc.get("settings", {}).get("quick") == settings.quick
            and not force):
        return {k: v for k, v in doc.get("experiments", {}).items()
                if isinstance(v, dict) and v.get("verdict") != "failed"}
    if not force:
        if isinstance(doc, dict) and doc.get("complete") is False:
            why = (f"holds an unfinished report of commit {doc.get('commit')} with quick="
                   f"{doc.get('settings', {}).get('quick')}; this run is commit {head} with "
                   f"quick={settings.quick}, so it cannot resume it")
        elif isinstance(doc, dict):
            why = "holds a finished report"
        else:
            why = "is not empty and holds no report"
        raise ReportError(f"--out {out} {why}: pass --force to write the report over it "
                          "(only report.json, index.html, charts/ and trials/ are replaced), "
                          "or "
                          "choose another folder")
    for name in (REPORT_JSON, INDEX):
        (out / name).unlink(missing_ok=True)
    shutil.rmtree(out / CHARTS, ignore_errors=True)
    shutil.rmtree(out / TRIALS, ignore_errors=True)
    return {}


def _write(out: Path, doc: dict[str, Any], order: Sequence[Experiment]) -> None:
    """report.json and index.html, each replaced atomically."""
    text = json.dumps(_plain(doc), indent=1, allow_nan=False)
    atomic_write_text(out / REPORT_JSON, text + "\n")
    write_page(out / INDEX, doc, [(e.key, e.title) for e in order], out / CHARTS)


def _plain(o: Any) -> Any:
    """``o`` as strict JSON: numpy made plain, a missing figure (NaN, inf) as null, so
    report.json loads in any JSON reader (a section's data may hold either)."""
    import math

    import numpy as np

    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def _left(done_s: float, done_est: float, remaining_est: float) -> float:
    """Seconds left: the estimates of what remains, scaled by how the finished experiments
    ran against theirs (this machine may be faster or slower than the estimates')."""
    scale = done_s / done_est if done_est > 0 else 1.0
    return remaining_est * scale


def run_report(out: Path, experiments: Sequence[Experiment], settings: Settings,
               force: bool = False, say: Callable[[str], None] = _say) -> dict[str, Any]:
    """Run ``experiments`` into ``out`` (module docstring); returns report.json's document.
    Raises :class:`ReportError` before running anything where the folder may not be
    written."""
    out = Path(out)
    head = commit()
    kept = _kept(out, settings, head, force)
    (out / CHARTS).mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    doc: dict[str, Any] = {
        "report": "oralnav", "command": settings.command, "commit": head,
        "machine": describe(), "settings": {"quick": settings.quick,
                                            "scheduler": settings.scheduler,
                                            "workers": settings.workers},
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "complete": False,
        "experiments": {k: v for k, v in kept.items() if k in {e.key for e in experiments}},
    }
    _write(out, doc, experiments)
    if doc["experiments"]:
        say(f"resuming in {out}: {len(doc['experiments'])} experiments kept from the "
            f"interrupted run ({', '.join(doc['experiments'])})")
    est = {e.key: e.estimate_s[0 if settings.quick else 1] for e in experiments}
    todo = [e for e in experiments if e.key not in doc["experiments"]]
    say(f"{len(todo)} experiments to run, about {sum(est[e.key] for e in todo) / 60:.1f} min "
        f"by the estimates ({'quick' if settings.quick else 'full'})")
    done_s = done_est = 0.0
    for i, exp in enumerate(todo, 1):
        ctx = Context(quick=settings.quick, charts=out / CHARTS, scheduler=settings.scheduler,
                      workers=settings.workers,
                      say=lambda m, k=exp.key: say(f"[{k}] {m}"), trials=out / TRIALS)
        say(f"({i}/{len(todo)}) {exp.key}: {exp.title}")
        t0 = time.perf_counter()
        try:
            section = exp.run(ctx)
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # any failure becomes the section's; the rest still runs
            section = Section(exp.key, exp.title, "", error=f"{type(exc).__name__}: {exc}",
                              data={"traceback": traceback.format_exc()})
            say(f"[{exp.key}] failed: {section.error}")
        section.seconds = round(time.perf_counter() - t0, 2)
        entry = section.as_dict()
        doc["experiments"][exp.key] = entry
        _write(out, doc, experiments)
        done_s += section.seconds
        done_est += est[exp.key]
        left = _left(done_s, done_est, sum(est[e.key] for e in todo[i:]))
        say(f"({i}/{len(todo)}) {exp.key}: {entry['verdict_line']} [{section.seconds:.0f} s; "
            f"about {left / 60:.1f} min left]")
    doc["complete"] = True
    doc["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    _write(out, doc, experiments)
    verdicts = [v["verdict"] for v in doc["experiments"].values()]
    say(f"wrote {out / INDEX} and {out / REPORT_JSON} in {doc['elapsed_s'] / 60:.1f} min: "
        + ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts)))
    return doc
