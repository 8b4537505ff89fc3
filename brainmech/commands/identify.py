"""``brainmech identify``: two-stage identification of (mu, alpha)."""

from __future__ import annotations

from .. import args as a
from ..errors import say


def add(sub) -> None:
    p = sub.add_parser(
        "identify", help="two-stage identification of (mu, alpha): surrogate, then FE",
        description="For every specimen (or region-averaged curve) of the recordings: "
        "stage 1 minimises the normalised stress error (Gavrus) on the surrogates, stage 2 "
        "restarts from that optimum with the FE model and its exact sensitivities "
        "(trust-region least squares). Writes DIR/parameters.csv, DIR/history.csv and "
        "DIR/figures/.")
    p.add_argument("--recordings", required=True, metavar="FILE", help="CSV or Parquet")
    p.add_argument("--specimens", required=True, metavar="FILE", help="CSV or Parquet")
    p.add_argument("--surrogates", required=True, metavar="MODEL_DIR")
    p.add_argument("--fit", choices=["compression_tension", "all", "both"], default="all",
                   help="tests used: compression/tension only, all tests, or both fits")
    p.add_argument("--refinement", type=a.count(1), default=None, help="FE mesh level "
                   "(default: the <= 1 %% error level)")
    p.add_argument("--strict-surrogates", action="store_true",
                   help="refuse surrogates trained for another specimen geometry (default: "
                   "use them for the stage-1 start with a warning)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.set_defaults(run=run)


def run(args) -> int:
    from brain_fe.io import check_output_dir
    from identification.batch import identify_all

    check_output_dir(args.out)
    fits = ("compression_tension", "all") if args.fit == "both" else (args.fit,)
    table = identify_all(args.recordings, args.specimens, args.surrogates, args.out,
                         fits=fits, refinement=args.refinement,
                         surrogate_mismatch="error" if args.strict_surrogates else "warn",
                         progress=True)
    first = "region" if "region" in table and "specimen" not in table else "specimen"
    lines = [f"{args.out}/parameters.csv: {len(table)} fits"]
    for r in table.itertuples(index=False):
        d = r._asdict()
        lines.append(f"  {d[first]} [{d['fit']}]: mu = {d['mu_kPa']:.4g} +- "
                     f"{d['mu_se_kPa']:.2g} kPa, alpha = {d['alpha']:.4g} +- "
                     f"{d['alpha_se']:.2g}, objective {d['objective']:.3g}, "
                     f"{d['fe_solves']} FE solves")
    say(lines)
    return 0
