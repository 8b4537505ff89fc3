"""``brainmech simulate``: one test protocol on the FE model, written as a CSV."""

from __future__ import annotations

import logging
import sys

from .. import args as a
from ..errors import CLIError

log = logging.getLogger("brainmech")


def add(sub) -> None:
    p = sub.add_parser(
        "simulate", help="run one test protocol on the FE model and write a CSV",
        description="Displacement-controlled compression/tension (1 -> 1-A -> 1 -> 1+A -> 1) "
        "or torsion (0 -> A -> 0, height fixed) of a glued cylinder with a compressible "
        "N-term Ogden material. Units: mm, kPa, mN, mN mm, s.")
    a.accept_negative_lists(p)
    p.add_argument("--model", choices=["axisymmetric", "3d"], default="axisymmetric")
    p.add_argument("--test", choices=["compression_tension", "torsion"],
                   default="compression_tension")
    p.add_argument("--amplitude", type=a.positive, default=None,
                   help="stretch amplitude A (default 0.15) or maximum amount of shear "
                   "(default 0.30)")
    p.add_argument("--mu", type=a.floats, default=(1.0,),
                   help="shear modulus per Ogden term, kPa, comma list (default 1.0)")
    p.add_argument("--alpha", type=a.floats, default=(-20.0,),
                   help="Ogden exponent per term, comma list (default -20)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--kappa", type=a.positive, default=None, help="bulk modulus, kPa")
    g.add_argument("--nu0", type=a.finite, default=None,
                   help="initial Poisson ratio (default 0.49); kappa = 2 mu (1+nu0)/(3(1-2 nu0))")
    p.add_argument("--volumetric", choices=["quadratic", "log"], default="quadratic",
                   help="U(J): quadratic kappa/2 (J-1)^2 (default) or log "
                   "kappa/4 (J^2-1-2 ln J)")
    p.add_argument("--radius-mm", type=a.positive, default=4.0)
    p.add_argument("--height-mm", type=a.positive, default=5.0)
    p.add_argument("--ends", choices=["glued", "slip", "springs", "unglued"], default="glued",
                   help="glued plates (default), frictionless (slip), a compliant glue "
                   "layer (springs: give --k-r and --k-theta) or rough plates without glue "
                   "that lift off instead of pulling (unglued)")
    p.add_argument("--refinement", type=a.count(1), default=None,
                   help="mesh refinement level k (default: the level with <= 1 %% force "
                   "error, see BENCHMARKS.md)")
    p.add_argument("--rate", type=a.positive, default=0.01,
                   help="rate of the controlled quantity, 1/s (default 0.01)")
    p.add_argument("--cycles", type=a.count(1), default=1)
    p.add_argument("--hold", type=a.non_negative, default=0.0, metavar="S",
                   help="dwell after every branch, s (relaxation; default 0)")
    x = p.add_argument_group("physics extensions (docs/physics.md); defaults are neutral")
    x.add_argument("--maxwell-beta", type=a.floats, default=(), metavar="LIST",
                   help="relative stiffness beta_i >= 0 of each Maxwell branch")
    x.add_argument("--maxwell-tau", type=a.floats, default=(), metavar="LIST",
                   help="relaxation time tau_i > 0 of each Maxwell branch, s")
    x.add_argument("--softening", type=a.finite, default=0.0, metavar="D",
                   help="Ogden-Roxburgh softening d = 1/r in [0, 1) (Mullins effect)")
    x.add_argument("--softening-m", type=a.positive, default=0.05, metavar="KPA",
                   help="Ogden-Roxburgh energy scale m, kPa (default 0.05)")
    x.add_argument("--k-r", type=a.non_negative, default=None, metavar="KPA_MM",
                   help="radial stiffness per area of the glue layer (--ends springs)")
    x.add_argument("--k-theta", type=a.non_negative, default=None, metavar="KPA_MM",
                   help="circumferential stiffness per area of the glue layer")
    m = p.add_argument_group("measurement artefacts (true = nominal x (1 + e)); default 0")
    m.add_argument("--height-rel", type=a.finite, default=0.0, metavar="E")
    m.add_argument("--radius-rel", type=a.finite, default=0.0, metavar="E")
    m.add_argument("--stretch-offset", type=a.finite, default=0.0, metavar="S",
                   help="contact-point zero offset: true stretch = recorded + S")
    m.add_argument("--force-offset", type=a.finite, default=0.0, metavar="MN")
    m.add_argument("--torque-offset", type=a.finite, default=0.0, metavar="MNMM")
    p.add_argument("--sensitivities", action="store_true",
                   help="add d_<column>/d_<parameter> columns for every model parameter")
    p.add_argument("--out", default=None, help="CSV file (default: print to stdout)")
    p.add_argument("--fields", default=None,
                   help="XDMF file for the displacement field per step (ParaView)")
    p.set_defaults(run=run)


def run(args) -> int:
    from mpi4py import MPI

    from brain_fe import api
    from brain_fe.io import check_output_file

    if args.out:
        check_output_file(args.out, suffixes=(".csv",))
    if args.fields:
        check_output_file(args.fields, suffixes=(".xdmf",))
    if (args.k_r is None) != (args.k_theta is None):
        raise CLIError("give both --k-r and --k-theta")
    springs = args.k_r is not None
    if springs != (args.ends == "springs"):
        raise CLIError("--ends springs needs --k-r and --k-theta (kPa/mm), and they need "
                       "--ends springs")
    nu0 = args.nu0 if args.nu0 is not None else (None if args.kappa else 0.49)
    df = api.simulate(model=args.model, test=args.test, amplitude=args.amplitude, mu=args.mu,
                      alpha=args.alpha, kappa=args.kappa, nu0=nu0,
                      volumetric=args.volumetric, radius_mm=args.radius_mm,
                      height_mm=args.height_mm, ends=args.ends, refinement=args.refinement,
                      rate_per_s=args.rate, cycles=args.cycles, hold_s=args.hold,
                      field_output=args.fields, progress=True,
                      sensitivities=args.sensitivities,
                      physics=dict(beta=args.maxwell_beta, tau_s=args.maxwell_tau,
                                   softening=args.softening,
                                   softening_m_kPa=args.softening_m),
                      interface=(args.k_r, args.k_theta) if springs else None,
                      artefacts=dict(height_rel=args.height_rel, radius_rel=args.radius_rel,
                                     stretch_offset=args.stretch_offset,
                                     force_offset_mN=args.force_offset,
                                     torque_offset_mNmm=args.torque_offset))
    if args.out:
        api.write_csv(df, args.out)
        log.info("wrote %s (%d rows)", args.out, len(df))
    elif MPI.COMM_WORLD.rank == 0:
        sys.stdout.write(df.to_csv(index=False, float_format="%.10g"))
    return 0
