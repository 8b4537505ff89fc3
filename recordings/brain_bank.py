"""A synthetic "virtual brain bank": recordings made by the project's own FE model.

Clearly labelled synthetic. Eight regions, several brains, one specimen per brain and
region (some missing, as after failed tests), specimen geometry varying around R = 4 mm,
H = 5 mm, compression/tension (0.15) and torsion (0.15, 0.30) with loading and unloading
branches and noise; a composition table of 11 components for the first brains, with some
specimens only in one of the two tables (the paper's Figure 3); region-averaged curves;
and the ground truth in its own file (``truth.json``), which the pipeline never reads.

Planted structure (the generator's only assumptions, recorded in ``truth.json``):
region composition z-scores z_rc ~ N(0, 1); relative concentrations exp(0.3 z) times
specimen noise; ln mu_r = ln mu0 + sum_c b_c z_rc + N(0, sd), alpha_r = alpha0 +
sum_c a_c z_rc + N(0, sd); specimens scatter around their region.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd

from brain_fe.io import staged_directory, write_json_atomic
from brain_fe.parallel import Progress

log = logging.getLogger(__name__)

REGIONS = {"Am": "amygdala", "BG": "basal ganglia", "CC": "corpus callosum",
           "Cb": "cerebellum", "CR": "corona radiata", "Cx": "cortex", "Hi": "hippocampus",
           "Th": "thalamus"}
COMPONENTS = ("Iba1", "GFAP", "NeuN", "MBP", "Col_I", "Col_III", "Col_IV", "Col_VI", "HA",
              "FN", "Laminin")


@dataclass(frozen=True)
class BankSpec:
    """Design of the virtual brain bank (units: kPa, mm)."""

    seed: int = 2024
    n_brains: int = 6
    elisa_brains: int = 4  # brains 1..elisa_brains also have composition data
    regions: tuple[str, ...] = tuple(REGIONS)
    mu0_kPa: float = 0.8
    alpha0: float = -18.0
    mu_effects: dict = field(default_factory=lambda: {"Iba1": 0.30, "Col_VI": 0.22,
                                                      "GFAP": 0.18, "Col_IV": -0.18})
    alpha_effects: dict = field(default_factory=lambda: {"HA": 3.0, "FN": -2.0})
    region_sd_ln_mu: float = 0.05
    region_sd_alpha: float = 1.0
    specimen_sd_ln_mu: float = 0.08
    specimen_sd_alpha: float = 1.5
    radius_sd_mm: float = 0.15
    height_sd_mm: float = 0.3
    noise: float = 0.015  # of each channel's peak, per recorded point
    p_missing_mechanics: float = 0.1  # ELISA specimens without mechanics (failed tests)
    p_missing_elisa: float = 0.1  # mechanics specimens of ELISA brains without an assay
    nu0: float = 0.49
    refinement: int | None = None


def _tables(spec: BankSpec):
    rng = np.random.default_rng(spec.seed)
    regions = list(spec.regions)
    z = pd.DataFrame(rng.normal(size=(len(regions), len(COMPONENTS))), index=regions,
                     columns=COMPONENTS)
    ln_mu = (np.log(spec.mu0_kPa) + sum(b * z[c] for c, b in spec.mu_effects.items())
             + rng.normal(0, spec.region_sd_ln_mu, len(regions)))
    alpha = (spec.alpha0 + sum(a * z[c] for c, a in spec.alpha_effects.items())
             + rng.normal(0, spec.region_sd_alpha, len(regions)))
    region_truth = pd.DataFrame({"region": regions, "mu_kPa": np.exp(ln_mu),
                                 "alpha": np.asarray(alpha)})
    mech, comp, truth = [], [], []
    for b in range(1, spec.n_brains + 1):
        for r in regions:
            sid = f"B{b}-{r}"
            has_elisa = b <= spec.elisa_brains
            mech_ok = not (has_elisa and rng.random() < spec.p_missing_mechanics)
            elisa_ok = has_elisa and (not mech_ok or rng.random() >= spec.p_missing_elisa)
            rt = region_truth.set_index("region").loc[r]
            mu = float(rt.mu_kPa * np.exp(rng.normal(0, spec.specimen_sd_ln_mu)))
            al = float(min(rt.alpha + rng.normal(0, spec.specimen_sd_alpha), -2.0))
            if mech_ok:
                mech.append({"specimen": sid, "region": r, "brain": f"B{b}",
                             "radius_mm": round(4.0 + rng.normal(0, spec.radius_sd_mm), 3),
                             "height_mm": round(5.0 + rng.normal(0, spec.height_sd_mm), 3)})
                truth.append({"specimen": sid, "region": r, "mu_kPa": mu, "alpha": al})
            if elisa_ok:
                conc = np.exp(0.3 * z.loc[r].to_numpy() + rng.normal(0, 0.1, len(COMPONENTS)))
                comp.append({"specimen": sid, "region": r, "brain": f"B{b}",
                             **dict(zip(COMPONENTS, np.round(conc, 5), strict=True))})
    return (pd.DataFrame(mech), pd.DataFrame(comp), pd.DataFrame(truth), region_truth, z)


def region_average_curves(recordings: pd.DataFrame, specimens: pd.DataFrame,
                          radius_mm: float = 4.0) -> pd.DataFrame:
    """Average the recorded curves of each region point by point (same protocol grid), as
    the paper's region-wise curves. Geometry-normalised quantities are averaged (nominal
    stress, torque-derived shear stress, axial force per pi R^2) and returned for the
    nominal radius; the "specimen" of an averaged curve is its region."""
    from brain_fe.vocabulary import shear_stress_kPa, torque_mNmm

    geo = specimens.set_index("specimen")
    R = recordings.specimen.map(geo.radius_mm).to_numpy(float)
    rec = recordings.assign(region=recordings.specimen.map(geo.region),
                            tau=shear_stress_kPa(recordings.torque_mNmm, R),
                            fz=recordings.axial_force_mN / (np.pi * R**2),
                            point=recordings.groupby(["specimen", "test", "amplitude"])
                            .cumcount())
    keys = ["region", "test", "amplitude", "point"]
    first = rec.groupby(keys, sort=True)[["cycle", "branch", "time_s", "stretch", "shear"]].first()
    mean = rec.groupby(keys, sort=True)[["nominal_stress_kPa", "tau", "fz"]].mean()
    out = first.join(mean).reset_index()
    out["torque_mNmm"] = torque_mNmm(out.tau, radius_mm)
    out["axial_force_mN"] = out.fz * np.pi * radius_mm**2
    out = out.rename(columns={"region": "specimen"})
    return out[["specimen", "test", "amplitude", "cycle", "branch", "time_s", "stretch",
                "shear", "nominal_stress_kPa", "torque_mNmm", "axial_force_mN"]]


def make_brain_bank(out_dir: str, spec: BankSpec = BankSpec(), *,
                    progress: bool = False) -> dict:
    """Generate every table of the bank into ``out_dir`` (atomically, after all solves)."""
    from brain_fe.io import write_table_atomic

    from .synthetic import make_recordings

    mech, comp, truth, region_truth, z = _tables(spec)
    cache: dict = {}
    parts = []
    with Progress(len(mech), "virtual brain bank", "specimen", enabled=progress) as bar:
        for i in range(len(mech)):
            parts.append(make_recordings(mech.iloc[[i]], truth, noise=spec.noise,
                                         seed=spec.seed * 1000 + i, nu0=spec.nu0,
                                         refinement=spec.refinement, model_cache=cache))
            bar.update()
    rec = pd.concat(parts, ignore_index=True)
    regions = pd.DataFrame({"specimen": list(spec.regions), "region": list(spec.regions),
                            "brain": "average", "radius_mm": 4.0, "height_mm": 5.0})
    with staged_directory(out_dir) as stage:
        files = {"specimens.csv": mech, "recordings.csv": rec, "composition.csv": comp,
                 "regions.csv": regions,
                 "recordings_regions.csv": region_average_curves(rec, mech)}
        for name, df in files.items():
            write_table_atomic(df, stage / name)
        both = sorted(set(mech.specimen) & set(comp.specimen))
        summary = {"synthetic": True, "generator": "recordings.brain_bank.make_brain_bank",
                   "command": f"brainmech make-brain-bank --seed {spec.seed} --out {out_dir}",
                   "spec": {k: v for k, v in asdict(spec).items()},
                   "counts": {"mechanics": len(mech), "composition": len(comp),
                              "both": len(both), "regions": len(spec.regions)}}
        truth_doc = {**summary, "region_truth": region_truth.to_dict("records"),
                     "specimen_truth": truth.to_dict("records"),
                     "composition_z": z.reset_index(names="region").to_dict("records")}
        write_json_atomic(stage / "truth.json", truth_doc, indent=1)
    log.info("virtual brain bank in %s: %s", out_dir, summary["counts"])
    return summary
