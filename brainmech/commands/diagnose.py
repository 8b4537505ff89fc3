"""``brainmech diagnose``: locate the mismatch, name the missing physics, model it."""

from __future__ import annotations

from .. import args as a
from ..errors import CLIError, say


def add(sub) -> None:
    p = sub.add_parser(
        "diagnose", help="locate the mismatch, name the missing physics, model it",
        description="Fit the base model, locate where the misfit is systematic, fit every "
        "candidate physics extension (FE in the loop), rank them by BIC and likelihood-ratio "
        "tests and refit with the winner. Writes DIR/diagnosis.json, DIR/report.md and "
        "figures. Run under `mpirun -n K` to share the work among K ranks. "
        "With --budday the homogeneous analytical model is the base and the averaged "
        "human-brain curves of Budday et al. (2017) are diagnosed region by region.")
    p.add_argument("--recordings", default=None, help="recordings table (CSV or Parquet)")
    p.add_argument("--specimens", default=None, help="specimens table (CSV or Parquet)")
    p.add_argument("--specimen", default=None, help="diagnose only this specimen")
    p.add_argument("--base", choices=["one-term-ogden", "homogeneous-ogden"],
                   default="one-term-ogden")
    p.add_argument("--budday", nargs="?", const="", default=None, metavar="CSV",
                   help="diagnose the Budday 2017 averaged curves (default path: "
                   "../shared/data/budday2017/budday2017_averaged.csv)")
    p.add_argument("--effects", type=a.names, default=None,
                   help="comma list of candidate effects (default: all the base can express)")
    p.add_argument("--refinement", type=a.count(1), default=1,
                   help="working mesh level; k+1 corrects its discretisation error")
    p.add_argument("--nu0", type=a.finite, default=0.49, help="assumed initial Poisson ratio")
    p.add_argument("--noise", type=a.noise_option, default=None,
                   metavar="CH=SD,... | noise.json",
                   help="the instrument's white noise per channel, e.g. stress=0.005,"
                   "torque=0.02,axial_force=0.3 (kPa, mN mm, mN), or per specimen from a "
                   "JSON file {specimen: {CH: SD}} (the noise.json of `brainmech import`); "
                   "held fixed while wander and drift are still fitted (default: estimated "
                   "from the recordings)")
    p.add_argument("--check-digits", action="store_true",
                   help="diagnose every specimen a second time with its recorded numbers "
                   "changed in their last digits (relative 4e-16); a verdict that moves is "
                   "reported as cannot tell: not determined by the recordings (twice the "
                   "time)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(run=run)


def run(args) -> int:
    from mpi4py import MPI

    from brain_fe.io import check_output_dir
    from diagnosis.effects import check_effects

    check_output_dir(args.out)
    if args.budday is not None or args.base == "homogeneous-ogden":
        from diagnosis.budday import diagnose_budday

        if args.recordings:
            raise CLIError("the homogeneous base model reads --budday data, not --recordings")
        check_effects(args.effects, "cube")
        if args.noise:
            raise CLIError("--noise applies to --recordings (the Budday curves are averages)")
        if args.check_digits:
            raise CLIError("--check-digits applies to --recordings")
        res = diagnose_budday(args.budday or None, args.out, nu0=args.nu0)
        say([f"{r}: verdict {v['verdict']}, RMS/noise {v['rms_before']:.2f} -> "
             f"{v['rms_after']:.2f}" for r, v in res.items()] + [f"wrote {args.out}"])
        return 0
    from diagnosis.batch import diagnose_recordings

    if not args.recordings or not args.specimens:
        raise CLIError("give --recordings and --specimens (or --budday)")
    check_effects(args.effects, "fe")
    res = diagnose_recordings(args.recordings, args.specimens, args.out,
                              specimen=args.specimen, refinement=args.refinement,
                              effects=args.effects, nu0=args.nu0, noise=args.noise,
                              check_digits=args.check_digits, progress=True)
    if MPI.COMM_WORLD.rank == 0:
        say([f"{n}: not diagnosed: {r['error']}" if "error" in r else
             f"{n}: verdict {r['verdict']}, RMS/noise {r['rms_before']:.2f} -> "
             f"{r['rms_after']:.2f} ({'reused' if r['reused'] else 'diagnosed in this run'})"
             for n, r in res.items()] + [f"wrote {args.out}"])
    return 0
