"""``brainmech benchmark-diagnosis``: blind benchmark of the diagnosis."""

from __future__ import annotations

from .. import args as a
from ..errors import CLIError, say


def add(sub) -> None:
    p = sub.add_parser(
        "benchmark-diagnosis", help="blind benchmark of the diagnosis on synthetic specimens",
        description="Generate N synthetic specimens (full protocol, 2 cycles, 1 %% noise, a "
        "finer mesh than the diagnosis), each with one concealed effect or none (controls, "
        ">= 20 %%), store the labels apart, diagnose blind and score: confusion matrix, "
        "accuracy, false alarms, RMS after modelling, parameter recovery. Each case goes "
        "to whichever MPI rank is free (mpirun -n K).")
    p.add_argument("--cases", type=a.count(1), default=None, help="number of cases (required "
                   "unless --rescore)")
    p.add_argument("--rescore", action="store_true",
                   help="score the finished benchmark in --out again (no new runs)")
    p.add_argument("--world", choices=("closed", "open"), default="closed",
                   help="closed: one library effect or none per case, white noise, the "
                   "diagnosis's own model path; open: controls with rig noise (white, "
                   "filtered, wander, drift, quantised), single effects, pairs and effects "
                   "outside the library, recorded on a converged, sub-stepped path at the "
                   "instrument's clock, varied specimens and protocols (default: closed)")
    p.add_argument("--seed", type=a.count(0), default=0)
    p.add_argument("--refinement", type=a.count(1), default=1)
    p.add_argument("--truth-refinement", type=a.count(1), default=3)
    p.add_argument("--effects", type=a.names, default=None, help="comma list (default: all)")
    p.add_argument("--cycles", type=a.count(1), default=2)
    p.add_argument("--increment", type=a.positive, default=0.03,
                   help="stretch increment between recorded points (default 0.03)")
    p.add_argument("--out", required=True)
    p.set_defaults(run=run)


def run(args) -> int:
    from mpi4py import MPI

    from brain_fe.io import check_output_dir
    from diagnosis.benchmark import rescore, run_benchmark
    from diagnosis.effects import check_effects

    if args.world == "open":
        return _run_open(args)
    if args.rescore:
        s = rescore(args.out)
        say([f"cases {s['cases']}, accuracy {s['accuracy']:.3f}, false alarms "
             f"{s['false_alarms_on_controls']}/{s['controls']}", f"wrote {args.out}"])
        return 0
    if args.cases is None:
        raise CLIError("give --cases (or --rescore)")
    check_effects(args.effects, "fe")
    check_output_dir(args.out)
    s = run_benchmark(args.cases, args.seed, args.out, refinement=args.refinement,
                      truth_refinement=args.truth_refinement,
                      correction_refinement=args.refinement + 1, effects=args.effects,
                      cycles=args.cycles, increment=args.increment, progress=True)
    if MPI.COMM_WORLD.rank == 0:
        say([f"cases {s['cases']}, accuracy {s['accuracy']:.3f}, false alarms "
             f"{s['false_alarms_on_controls']}/{s['controls']}, median RMS after/noise "
             f"{s['rms_after_over_noise_median']:.2f}", f"wrote {args.out}"])
    return 0


def _run_open(args) -> int:
    from mpi4py import MPI

    from brain_fe.io import check_output_dir
    from diagnosis.open_benchmark import rescore_open, run_open_benchmark

    if args.rescore:
        s = rescore_open(args.out)
    else:
        if args.cases is None:
            raise CLIError("give --cases (or --rescore)")
        for flag, given in (("--effects", args.effects), ("--truth-refinement",
                                                          args.truth_refinement != 3),
                            ("--cycles", args.cycles != 2), ("--increment",
                                                             args.increment != 0.03)):
            if given:
                raise CLIError(f"{flag} belongs to the closed world (the open world draws "
                               "its specimens, protocols and effects)")
        check_output_dir(args.out)
        s = run_open_benchmark(args.cases, args.seed, args.out, refinement=args.refinement,
                               progress=True)
    if MPI.COMM_WORLD.rank == 0:
        c, si, p, o = s["control"], s["single"], s["pair"], s["outside"]
        say([f"cases {s['cases']}: controls {c['cases'] - c['false_alarms']}/{c['cases']} "
             f"none, singles {si['correct']}/{si['cases']}, pairs {p['correct']}/"
             f"{p['cases']}, outside unexplained {o['correct']}/{o['cases']}",
             f"wrote {args.out}"])
    return 0
