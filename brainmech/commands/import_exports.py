"""``brainmech import``: rheometer exports -> specimens and recordings tables."""

from __future__ import annotations

from .. import args as a
from ..errors import say


def add(sub) -> None:
    p = sub.add_parser(
        "import", help="import rheometer exports (TA Instruments TRIOS .txt/.xls/.xlsx)",
        description="Read raw traces (.txt), TRIOS workbooks (.xls/.xlsx: Axial, Peak hold "
        "steps) and processed curves (.xlsx) into DIR/specimens.csv, DIR/recordings.csv, "
        "DIR/noise.json (noise SD per specimen and channel, for `diagnose --noise`) and "
        "DIR/import.md (one line per file). Contact from the normal force, cycles and "
        "branches from the gap, holds dropped, ramps resampled to bin averages. Nothing is "
        "written unless every file imports.")
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="export files or folders (searched recursively)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--radius-mm", type=a.positive, default=4.0,
                   help="plate radius R [mm] (default 4: 8 mm plates)")
    p.add_argument("--points-per-ramp", type=a.count(2), default=20,
                   help="bin averages per loading or unloading ramp (default 20)")
    p.add_argument("--region", default=None,
                   help="region (material) of every file (default: from the folders)")
    p.add_argument("--height-mm", type=a.positive, default=None,
                   help="height of processed curves, which hold no gap (default: the mean "
                   "contact height of the raw files of the same material)")
    p.set_defaults(run=run)


def run(args) -> int:
    from brain_fe.io import check_output_dir
    from recordings.rheometer import import_exports

    check_output_dir(args.out)
    s = import_exports(args.paths, args.out, radius_mm=args.radius_mm,
                       points=args.points_per_ramp, region=args.region,
                       height_mm=args.height_mm)
    say([f"{args.out}: {s['specimens']} specimens, {s['rows']} recording rows ("
         + ", ".join(f"{g}: {n}" for g, n in s["groups"].items()) + "); see import.md"])
    return 0
