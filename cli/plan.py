"""``oralnav plan``: preoperative planning from the command line (docs/planning.md).

    oralnav plan fpsm --mesh FILE --slices M --points N --out FPSM.json
                      [--samples Z] [--method slp|lbfgs|paper] [--units auto|m|mm]
                      [--z-range-mm LOW HIGH] [--margin-mm D] [--figures DIR] [--json]
    oralnav plan place --scene FILE [--equation 14|21|22] [--seed N] [--figures DIR] [--json]

``plan fpsm`` fits the surrogate model to a mesh and writes it atomically (a refused fit
writes nothing). ``plan place`` prints ``{"d_T", "theta_T", "objective", "iterations",
"time_ms", "collision_free"}`` (metres, radians) and exits 3 when no collision-free
placement exists: the numbers are then the least bad found, never a plan to follow.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

from oralnav.cli.extras import require_bench_extra
from oralnav.config.planning import load_planning_scene, save_fpsm
from oralnav.control.planning.fpsm import (
    DENSE_RAYS,
    METHODS,
    FitSettings,
    build_fpsm,
    slice_boundaries,
)
from oralnav.control.planning.placement import EQUATIONS, PlacementProblem, place

#: Exit status of ``plan place`` when no collision-free placement exists.
NO_SAFE_PLACEMENT = 3


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def cmd_fpsm(args: argparse.Namespace) -> int:
    from oralnav.config.mesh import load_mesh

    if args.figures:
        require_bench_extra()

    loaded = load_mesh(args.mesh, units=args.units)
    _progress(f"mesh {args.mesh}: {loaded.report.summary()}")
    z = None if args.z_range_mm is None else (args.z_range_mm[0] * 1e-3,
                                              args.z_range_mm[1] * 1e-3)
    model, report = build_fpsm(loaded.mesh, args.slices, args.points, args.samples, z,
                               FitSettings(method=args.method, margin=args.margin_mm * 1e-3))
    out = save_fpsm(model, Path(args.out), report, args.mesh)
    doc = {"out": str(out), **report.to_dict()}
    if args.figures:
        folder = Path(args.figures)
        folder.mkdir(parents=True, exist_ok=True)
        from oralnav.bench.plan_figures import slice_fits

        dense = slice_boundaries(loaded.mesh, model.z, DENSE_RAYS)
        doc["figures"] = [str(slice_fits(model, dense, folder / "fpsm_slices.png",
                                         f"FPSM {args.slices} x {args.points} ({args.method})"))]
    if args.json:
        print(json.dumps(doc))
    else:
        worst = min(r.coverage for r in report.per_slice)
        print(f"FPSM {args.slices} slices x {args.points} points ({args.method}) in "
              f"{report.total_s * 1e3:.0f} ms: coverage {report.coverage:.1%} (worst slice "
              f"{worst:.1%}), {report.penetrating_samples} penetrating samples, deepest "
              f"excursion between samples {report.penetration_max * 1e3:.3f} mm -> {out}")
    return 0


def cmd_place(args: argparse.Namespace) -> int:
    if args.figures:
        require_bench_extra()
    scene = load_planning_scene(args.scene)
    s = scene.settings
    if args.equation is not None:
        s = replace(s, equation=args.equation)
    if args.seed is not None:
        s = replace(s, pso=replace(s.pso, seed=args.seed))
    if scene.build is not None:
        _progress(f"fitted {scene.source}: coverage {scene.build.coverage:.1%} in "
                  f"{scene.build.total_s * 1e3:.0f} ms")
    p = place(scene.model, scene.hole, s)
    doc = p.to_dict()
    if args.figures:
        from oralnav.bench.plan_figures import convergence, objective_contour

        folder = Path(args.figures)
        folder.mkdir(parents=True, exist_ok=True)
        problem = PlacementProblem(scene.model, scene.hole, s)
        doc_fig = [objective_contour(problem, p, folder / "place_objective.png"),
                   convergence(p, folder / "place_convergence.png")]
        if scene.mesh is not None:
            from oralnav.bench.plan_figures import slice_fits

            dense = slice_boundaries(scene.mesh, scene.model.z, DENSE_RAYS)
            doc_fig.append(slice_fits(scene.model, dense, folder / "fpsm_slices.png"))
        if not args.json:
            _progress("figures: " + ", ".join(str(f) for f in doc_fig))
    if args.json:
        print(json.dumps(doc))
    else:
        state = "collision-free" if p.collision_free else "NO SAFE PLACEMENT"
        print(f"{state}: d_T = {p.d_T * 1e3:.3f} mm, theta_T = {math.degrees(p.theta_T):.3f} "
              f"deg, objective {p.objective:.4f} (eq. {s.equation}), {p.iterations} "
              f"iterations in {p.time_ms:.1f} ms")
    if not p.collision_free:
        _progress(f"oralnav: no collision-free placement: {p.reason}; move the hole, widen "
                  "the search box or use a thinner instrument")
        return NO_SAFE_PLACEMENT
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    pl = sub.add_parser("plan", help="preoperative planning: surrogate model and instrument "
                                     "placement").add_subparsers(dest="cmd", required=True)
    fp = pl.add_parser("fpsm", help="fit the finite-parameter surrogate model to a mesh")
    fp.add_argument("--mesh", required=True, help="oral-cavity mesh (STL, PLY or OBJ) in the "
                                                  "Center frame")
    fp.add_argument("--slices", type=int, default=15, help="slices along Center z (15)")
    fp.add_argument("--points", type=int, default=15, help="control points per slice (15)")
    fp.add_argument("--samples", type=int, default=150, help="sampling rays per slice (150)")
    fp.add_argument("--method", choices=METHODS, default="slp", help="fit method (slp)")
    fp.add_argument("--units", choices=("auto", "m", "mm"), default="auto",
                    help="the mesh file's length unit (auto: from its size)")
    fp.add_argument("--z-range-mm", type=float, nargs=2, metavar=("LOW", "HIGH"),
                    help="slice range along Center z (default: the mesh's extent)")
    fp.add_argument("--margin-mm", type=float, default=0.0,
                    help="clearance kept between the curves and the tissue (0)")
    fp.add_argument("--out", required=True, help="FPSM JSON file to write")
    fp.add_argument("--figures", help="folder for the slice-fit PNG")
    fp.add_argument("--json", action="store_true", help="print one JSON object")
    fp.set_defaults(func=cmd_fpsm)
    pc = pl.add_parser("place", help="place the instrument's feeding target by PSO")
    pc.add_argument("--scene", required=True, help="placement scene TOML (docs/formats.md)")
    pc.add_argument("--equation", type=int, choices=EQUATIONS,
                    help="override the objective (14 adopted; 21, 22 the paper's variants)")
    pc.add_argument("--seed", type=int, help="override the PSO seed")
    pc.add_argument("--figures", help="folder for the contour and convergence PNGs")
    pc.add_argument("--json", action="store_true", help="print one JSON object")
    pc.set_defaults(func=cmd_place)
