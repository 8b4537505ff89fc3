"""``brainmech sample``: FE samples over a parameter design (parallel, resumable)."""

from __future__ import annotations

from .. import args as a
from ..errors import say


def add(sub) -> None:
    p = sub.add_parser(
        "sample", help="generate FE samples over a parameter design (parallel, resumable)",
        description="Solve the forward model for n parameter sets (mu log-uniform, alpha "
        "uniform) and store the results in DIR (manifest.json + Parquet chunks). Run as "
        "`mpirun -n K brainmech sample ...`: every rank solves its own share on "
        "MPI.COMM_SELF. Re-running the same command resumes: it computes only the missing "
        "samples.")
    a.accept_negative_lists(p)
    p.add_argument("--n", type=a.count(1), required=True, help="number of parameter sets")
    p.add_argument("--seed", type=a.count(0), default=0)
    p.add_argument("--design", choices=["sobol", "lhs"], default="sobol")
    p.add_argument("--mu-range", type=a.interval, default=(0.1, 5.0),
                   help="mu range in kPa, log-uniform (default 0.1,5)")
    p.add_argument("--alpha-range", type=a.interval, default=(-40.0, -2.0),
                   help="alpha range, uniform, not containing 0 (default -40,-2)")
    p.add_argument("--nu0", type=a.finite, default=0.49, help="initial Poisson ratio (0.49)")
    p.add_argument("--tests", default="compression_tension,torsion:0.15,torsion:0.30",
                   help="comma list of test[:amplitude] (default "
                   "compression_tension,torsion:0.15,torsion:0.30)")
    p.add_argument("--model", choices=["axisymmetric", "3d"], default="axisymmetric")
    p.add_argument("--refinement", type=a.count(1), default=None,
                   help="mesh refinement level k (default: the model's default)")
    p.add_argument("--radius-mm", type=a.positive, default=4.0)
    p.add_argument("--height-mm", type=a.positive, default=5.0)
    p.add_argument("--ends", choices=["glued", "slip"], default="glued",
                   help="glued plates (default) or frictionless (slip)")
    p.add_argument("--volumetric", choices=["quadratic", "log"], default="quadratic")
    p.add_argument("--chunk-size", type=a.count(1), default=1,
                   help="samples per Parquet chunk and rank (default 1: a kill loses at "
                   "most the sample in progress; each run merges its chunks at the end)")
    p.add_argument("--out", required=True, metavar="DIR", help="store directory")
    p.set_defaults(run=run)


def run(args) -> int:
    from mpi4py import MPI

    from brain_fe import sampling
    from brain_fe.io import check_output_dir

    comm = MPI.COMM_WORLD
    try:
        spec = sampling.SampleSpec(
            n=args.n, seed=args.seed, design=args.design, mu_range=args.mu_range,
            alpha_range=args.alpha_range, nu0=args.nu0, tests=args.tests, model=args.model,
            radius_mm=args.radius_mm, height_mm=args.height_mm, refinement=args.refinement,
            ends=args.ends, volumetric=args.volumetric)
        check_output_dir(args.out)
        summary = sampling.run_sampling(spec, args.out, comm=comm, chunk_size=args.chunk_size)
    except (ValueError, OSError):
        if comm.rank != 0:  # every rank raises the same error; rank 0 reports it once
            return 1
        raise
    if comm.rank == 0:
        lines = [f"{args.out}: {summary.line()}; computed {summary.computed} in this run"]
        lines += [f"  failed: sample {s} {t}: {r}" for s, t, r in summary.failures[:10]]
        if len(summary.failures) > 10:
            lines.append(f"  ... {len(summary.failures) - 10} more failed tests")
        say(lines)
    return 0
