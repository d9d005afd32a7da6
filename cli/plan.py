"""``oralnav plan``: preoperative planning from the command line (docs/planning.md).

    oralnav plan fpsm --mesh FILE --slices M --points N --out FPSM.json
                      [--samples Z] [--method slp|lbfgs|paper] [--units auto|m|mm]
                      [--z-range-mm LOW HIGH] [--margin-mm D] [--figures DIR] [--json]
    oralnav plan place --scene FILE [--equation 14|21|22] [--seed N] [--figures DIR] [--json]
    oralnav plan mouth --out FILE [--width-mm W] [--height-mm H] [--depth-mm D] [--no-teeth]
                       [--missing TOOTH ...] [--closed-front] [--resolution R] [--units mm|m]
                       [--json]

``plan fpsm`` fits the surrogate model to a mesh and writes it atomically (a refused fit
writes nothing). ``plan place`` prints ``{"d_T", "theta_T", "objective", "iterations",
"time_ms", "collision_free"}`` (metres, radians) and exits 3 when no collision-free
placement exists: the numbers are then the least bad found, never a plan to follow.
``plan mouth`` writes the parametric oral cavity (``sim/world/oral_cavity.py``), a scan's
stand-in, as a mesh ``plan fpsm`` reads.
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


def cmd_mouth(args: argparse.Namespace) -> int:
    """Write the parametric oral cavity as a mesh (STL, PLY or OBJ from the suffix) in the
    Center frame: Z from the pharynx (z = 0) out of the mouth, y up toward the palate."""
    from oralnav.cli.examples import ExampleError
    from oralnav.config.mesh import FORMATS, check_mesh, save_mesh
    from oralnav.sim.world.oral_cavity import dental_arches, oral_cavity_mesh

    out = Path(args.out)
    if out.suffix.lower() not in FORMATS:
        raise ExampleError(f"--out {out}: the suffix picks the format; use one of "
                           f"{', '.join(FORMATS)}")

    for option, mm in (("--width-mm", args.width_mm), ("--height-mm", args.height_mm),
                       ("--depth-mm", args.depth_mm)):
        if not 20.0 <= mm <= 300.0:  # the model's own range (an oral cavity)
            raise ExampleError(f"{option} must be 20..300 mm, got {mm:g}")
    if not 0.0 < args.resolution <= 4.0:
        raise ExampleError(f"--resolution must be above 0 and at most 4, got "
                           f"{args.resolution:g}")
    size = (args.width_mm * 1e-3, args.height_mm * 1e-3, args.depth_mm * 1e-3)
    teeth = not args.no_teeth
    crowns: tuple = ()
    if teeth:
        try:
            crowns = dental_arches(*size)
        except ValueError:
            raise ExampleError(f"--width-mm {args.width_mm:g} --height-mm {args.height_mm:g}: "
                               "the mouth is too small for the dental arches; open it wider "
                               "or give --no-teeth") from None
    elif args.missing:
        raise ExampleError("--missing leaves out single teeth, but --no-teeth leaves out all")
    unknown = sorted(set(args.missing) - {t.name for t in crowns})
    if unknown:
        raise ExampleError(f"--missing: no tooth named {', '.join(unknown)}; the crowns are "
                           f"{', '.join(t.name for t in crowns)}")
    mesh = oral_cavity_mesh(*size, teeth=teeth, closed_front=args.closed_front,
                            resolution=args.resolution, missing=tuple(args.missing))
    out.parent.mkdir(parents=True, exist_ok=True)
    out = save_mesh(mesh, out, units=args.units)
    report = check_mesh(mesh.copy(), out)
    doc = {"out": str(out), "units": args.units, "width_mm": args.width_mm,
           "height_mm": args.height_mm, "depth_mm": args.depth_mm,
           "teeth": len(crowns) - len(set(args.missing)), "missing": list(args.missing),
           "closed_front": args.closed_front, "faces": report.faces,
           "vertices": report.vertices, "components": report.components,
           "watertight": report.watertight, "boundary_edges": report.boundary_edges}
    if args.json:
        print(json.dumps(doc))
    else:
        front = "closed (watertight)" if report.watertight else "open, as a scan's"
        print(f"mouth {args.width_mm:g} x {args.height_mm:g} x {args.depth_mm:g} mm with "
              f"{doc['teeth']} crowns, front {front}: {report.faces} faces -> {out} "
              f"({args.units}, Center frame); fit it with oralnav plan fpsm --mesh {out}")
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
    mo = pl.add_parser("mouth", help="write the parametric oral cavity (a scan's stand-in) as "
                                     "a mesh for plan fpsm")
    mo.add_argument("--out", required=True, help="mesh file to write: .stl, .ply or .obj")
    mo.add_argument("--width-mm", type=float, default=55.0,
                    help="mouth opening, cheek to cheek (Center x), mm (55)")
    mo.add_argument("--height-mm", type=float, default=45.0,
                    help="mouth opening, floor to palate (Center y), mm (45)")
    mo.add_argument("--depth-mm", type=float, default=90.0,
                    help="pharynx to opening (Center z), mm (90)")
    mo.add_argument("--no-teeth", action="store_true", help="the soft-tissue wall only")
    mo.add_argument("--missing", nargs="+", default=[], metavar="TOOTH",
                    help="crowns to leave out, e.g. lower_left_molar1 (an implant's gap)")
    mo.add_argument("--closed-front", action="store_true",
                    help="cap the opening too, so the mesh is watertight (default: open, as "
                         "a scan of an open mouth)")
    mo.add_argument("--resolution", type=float, default=1.0,
                    help="scales the face count (1: about 29 000 faces)")
    mo.add_argument("--units", choices=("mm", "m"), default="mm",
                    help="the file's length unit (mm, as scanners write)")
    mo.add_argument("--json", action="store_true", help="print one JSON object")
    mo.set_defaults(func=cmd_mouth)
