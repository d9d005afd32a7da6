"""Run benchmarks: ``python -m bench [render] [--quick] [--out DIR]``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from oralnav.bench import (
    calibration,
    control,
    faults,
    navigation,
    needle,
    needle_tracking,
    planning,
    render,
)

BENCHES = {"render": render.main, "navigation": navigation.main, "control": control.main,
           "calibration": calibration.main, "planning": planning.main, "needle": needle.main,
           "needle_tracking": needle_tracking.main, "faults": faults.main}


def main() -> int:
    p = argparse.ArgumentParser(prog="python -m bench")
    p.add_argument("names", nargs="*", default=list(BENCHES), help=f"of {list(BENCHES)}")
    p.add_argument("--quick", action="store_true", help="fewer repetitions")
    p.add_argument("--out", default=str(Path(__file__).parent / "out"))
    args = p.parse_args()
    for n in args.names:
        if n not in BENCHES:
            p.error(f"unknown benchmark {n!r}; have {list(BENCHES)}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for n in args.names:
        BENCHES[n](out, quick=args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
