"""Blind benchmark: synthetic specimens, each with one concealed effect (or none).

Every case draws random base parameters (mu log-uniform in [0.5, 2] kPa, alpha uniform in
[-25, -8], nu0 = 0.49 assumed) and one effect of the library (controls: none). The effect
size is calibrated so that the best base fit to the noiseless recordings leaves a misfit of
about ``target`` (default 3.5, accepted 2-5) noise standard deviations RMS: concealed, not
obvious by eye. Recordings come from a finer mesh than the diagnosis uses
(``truth_refinement``), with 1 % Gaussian noise (of each channel's peak). The labels are
written apart (``labels.json``) and the diagnosis never sees them.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from mpi4py import MPI

from brain_fe import geometry as geo
from brain_fe.io import write_json_atomic, write_text_atomic
from brain_fe.logs import rank_local
from brain_fe.materials import MaterialModel
from brain_fe.model import ForwardModel
from brain_fe.parallel import SharedCounter, as_progress, dynamic_items, gather_all
from brain_fe.parameters import Param
from brain_fe.protocols import compression_tension, torsion
from brain_fe.solver import ConvergenceError
from recordings.observations import observations, peak_per_series
from recordings.synthetic import record
from recordings.tables import read_recordings, read_specimens
from simulators.coordinates import model_point
from simulators.fe import FESimulator

from .effects import BASE_NAMES, EFFECTS
from .engine import ENGINE_VERSION, diagnose
from .fitting import fit

log = logging.getLogger(__name__)
CLASSES = tuple(EFFECTS) + ("none",)


def full_protocols(cycles: int = 2, increment: float = 0.03):
    """Compression/tension 0.15 and torsion 0.15, 0.30, ``cycles`` cycles each, every ramp
    sampled with the same number of points (``0.15 / increment``): the noise estimate
    needs several points per ramp in every channel."""
    return [compression_tension(0.15, cycles=cycles, max_increment=increment),
            torsion(0.15, cycles=cycles, max_increment=0.15 * increment / 0.15),
            torsion(0.30, cycles=cycles, max_increment=0.30 * increment / 0.15)]


# Largest effect size the calibration may reach: realistic materials and test set-ups
# (two-term mu_1 <= mu_0, Maxwell beta <= 3, softening d <= 0.9, nu0 >= 0.24, interface
# k >= k_shape / 30, contact-point offset <= 3 % stretch).
MAX_SIZE = {"viscoelastic": 10.0, "mullins": 3.0, "ogden_2term": 10.0,
            "compressibility": 8.33, "imperfect_gluing": 30.0, "artefacts": 7.5}


def effect_values(effect: str, size: float, shape: dict) -> dict:
    """Extra parameter values of ``effect`` at scalar ``size`` (0 = neutral)."""
    if effect == "viscoelastic":
        v = {"beta_0": size * 0.3, "log10_tau_0": shape["log10_tau"]}
    elif effect == "mullins":
        v = {"softening": min(size * 0.3, 0.9), "log10_softening_m": shape["log10_m"]}
    elif effect == "ogden_2term":
        v = {"mu_1": size * 0.1 * shape["mu"], "alpha_1": shape["alpha_1"]}
    elif effect == "compressibility":
        v = {"nu0": 0.49 - min(size * 0.03, 0.25)}
    elif effect == "imperfect_gluing":
        v = {"log10_k": math.log10(shape["k"] / max(size, 1e-6))}
    elif effect == "artefacts":
        v = {"stretch_offset": size * shape["offset"], "force_offset": 0.0,
             "torque_offset": 0.0}
    else:
        v = {}
    return {Param.parse(k): x for k, x in v.items()}


def _shape(effect, rng, mu):
    return {"log10_tau": rng.uniform(0.5, 1.5), "log10_m": rng.uniform(-2.0, -1.3),
            "mu": mu, "alpha_1": rng.choice([-1, 1]) * rng.uniform(8, 15),
            "k": 10 ** rng.uniform(0.5, 1.0), "offset": rng.choice([-1, 1]) * 0.004}


@dataclass
class Case:
    name: str
    effect: str
    values: dict
    size: float
    base_misfit: float  # RMS of the best base fit to the noiseless data, in noise units


def _recordings(values, protocols, geometry_truth, name, noise, rng, nu0=0.49):
    """Recordings of the full protocol from the truth model (finer mesh)."""
    pt = model_point(values, nu0)
    ph = pt.physics
    material = MaterialModel.build(ph.n_terms, maxwell=ph.maxwell, softening=ph.softening,
                                   laws=ph.laws)  # an effect built on a further law too
    fm = ForwardModel(geometry_truth, material, ends="springs" if ph.springs else "glued")
    return record(fm, pt.material, protocols, name, noise=noise, rng=rng,
                  artefacts=pt.artefacts, interface=pt.interface)


def make_case(i: int, effect: str, rng, *, refinement: int, truth_refinement: int,
              protocols, target: float = 3.5, noise: float = 0.01, models: dict):
    """One calibrated case: (recordings, specimens row, Case label)."""
    name = f"case{i:03d}"
    mu = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
    base = {Param("mu", 0): mu, Param("alpha", 0): float(rng.uniform(-25, -8))}
    shape = _shape(effect, rng, mu)
    g_truth = models.setdefault(("g", truth_refinement),
                                geo.make("axisymmetric", 4.0, 5.0, truth_refinement,
                                         comm=MPI.COMM_SELF))
    size, misfit = 0.0, 0.0
    for draw in range(3 if effect != "none" else 0):
        if draw:  # this shape could not be made visible within the size caps: draw another
            log.info("%s %s: misfit %.2f out of range, drawing a new effect shape", name,
                     effect, misfit)
            shape = _shape(effect, rng, mu)
        size = 1.0
        for attempt in range(4):  # calibrate the size: misfit ~ linear in size when small
            values = {**base, **effect_values(effect, size, shape)}
            clean = _recordings(values, protocols, g_truth, name, 0.0, rng)
            obs = observations(clean)
            sim = FESimulator(obs, 4.0, 5.0, refinement=refinement)
            fine = FESimulator(obs, 4.0, 5.0, refinement=truth_refinement)
            y_f, _ = fine.predict(base, [])
            y_c, _ = sim.predict(base, [])
            sim.correction = y_f - y_c
            sigma = noise * peak_per_series(obs)
            f = fit(sim, obs, sigma, base, list(BASE_NAMES), max_nfev=30)
            misfit = float(np.sqrt(np.mean(f.z**2)))
            log.info("%s %s size %.3g: base misfit %.2f x noise", name, effect, size, misfit)
            if 2.5 <= misfit <= 4.5 or attempt == 3:
                break  # the size kept is the one whose misfit was measured
            new = min(size * float(np.clip(target / max(misfit, 1e-3), 0.1, 10.0)),
                      MAX_SIZE[effect])
            if new == size:
                break  # at the cap
            size = new
        if 2.5 <= misfit <= 4.5:
            break
    values = {**base, **effect_values(effect, size, shape)}
    rec = _recordings(values, protocols, g_truth, name, noise, rng)
    spec = pd.DataFrame({"specimen": [name], "region": ["synthetic"], "brain": ["B0"],
                         "radius_mm": [4.0], "height_mm": [5.0]})
    return rec, spec, Case(name, effect, {str(k): float(v) for k, v in values.items()}, size,
                           misfit)


def run_benchmark(n_cases: int, seed: int, out: str | Path, *, refinement: int = 1,
                  truth_refinement: int = 3, correction_refinement: int = 2,
                  controls: float = 0.25, effects=None, cycles: int = 2,
                  increment: float = 0.03, comm=MPI.COMM_WORLD, progress=None) -> dict:
    """Generate, diagnose blind and score ``n_cases`` cases; each case goes to whichever
    MPI rank is free (each works on MPI.COMM_SELF). Writes DIR/cases/ (recordings, specimens and
    each blind result), labels.json, results.json, summary.json and summary.md. Resumable:
    a case whose recordings come out identical to those already in DIR is not diagnosed
    again when the diagnosis settings (DIR/config.json) are unchanged."""
    out = Path(out)
    classes = list(effects or EFFECTS)
    n_ctrl = max(1, int(math.ceil(controls * n_cases)))
    labels = ["none"] * n_ctrl + [classes[i % len(classes)] for i in range(n_cases - n_ctrl)]
    rng = np.random.default_rng(seed)
    order = rng.permutation(n_cases)
    labels = [labels[i] for i in order]
    seeds = rng.integers(0, 2**31, size=n_cases)
    protocols = full_protocols(cycles, increment)
    mine = []
    models: dict = {}
    # what a diagnosis result depends on besides the recordings: earlier results are
    # reused only when it is unchanged
    config = {"refinement": refinement, "correction_refinement": correction_refinement,
              "effects": classes, "engine": ENGINE_VERSION}
    previous: dict = {}
    reusable = ((out / "config.json").exists()
                and json.loads((out / "config.json").read_text()) == config)
    if reusable and (out / "results.json").exists():
        previous = json.loads((out / "results.json").read_text())
    bar = as_progress(progress, None, "diagnosis benchmark (rank 0's cases)", "case", comm)
    if comm.rank == 0:
        (out / "cases").mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / "config.json", config, indent=1)
    comm.Barrier()
    counter = SharedCounter(comm)
    with rank_local():  # this rank's own cases: its warnings are said
        # each case to whichever rank is free (a case depends only on its seed and
        # index, not on the rank or the cases before it)
        for i in dynamic_items(range(n_cases), counter):
            case_rng = np.random.default_rng(seeds[i])
            for attempt in range(3):  # a truth the FE model cannot follow is drawn again
                try:
                    rec, spec, case = make_case(i, labels[i], case_rng, refinement=refinement,
                                                truth_refinement=truth_refinement,
                                                protocols=protocols, models=models)
                    break
                except ConvergenceError as exc:
                    if attempt == 2:
                        raise
                    log.warning("case%03d: truth draw %d not solvable (%s); drawing again", i,
                                attempt, exc)
            csv_path = out / "cases" / f"{case.name}_recordings.csv"
            result_path = out / "cases" / f"{case.name}_result.json"
            text = rec.to_csv(index=False)
            # resume: the diagnosis is deterministic, so identical recordings diagnosed
            # before (this case's result file, or the results.json of an earlier run of the
            # same benchmark) are not diagnosed again
            res = None
            if reusable and csv_path.exists() and csv_path.read_text() == text:
                if result_path.exists():
                    res = json.loads(result_path.read_text())
                elif case.name in previous:
                    res = previous[case.name]
            if res is not None:
                log.info("%s: recordings unchanged, diagnosis reused", case.name)
            write_text_atomic(csv_path, text)
            spec.to_csv(out / "cases" / f"{case.name}_specimens.csv", index=False)
            # --- blind: from here on only the recordings are used
            obs = observations(rec)
            if res is None:
                res = _diagnose_case(obs, refinement, correction_refinement, classes, case.name)
                write_json_atomic(result_path, res, indent=1)
            res.update(case=case.name)
            mine.append((case, res, _rms_over_true_noise(obs, res)))
            log.info("%s: truth %s, verdict %s (%.0f s)", case.name, case.effect, res["verdict"],
                     res["elapsed_s"])
            bar.update(1, f"{case.name} {case.effect} -> {res['verdict']}")
    bar.close()
    counter.free()
    allres = sorted(gather_all(comm, mine), key=lambda x: x[0].name)  # in case order
    summary = score([c for c, _, _ in allres], [r for _, r, _ in allres], classes,
                    [t for _, _, t in allres])
    if comm.rank == 0:
        labels_json = {c.name: {"effect": c.effect, "values": c.values, "size": c.size,
                                "base_misfit_over_noise": c.base_misfit} for c, _, _ in allres}
        write_json_atomic(out / "labels.json", labels_json, indent=1)
        write_json_atomic(out / "results.json", {r["case"]: r for _, r, _ in allres},
                          indent=1)
        write_json_atomic(out / "summary.json", summary, indent=1)
        write_text_atomic(out / "summary.md", summary_markdown(summary))
    return summary


def _nanstat(f, values) -> float:
    v = np.asarray(values or [], float)
    return float(f(v)) if len(v) and np.isfinite(v).any() else float("nan")


def summary_markdown(s: dict) -> str:
    """The benchmark's scores as Markdown: headline, confusion matrix, parameter recovery."""
    conf = s["confusion"]
    cols = [c for c in next(iter(conf.values())) if c != "error"
            or any(r.get("error", 0) for r in conf.values())]
    lines = ["# Blind diagnosis benchmark", "",
             f"- cases: {s['cases']} ({s['controls']} controls)",
             f"- correct attribution: {s['accuracy']:.1%}",
             f"- false alarms on controls: {s['false_alarms_on_controls']} of {s['controls']}",
             f"- residual RMS after modelling / noise: median "
             f"{s['rms_after_over_noise_median']:.2f}, max {s['rms_after_over_noise_max']:.2f}"
             f" ({s.get('rms_after_over_noise_above_1.2', 0)} cases above 1.2); against the "
             f"noise actually added: median {s.get('rms_after_over_true_noise_median', 0):.2f}"
             f", max {s.get('rms_after_over_true_noise_max', 0):.2f}",
             "- base misfit of the effect cases / noise: "
             + (f"{min(s['base_misfit_over_noise']):.2f}-{max(s['base_misfit_over_noise']):.2f}"
                if s["base_misfit_over_noise"] else "-"),
             f"- diagnosis time per case (median): {s['elapsed_s_per_case_median']:.0f} s", "",
             "Confusion matrix (rows: truth, columns: verdict)", "",
             "| truth \\ verdict | " + " | ".join(cols) + " |",
             "|---|" + "---|" * len(cols)]
    for truth, row in conf.items():
        if sum(row.values()):
            lines.append(f"| {truth} | " + " | ".join(str(row.get(c, 0)) for c in cols) + " |")
    rec = pd.DataFrame(s["parameter_recovery"])
    if len(rec):
        rec["error"] = rec["fitted"] - rec["truth"]
        lines += ["", "Effect-parameter recovery (correct verdicts)", "",
                  "| parameter | cases | median truth | median abs. error | max abs. error |",
                  "|---|---|---|---|---|"]
        for name, g in rec.groupby("parameter", sort=False):
            lines.append(f"| {name} | {len(g)} | {g['truth'].median():.3g} | "
                         f"{g['error'].abs().median():.3g} | {g['error'].abs().max():.3g} |")
    return "\n".join(lines) + "\n"


def _diagnose_case(obs, refinement, correction_refinement, classes, name) -> dict:
    """The blind diagnosis of one case's observations (a failure is scored, not fatal)."""
    sim = FESimulator(obs, 4.0, 5.0, refinement=refinement)
    fine = FESimulator(obs, 4.0, 5.0, refinement=correction_refinement)
    try:
        d = diagnose(sim, obs, fine_sim=fine, effects=classes)
    except RuntimeError as exc:
        log.error("%s: diagnosis failed: %s", name, exc)
        return {"verdict": "error", "error": str(exc), "rms_after": float("nan"),
                "refit_parameters": {}, "elapsed_s": float("nan")}
    return d.to_json()


def rms_over_true_noise(obs: pd.DataFrame, res: dict, sigma) -> float:
    """Residual RMS after modelling against the noise actually added, pooled over rows;
    ``sigma(channel, series)``: that noise's SD for one (curve, channel) series, the rows
    of ``obs`` (the benchmark knows it, the diagnosis estimates it)."""
    if "rms_by_curve_after" not in res:
        return float("nan")
    total, n = 0.0, 0
    for (c, ch), g in obs.groupby(["curve", "channel"], sort=False):
        sd = sigma(ch, g)
        total += len(g) * (res["rms_by_curve_after"][f"{c}/{ch}"]["rms"] / sd) ** 2
        n += len(g)
    return math.sqrt(total / n)


def _rms_over_true_noise(obs: pd.DataFrame, res: dict, noise: float = 0.01) -> float:
    """The closed benchmark's noise: ``noise`` times each channel's peak of ``obs``."""
    return rms_over_true_noise(obs, res,
                               lambda ch, g: noise * float(g["value"].abs().max()))


def _case_observations(out: Path, name: str) -> pd.DataFrame:
    """Observations of a case's recordings as stored in DIR/cases/."""
    cases = out / "cases"
    spec = read_specimens(cases / f"{name}_specimens.csv")
    return observations(read_recordings(cases / f"{name}_recordings.csv", spec))


def rescore(out: str | Path) -> dict:
    """Score an existing benchmark directory again (labels, blind results and recordings
    as written by :func:`run_benchmark`); rewrites summary.json and summary.md."""
    out = Path(out)
    need = [out / n for n in ("labels.json", "results.json", "config.json")]
    missing = [str(p) for p in need if not p.exists()]
    if missing:
        raise ValueError(f"{missing[0]}: not found (not a benchmark directory?)")
    labels = json.loads(need[0].read_text())
    results = json.loads(need[1].read_text())
    classes = json.loads(need[2].read_text())["effects"]
    names = sorted(labels)
    cases = [Case(n, labels[n]["effect"], labels[n]["values"], labels[n]["size"],
                  labels[n]["base_misfit_over_noise"]) for n in names]
    res = [dict(results[n], case=n) for n in names]
    summary = score(cases, res, classes, [_rms_over_true_noise(_case_observations(out, n), r)
                                          for n, r in zip(names, res, strict=True)])
    write_json_atomic(out / "summary.json", summary, indent=1)
    write_text_atomic(out / "summary.md", summary_markdown(summary))
    return summary


def score(cases, results, classes, rms_true=None) -> dict:
    """Confusion matrix, accuracy, false alarms, RMS ratio, effect-parameter recovery.
    ``rms_true``: per case, the RMS after modelling against the noise actually added."""
    names = list(classes) + ["none"]
    conf = pd.DataFrame(0, index=names, columns=names + ["error"])
    recovery = []
    for c, r in zip(cases, results, strict=True):
        if r["verdict"] not in conf.columns:  # a combination or `unexplained`
            conf[r["verdict"]] = 0
        conf.loc[c.effect, r["verdict"]] += 1
        if c.effect != "none" and r["verdict"] == c.effect:
            for n in map(str, EFFECTS[c.effect].names):
                if n in r["refit_parameters"] and abs(c.values.get(n, 0.0)) > 0:
                    recovery.append({"case": c.name, "parameter": n, "truth": c.values[n],
                                     "fitted": r["refit_parameters"][n]})
    correct = sum(conf.loc[n, n] for n in names)
    ctrl = [r for c, r in zip(cases, results, strict=True) if c.effect == "none"]
    ratio = [r["rms_after"] for r in results]
    return {
        "cases": len(cases),
        "accuracy": correct / max(len(cases), 1),
        "false_alarms_on_controls": sum(r["verdict"] != "none" for r in ctrl),
        "controls": len(ctrl),
        "confusion": {k: {kk: int(vv) for kk, vv in row.items()}
                      for k, row in conf.to_dict(orient="index").items()},
        "rms_after_over_noise_median": float(np.nanmedian(ratio)) if ratio else float("nan"),
        "rms_after_over_noise_max": float(np.nanmax(ratio)) if ratio else float("nan"),
        "rms_after_over_noise_above_1.2": int(np.sum(np.array(ratio) > 1.2)),
        "rms_after_over_true_noise_median": _nanstat(np.nanmedian, rms_true),
        "rms_after_over_true_noise_max": _nanstat(np.nanmax, rms_true),
        "base_misfit_over_noise": [c.base_misfit for c in cases if c.effect != "none"],
        "parameter_recovery": recovery,
        "elapsed_s_per_case_median": float(np.nanmedian([r["elapsed_s"] for r in results]))
        if results else float("nan"),
    }
