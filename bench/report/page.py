"""``index.html``: the report as one self-contained page (styles inline, charts embedded as
PNG data, no script, no link out), so it opens offline and travels as one file."""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from oralnav.config.loader import atomic_write_text

__all__ = ["render_page", "write_page"]

_STYLE = """
body { font: 15px/1.45 system-ui, sans-serif; margin: 2em auto; max-width: 1100px;
       padding: 0 1em; color: #1b1b1b; }
h1 { font-size: 1.6em; } h2 { margin-top: 2.2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
.met { background: #dff3df; } .missed { background: #f8dcdc; } .failed { background: #f3c4c4; }
.not-measured { background: #fbefc9; } .shown { background: #eef1f6; }
.notrun { background: #eee; }
.verdict { font-weight: 600; padding: 0.35em 0.6em; display: inline-block; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.5em 0; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.8em; }
.meta { color: #555; font-size: 0.9em; }
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(x: Any) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        if not math.isfinite(x):
            return "-"
        return f"{x:.4g}"
    return _e(x)


def _cls(verdict: str) -> str:
    return verdict.replace(" ", "-")


def _target(t: dict[str, Any] | None, unit: str) -> str:
    if not t:
        return ""
    return _e(f"{t['op']} {t['value']:.4g} {unit} ({t['source']})")


def _img(charts: Path, name: str) -> str:
    path = charts / name
    try:
        data = base64.b64encode(path.read_bytes()).decode("ascii")
    except OSError:
        return f"<p class='missed'>chart {_e(name)} is missing</p>"
    return f"<img alt='{_e(name)}' src='data:image/png;base64,{data}'>"


def _section(key: str, title: str, entry: dict[str, Any] | None, charts: Path) -> str:
    anchor = _e(key.replace("/", "-"))
    if entry is None:
        return (f"<h2 id='{anchor}'>{_e(key)}: {_e(title)}</h2>"
                "<p class='verdict notrun'>not run yet (the run stopped before it, or is "
                "still going)</p>")
    parts = [f"<h2 id='{anchor}'>{_e(key)}: {_e(entry.get('title') or title)}</h2>",
             f"<p class='verdict {_cls(entry['verdict'])}'>{_e(entry['verdict_line'])}</p>"]
    if entry.get("setup"):
        parts.append(f"<p>{_e(entry['setup'])}</p>")
    if entry.get("error"):
        tb = entry.get("data", {}).get("traceback", "")
        parts.append(f"<pre>{_e(tb or entry['error'])}</pre>")
    if entry.get("rows"):
        parts.append("<table><tr><th>figure</th><th>unit</th><th>paper</th><th>ours</th>"
                     "<th>target</th><th>verdict</th><th>note</th></tr>")
        for r in entry["rows"]:
            mark = " (from a minority of runs)" if r.get("minority") else ""
            parts.append(
                f"<tr><td>{_e(r['figure'])}</td><td>{_e(r['unit'])}</td>"
                f"<td class='num'>{_num(r['paper'])}</td><td class='num'>{_num(r['ours'])}"
                f"{_e(mark)}</td><td>{_target(r.get('target'), r['unit'])}</td>"
                f"<td class='{_cls(r['verdict'])}'>{_e(r['verdict'])}</td>"
                f"<td>{_e(r.get('note', ''))}</td></tr>")
        parts.append("</table>")
    parts += [_img(charts, c) for c in entry.get("charts", [])]
    if entry.get("seconds") is not None:
        parts.append(f"<p class='meta'>{entry['seconds']:.0f} s</p>")
    return "\n".join(parts)


def render_page(doc: dict[str, Any], order: Sequence[tuple[str, str]], charts: Path) -> str:
    """The page's HTML for report.json's document ``doc``; ``order``: (key, title) of every
    experiment the run was asked for, in report order (those not run yet are listed as
    such); ``charts``: the folder the sections' charts are read from."""
    exps = doc.get("experiments", {})
    m = doc.get("machine", {})
    state = ("complete" if doc.get("complete") else "unfinished (interrupted or running: "
             "rerun the same command to resume)")
    size = "quick" if doc.get("settings", {}).get("quick") else "full"
    head = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<title>oralnav report: the seeds' experiments in simulation</title>",
        f"<style>{_STYLE}</style></head><body>",
        "<h1>oralnav: the seeds' experiments in simulation, beside the papers</h1>",
        f"<p class='meta'>{_e(size)} run, {_e(state)}; command <code>{_e(doc.get('command'))}"
        f"</code>; commit {_e(doc.get('commit'))}; started {_e(doc.get('started'))}"
        + (f", {doc['elapsed_s'] / 60:.1f} min" if doc.get("elapsed_s") else "")
        + f"; machine: {_e(m.get('cpus'))} CPUs, {_e(m.get('cpu'))}, Python "
        f"{_e(m.get('python'))}.</p>",
        "<p>Each verdict is computed from the figures measured in this run against the "
        "target named beside it (the paper's own figure, or a project issue's). 'shown': a "
        "figure beside the paper's with nothing to pass; 'not measured': the figure is "
        "missing, never counted as met.</p>",
        "<table><tr><th>experiment</th><th>verdict</th><th>in one line</th><th>s</th></tr>"]
    for key, title in order:
        e = exps.get(key)
        v = e["verdict"] if e else "not run"
        line = e["verdict_line"] if e else ""
        secs = f"{e['seconds']:.0f}" if e and e.get("seconds") is not None else ""
        head.append(f"<tr><td><a href='#{_e(key.replace('/', '-'))}'>{_e(key)}</a>: "
                    f"{_e(title)}</td><td class='{_cls(v) if e else 'notrun'}'>{_e(v)}</td>"
                    f"<td>{_e(line)}</td><td class='num'>{secs}</td></tr>")
    head.append("</table>")
    body = [_section(key, title, exps.get(key), charts) for key, title in order]
    return "\n".join(head + body + ["</body></html>\n"])


def write_page(path: Path, doc: dict[str, Any], order: Sequence[tuple[str, str]],
               charts: Path) -> None:
    """:func:`render_page` written to ``path`` atomically."""
    atomic_write_text(path, render_page(doc, order, charts))
