"""Render speed of the scene simulator (issue 2 target: a 1920x1200 frame with three
fields in <= 30 ms median on the 2-core development machine).

Renders the shipped stereo example (robot, end-effector and opener fields, lens blur,
read + shot noise, illumination gradient) frame after frame and reports the median,
p90 and max per camera, for each supersampling setting.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from oralnav.config.scene import load_scene
from oralnav.sim.world.render import SceneRenderer

SCENE = Path(__file__).resolve().parent.parent / "config" / "examples" / "stereo_cell.toml"


def measure(scene, frames: int) -> dict:
    renderer = SceneRenderer(scene)
    t0 = time.perf_counter()
    renderer.prepare()
    prep = time.perf_counter() - t0
    renderer.render(frame=0)  # warm caches
    per_cam: dict[str, list[float]] = {c: [] for c in scene.rig.names}
    for k in range(1, frames + 1):
        f = renderer.render(frame=k)
        for c, s in f.render_s.items():
            per_cam[c].append(s * 1e3)
    return {"prepare_s": round(prep, 3), "frames": frames,
            "cameras": {c: {"median_ms": round(float(np.median(v)), 2),
                            "p90_ms": round(float(np.percentile(v, 90)), 2),
                            "max_ms": round(float(np.max(v)), 2)} for c, v in per_cam.items()}}


def main(out: Path, quick: bool = False) -> dict:
    scene = load_scene(SCENE)
    frames = 20 if quick else 100
    results = {}
    for ss in (1, 2):
        s = replace(scene, imaging=replace(scene.imaging, supersample=ss))
        print(f"render: supersample {ss}, {frames} frames...", file=sys.stderr, flush=True)
        results[f"supersample_{ss}"] = measure(s, frames)
    doc = {"bench": "render", "scene": str(SCENE.relative_to(SCENE.parents[2])),
           "image": "1920x1200 mono8, 3 fields, blur + noise + illumination gradient",
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "processor": platform.processor() or platform.machine()},
           "target_median_ms": 30.0, "results": results}
    (out / "render.json").write_text(json.dumps(doc, indent=1) + "\n")
    for name, r in results.items():
        for c, v in r["cameras"].items():
            print(f"{name:14s} {c:6s} median {v['median_ms']:6.1f} ms  p90 {v['p90_ms']:6.1f}"
                  f"  max {v['max_ms']:6.1f}")
    return doc
