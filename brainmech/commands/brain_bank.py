"""``brainmech make-brain-bank``: the synthetic virtual brain bank."""

from __future__ import annotations

from .. import args as a
from ..errors import CLIError, say


def add(sub) -> None:
    p = sub.add_parser(
        "make-brain-bank", help="generate the synthetic virtual brain bank (FE recordings)",
        description="Synthetic data made by the project's own FE model: 8 regions, several "
        "brains, specimen geometry around R = 4 mm, H = 5 mm, compression/tension and "
        "torsion (0.15, 0.30) recordings with noise, a composition table of 11 components "
        "with partial overlap, region-averaged curves, and truth.json (never read by the "
        "pipeline).")
    p.add_argument("--seed", type=a.count(0), default=2024)
    p.add_argument("--brains", type=a.count(1), default=6)
    p.add_argument("--elisa-brains", type=a.count(0), default=4)
    p.add_argument("--refinement", type=a.count(1), default=None)
    p.add_argument("--out", required=True, metavar="DIR")
    p.set_defaults(run=run)


def run(args) -> int:
    from brain_fe.io import check_output_dir
    from recordings.brain_bank import BankSpec, make_brain_bank

    if not args.elisa_brains <= args.brains:
        raise CLIError("need --elisa-brains <= --brains")
    check_output_dir(args.out)
    s = make_brain_bank(args.out, BankSpec(seed=args.seed, n_brains=args.brains,
                                           elisa_brains=args.elisa_brains,
                                           refinement=args.refinement), progress=True)
    say([f"{args.out}: synthetic brain bank {s['counts']}"])
    return 0
