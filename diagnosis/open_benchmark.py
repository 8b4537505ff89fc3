"""Open-world benchmark: recordings the diagnosis did not make, scored blind.

Cases come in blocks of 20 (:data:`BLOCK`): 5 controls (rig noise of one kind each, in
turn white, low-pass filtered, wander, drift, quantised, all of them), 8 single library
effects (every class in turn), 4 pairs (:data:`diagnosis.open_world.PAIRS`; artefacts with
a random other) and 3 effects outside the library (:data:`diagnosis.open_world.OUTSIDE`).
The recordings are made by :mod:`diagnosis.open_world` (converged mesh, sub-stepped time
integration, the instrument's clock, rig noise); the labels are written apart
(``labels.json``) and the diagnosis sees the recordings and specimens tables only.

Case ``i`` depends on ``(seed, i)`` only, so a benchmark of 40 cases is the first 40 of
one of 120 with the same seed, and a run resumes where an earlier one stopped.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import pandas as pd
from mpi4py import MPI

from brain_fe.io import write_json_atomic, write_text_atomic
from brain_fe.logs import rank_local
from brain_fe.parallel import SharedCounter, as_progress, dynamic_items, gather_all
from brain_fe.solver import ConvergenceError
from brain_fe.vocabulary import TIME
from recordings.noise import RigNoise
from recordings.observations import observations
from recordings.tables import read_recordings, read_specimens
from simulators.fe import FESimulator

from .benchmark import rms_over_true_noise
from .effects import EFFECTS
from .engine import ENGINE_VERSION, diagnose
from .open_world import NOISE_KINDS, OUTSIDE, PAIRS, VISIBLE, make_case, noise_sd
from .selection import chi2_needed

log = logging.getLogger(__name__)

CONTROL_NOISE = tuple((k,) if k == "white" else ("white", k) for k in NOISE_KINDS) + (
    NOISE_KINDS,)
BLOCK = ["control"] * 5 + ["single"] * 8 + ["pair"] * 4 + ["outside"] * 3
KINDS = ("control", "single", "pair", "outside")


def plan(i: int, seed: int) -> tuple[str, list, tuple | None, np.random.Generator]:
    """Case ``i``: (kind, truth effects, noise kinds or None for a random mix, its rng)."""
    block, j = divmod(i, len(BLOCK))
    order = np.random.default_rng([seed, block]).permutation(len(BLOCK))
    slot = int(order[j])
    kind = BLOCK[slot]
    rank_in_kind = block * BLOCK.count(kind) + BLOCK[:slot].count(kind)
    rng = np.random.default_rng([seed, 1_000_003, i])
    effects: list = []
    noise = None
    if kind == "control":
        noise = CONTROL_NOISE[rank_in_kind % len(CONTROL_NOISE)]
    elif kind == "single":
        effects = [list(EFFECTS)[rank_in_kind % len(EFFECTS)]]
    elif kind == "pair":
        a, b = PAIRS[rank_in_kind % len(PAIRS)]
        if b is None:  # artefacts with any other
            b = str(rng.choice([e for e in EFFECTS if e != a]))
        effects = [a, b]
    else:
        effects = [OUTSIDE[rank_in_kind % len(OUTSIDE)]]
    return kind, effects, noise, rng


def draw_case(i: int, seed: int, models: dict):
    """Case ``i`` (recordings, specimens, WorldCase), or None when five truths in a row
    could not be followed by the converged model (reported in the summary, not scored)."""
    name = f"world{i:03d}"
    kind, effects, noise, rng = plan(i, seed)
    for attempt in range(5):  # a truth the FE model cannot follow is drawn again
        try:
            return make_case(name, kind, effects, rng, noise_kinds=noise, models=models)
        except ConvergenceError as exc:
            log.warning("%s: truth draw %d not solvable (%s); drawing again", name, attempt,
                        exc)
    log.error("%s: no solvable truth in 5 draws; case left out", name)
    return None


def _diagnose(obs, spec, refinement, name, noise: dict | None = None) -> dict:
    """The diagnosis of one case, blind; ``noise``: a stated noise per channel (its white
    SD, or all of it, as a lab that knows its instrument would give with ``--noise``),
    else estimated."""
    sim = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=refinement)
    fine = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=refinement + 1)
    try:
        return diagnose(sim, obs, fine_sim=fine, noise=noise).to_json()
    except RuntimeError as exc:
        log.error("%s: diagnosis failed: %s", name, exc)
        return {"verdict": "error", "effects": [], "status": "error", "error": str(exc),
                "rms_after": float("nan"), "elapsed_s": float("nan")}


def _rms_over_rig_noise(obs: pd.DataFrame, res: dict, noise: dict,
                        realised: dict | None = None) -> float:
    """The open world's noise: per series, the RMS of the noise actually added
    (``realised``, {curve/channel: RMS}, the label's ``noise_rms``), or for labels written
    before it was kept, the RMS the rig model puts in on average (its stationary part,
    rounding and the drift over the series' times, :meth:`RigNoise.series_sd`);
    ``noise``: channel -> :class:`RigNoise` or the label's dict of its fields."""
    rig = {ch: n if isinstance(n, RigNoise) else RigNoise(**n) for ch, n in noise.items()}
    realised = realised or {}

    def sd(ch, g):
        key = f"{g['curve'].iloc[0]}/{ch}"
        return realised[key] if key in realised else rig[ch].series_sd(g[TIME].to_numpy())

    return rms_over_true_noise(obs, res, sd)


def run_open_benchmark(n_cases: int, seed: int, out: str | Path, *, refinement: int = 1,
                       comm=MPI.COMM_WORLD, progress=None) -> dict:
    """Generate, diagnose blind and score ``n_cases`` open-world cases, each on whichever
    MPI rank is free.  Writes DIR/cases/, labels.json, results.json, summary.json,
    summary.md."""
    t_start = time.perf_counter()
    out = Path(out)
    config = {"world": "open", "seed": seed, "refinement": refinement,
              "engine": ENGINE_VERSION}
    reusable = ((out / "config.json").exists()
                and json.loads((out / "config.json").read_text()) == config)
    if comm.rank == 0:
        (out / "cases").mkdir(parents=True, exist_ok=True)
        (out / "labels").mkdir(exist_ok=True)
        write_json_atomic(out / "config.json", config, indent=1)
    comm.Barrier()
    bar = as_progress(progress, None, "open-world benchmark (rank 0's cases)", "case", comm)
    models: dict = {}
    mine = []
    skipped = []
    reused = []
    counter = SharedCounter(comm)
    with rank_local():  # this rank's own cases: its warnings are said
        # each case to whichever rank is free (a case depends only on its seed and
        # index, not on the rank or the cases before it)
        for i in dynamic_items(range(n_cases), counter):
            t0 = time.perf_counter()
            made = draw_case(i, seed, models)
            if made is None:
                skipped.append(f"world{i:03d}")
                continue
            rec, spec_df, case = made
            # the truth's generation, its draws that could not be solved included
            label = dict(case.label(), noise_sd=noise_sd(case.noise),
                         generation_s=round(time.perf_counter() - t0, 2))
            # the label of every case as soon as it exists (apart from what the diagnosis
            # reads), so that a benchmark stopped early can be scored (--rescore)
            write_json_atomic(out / "labels" / f"{case.name}.json", label, indent=1)
            csv_path = out / "cases" / f"{case.name}_recordings.csv"
            result_path = out / "cases" / f"{case.name}_result.json"
            text = rec.to_csv(index=False)
            res = None
            if reusable and result_path.exists() and csv_path.exists() and \
                    csv_path.read_text() == text:
                res = json.loads(result_path.read_text())
                reused.append(case.name)
                log.info("%s: recordings unchanged, diagnosis reused", case.name)
            write_text_atomic(csv_path, text)
            write_text_atomic(out / "cases" / f"{case.name}_specimens.csv",
                              spec_df.to_csv(index=False))
            obs = observations(rec)  # blind from here on
            if res is None:
                res = _diagnose(obs, case.spec, refinement, case.name)
                write_json_atomic(result_path, res, indent=1)
            res["rms_after_over_true_noise"] = _rms_over_rig_noise(obs, res, case.noise,
                                                                   case.noise_rms)
            mine.append((case.name, label, res))
            log.info("%s: %s %s -> %s (%s)", case.name, label["kind"], label["expected"],
                     res["verdict"], res["status"])
            bar.update(1, f"{case.name} {label['expected']} -> {res['verdict']}")
    bar.close()
    counter.free()
    allres = sorted(gather_all(comm, mine), key=lambda x: x[0])
    labels = {n: lab for n, lab, _ in allres}
    results = {n: r for n, _, r in allres}
    summary = score(labels, results)
    summary["left_out"] = sorted(gather_all(comm, skipped))
    summary["run"] = {"wall_s": round(time.perf_counter() - t_start, 1), "ranks": comm.size,
                      "reused": len(gather_all(comm, reused))}
    if comm.rank == 0:
        write_json_atomic(out / "labels.json", labels, indent=1)
        write_json_atomic(out / "results.json", results, indent=1)
        write_json_atomic(out / "summary.json", summary, indent=1)
        write_text_atomic(out / "summary.md", summary_markdown(summary))
    return summary


def _effect_set(verdict: str) -> set:
    """The effects a verdict or an expected answer names (``none``: none)."""
    return set() if verdict == "none" else set(verdict.split("+"))


def _correct(label: dict, res: dict) -> bool:
    """The verdict names exactly the expected set (in any order: results of engines before
    open-world-4 joined effects in the order they were added), or, for a library truth, the
    expected set and effects the recordings really hold beside it: an effect that the
    generator put in but judged too small to show (``VISIBLE``, after ``MAX_DRAWS``) is left
    out of the expected answer, and a diagnosis that finds it anyway names what is there
    (measured: a second Ogden term of 0.6-1.4 noise SD on the base fit, named
    `ogden_2term` and explained to 0.98-0.99 of the true noise on seeds 2, 3 and 8)."""
    got, want = _effect_set(res["verdict"]), _effect_set(label["expected"])
    if got == want:
        return True
    drawn = set(label.get("effects") or [])
    return label.get("kind") in ("single", "pair") and want <= got <= drawn


def _named_within_ambiguity(label: dict, res: dict) -> bool:
    """The verdict is right up to a pair the diagnosis itself reported it cannot tell
    apart with these tests."""
    if _correct(label, res):
        return True
    swaps = [set(a["effects"]) for a in res.get("ambiguous", [])]
    want, got = set(label["effects"]), set(res.get("effects", []))
    return len(want ^ got) == 2 and (want ^ got) in swaps


def _within_stated_limit(label: dict, res: dict) -> bool:
    """The verdict names part of a library truth and nothing else, and every effect it left
    out has its true size within the detection limit the diagnosis stated for it beside the
    named ones (``detection_limits``: each parameter's true value closer to its neutral
    value than the step that would show; for an effect stated at several design points,
    than the smallest of them).  Counted apart from the exact set: the limit is taken
    under the final noise model, whose residual still holds the missed effect."""
    want, got = set(label["effects"]), set(res.get("effects", []))
    if label["kind"] == "outside" or not got or not got < want:
        return False
    truth = label.get("truth", {})
    for e in want - got:
        limits = (res.get("detection_limits") or {}).get(e)
        if not limits or not all(
                (n := v.get("parameter", key)) in truth and abs(truth[n] - v["from"]) < v["step"]
                for key, v in limits.items()):
            return False
    return True


def _said_hidden(label: dict, res: dict) -> bool:
    """The verdict names part of a library truth and nothing else, and says of every effect
    it left out that it could hide behind a named one (``hidden``: beside that effect the
    parameter's variance is inflated past the collinearity bar while some allowed value
    would show without it).  Counted apart from the exact set, as the stated limit."""
    want, got = set(label["effects"]), set(res.get("effects", []))
    if label["kind"] == "outside" or not got or not got < want:
        return False
    return want - got <= {h["effect"] for h in res.get("hidden") or []}


def separable(label: dict) -> bool | None:
    """Whether a combination's tests can show every one of its effects beside the others
    (each leaves at least ``VISIBLE`` noise SDs to the best model with the others:
    :func:`diagnosis.open_world.visible_beside`); None when the label does not say
    (single effects, labels of runs before the measure)."""
    beside = list((label.get("misfit_beside_the_other_over_noise") or {}).values())
    if not beside or not np.isfinite(beside).all():
        return None
    return bool(min(beside) >= VISIBLE)


def mimicked(closest: dict, under: str = "white") -> bool | None:
    """Whether a library effect mimics an outside one in its case's tests: ``closest``
    (:func:`diagnosis.open_world.closest_library`) holds an effect (or, where measured, a
    pair of them) whose best fit leaves the noiseless recordings less than even the most
    favourable test of a systematic misfit, one parameter, needs
    (:func:`diagnosis.selection.chi2_needed` (1, 1, n), n recorded values).  ``under``:
    the noise that test faces: ``white``, white noise at the rig's SD (the misfit's size
    n r^2, r the RMS left in noise SDs: the outside rule of ``benchmarks/oracle_open.py``),
    or ``rig``, the rig's whole noise, its wander, filter and drift included
    (``chi2_under_rig_noise``, :func:`diagnosis.open_world.misfit_chi2`), which a misfit as
    slow as they are hides in.  Then the recordings cannot show that anything outside the
    library is at work, and `unexplained` is out of any rule's reach.  None when nothing
    was measured."""
    by = mimicked_by(closest, under)
    return None if by is None else bool(by)


def mimicked_by(closest: dict, under: str = "white") -> str | None:
    """The library effect that leaves the least of ``closest`` when that is below the bar
    of :func:`mimicked`, else the pair (``a+b``) that does, ``""`` when none is, None when
    nothing was measured: a pair is named only where no effect alone mimics."""
    closest = closest or {}
    n = int(closest.get("points") or 0)
    if under == "white":
        sizes = {k: n * float(v) ** 2
                 for k, v in (closest.get("rms_left_over_noise") or {}).items()}
    elif under == "rig":
        sizes = {k: float(v) for k, v in (closest.get("chi2_under_rig_noise") or {}).items()}
    else:
        raise ValueError(f"under: 'white' or 'rig', not {under!r}")
    sizes = {k: v for k, v in sizes.items() if np.isfinite(v)}
    if not sizes or n <= 0:
        return None
    bar = chi2_needed(1, 1, n)
    for keys in ([k for k in sizes if "+" not in k], list(sizes)):
        least = min(keys, key=sizes.get, default=None)
        if least is not None and sizes[least] < bar:
            return least
    return ""


def singles_of(closest: dict) -> dict:
    """``closest`` (:func:`diagnosis.open_world.closest_library`) without its pairs."""
    if not closest:
        return {}
    return {k: ({e: v for e, v in closest[k].items() if "+" not in e}
                if isinstance(closest[k], dict) else closest[k])
            for k in closest if k != "pairs"}


def outside_ceiling(by_case: list, closest: dict, under: str = "white",
                    pairs: bool = True) -> dict:
    """The outside cases of a scored run (``by_case`` of its summary) split by whether a
    library effect mimics them (``closest``: case -> :func:`diagnosis.open_world.
    closest_library`; ``under``: the noise of :func:`mimicked`; ``pairs``: whether the
    pairs measured count as well, :func:`singles_of`): the right answer `unexplained` is
    out of any diagnosis's reach on a mimicked case, so the score of the rest is what the
    diagnosis can be held to.  ``mimicked_by``: the effect or pair of each."""
    rows = [r for r in by_case if r["kind"] == "outside" and r["case"] in closest]
    by = {r["case"]: mimicked_by(closest[r["case"]] if pairs
                                 else singles_of(closest[r["case"]]), under) for r in rows}
    free = [r for r in rows if by[r["case"]] == ""]
    mim = [r for r in rows if by[r["case"]]]
    return {"measured": sum(f is not None for f in by.values()),
            "mimicked": sorted(r["case"] for r in mim),
            "mimicked_by": {r["case"]: by[r["case"]] for r in mim},
            "mimicked_correct": sum(bool(r["correct"]) for r in mim),
            "not_mimicked": len(free),
            "not_mimicked_correct": sum(bool(r["correct"]) for r in free),
            "not_mimicked_wrong": sorted(r["case"] for r in free if not r["correct"])}


def trace(res: dict) -> dict:
    """What a diagnosis's last decisions read, kept with each case of a summary so that a
    rule on them can be tried on stored draws without their case data (which a run keeps
    only in its own folder): the p-values of the tests of what remains
    (:mod:`diagnosis.remaining`), the effects merely tried, the slow relaxation
    (:func:`diagnosis.engine.slow_relaxation`, with its gain under the noise of the fit
    without it) and the *cannot tell* text."""
    rem = res.get("remaining") or {}
    slow = res.get("slow_relaxation") or {}
    return {"p_values": {k: (rem.get(k) or {}).get("p_value")
                         for k in ("reproducible", "trend", "split")},
            "repeats": (rem.get("reproducible") or {}).get("repeats"),
            "tried": list(res.get("tried") or []),
            "slow": {k: slow[k] for k in ("tau_s", "longest_test_s",
                                          "gain_under_noise_without", "needed")
                     if k in slow} or None,
            "cannot_tell": res.get("cannot_tell") or None}


def score(labels: dict, results: dict) -> dict:
    """Scores per kind, the confusion matrices (expected x verdict, kind x status), RMS."""
    rows = []
    for n in sorted(labels):
        lab, r = labels[n], results[n]
        rows.append({"case": n, "kind": lab["kind"], "expected": lab["expected"],
                     "verdict": r["verdict"], "status": r["status"],
                     "correct": _correct(lab, r),
                     "within_ambiguity": _named_within_ambiguity(lab, r),
                     "within_limit": _within_stated_limit(lab, r),
                     "said_hidden": _said_hidden(lab, r),
                     "rms_before": r.get("rms_before", float("nan")),
                     "rms_after": r.get("rms_after", float("nan")),
                     "rms_after_over_true_noise": r.get("rms_after_over_true_noise",
                                                        float("nan")),
                     "noise_kinds": "+".join(lab["noise_kinds"]),
                     "misfit": max(lab["base_misfit_over_noise"].values(), default=0.0),
                     "separable": separable(lab),
                     "cannot_tell": bool(r.get("cannot_tell")),
                     "elapsed_s": r.get("elapsed_s", float("nan")),
                     "trace": trace(r)})
    df = pd.DataFrame(rows)
    out: dict = {"cases": len(df), "by_case": rows}
    for kind in KINDS:
        g = df[df["kind"] == kind]
        out[kind] = {"cases": len(g), "correct": int(g["correct"].sum()),
                     "within_ambiguity": int(g["within_ambiguity"].sum()),
                     "within_limit": int(g["within_limit"].sum()),
                     "said_hidden": int(g["said_hidden"].sum())}
    sep = df[(df["kind"] == "pair") & df["separable"].eq(True)]  # None: not measured
    out["pair"].update(separable=len(sep), separable_correct=int(sep["correct"].sum()),
                       measured=int(df[df["kind"] == "pair"]["separable"].notna().sum()))
    out["control"]["false_alarms"] = int((df[df["kind"] == "control"]["verdict"] != "none"
                                          ).sum())
    doubt = df[df["cannot_tell"]]
    out["cannot_tell"] = {"cases": len(doubt), "correct": int(doubt["correct"].sum()),
                          "by_kind": {k: int((doubt["kind"] == k).sum()) for k in KINDS},
                          "wrong": int((~df["correct"]).sum()),
                          "wrong_said": int((~doubt["correct"]).sum())}
    o = df[df["kind"] == "outside"]
    out["outside"]["not_explained"] = int((o["status"] != "explained").sum())
    explained = df[df["status"] == "explained"]
    out["explained_rms_over_true_noise_max"] = float(
        explained["rms_after_over_true_noise"].max()) if len(explained) else float("nan")
    out["explained_rms_over_true_noise_median"] = float(
        explained["rms_after_over_true_noise"].median()) if len(explained) else float("nan")
    above = explained[explained["rms_after_over_true_noise"] > 1.2]
    out["explained_above_1.2"] = sorted(above["case"])
    out["explained_above_1.2_cannot_tell"] = sorted(above.loc[above["cannot_tell"], "case"])
    out["elapsed_s_median"] = float(df["elapsed_s"].median()) if len(df) else float("nan")
    gen = pd.Series([labels[n].get("generation_s", np.nan) for n in sorted(labels)],
                    dtype=float)
    longest = df.nlargest(3, "elapsed_s") if len(df) else df
    out["time"] = {"diagnoses_s": float(df["elapsed_s"].sum()) if len(df) else 0.0,
                   "longest": [[c, float(t)] for c, t in zip(longest["case"],
                                                            longest["elapsed_s"],
                                                            strict=True)],
                   "generation_s": float(gen.sum()) if gen.notna().any() else None,
                   "generation_s_median": float(gen.median()) if gen.notna().any()
                   else None}
    out["confusion"] = pd.crosstab(df["expected"], df["verdict"]).to_dict(orient="index") \
        if len(df) else {}
    out["status_by_kind"] = pd.crosstab(df["kind"], df["status"]).to_dict(orient="index") \
        if len(df) else {}
    return out


def _pct(a: int, b: int) -> str:
    return f"{a}/{b} ({a / b:.0%})" if b else "-"


def _table(matrix: dict, corner: str) -> list[str]:
    cols = sorted({c for row in matrix.values() for c in row})
    lines = [f"| {corner} | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for k in sorted(matrix):
        lines.append(f"| {k} | " + " | ".join(str(matrix[k].get(c, 0) or "")
                                              for c in cols) + " |")
    return lines


def _doubt_line(d: dict | None) -> str:
    """The answers that carry a *cannot tell* (a reason the verdict may not hold)."""
    if not d:
        return "- *cannot tell* beside the verdict: not scored"
    kinds = ", ".join(f"{k} {n}" for k, n in d["by_kind"].items() if n) or "none"
    return (f"- *cannot tell* beside the verdict: {d['cases']} ({kinds}); right answers "
            f"among them {d['correct']}; wrong answers that say so {d['wrong_said']} of "
            f"{d['wrong']}")


def _time_line(s: dict) -> str:
    """Where the time went: the whole run (when this summary was written by the run
    itself), the diagnoses and the generation of the truths, in rank-seconds."""
    t = s.get("time", {})
    parts = []
    run = s.get("run")
    if run:
        parts.append(f"the whole run {run['wall_s'] / 60:.1f} min on {run['ranks']} rank(s)"
                     + (f" ({run['reused']} diagnoses reused from an earlier run)"
                        if run["reused"] else ""))
    longest = ", ".join(f"{c} {v:.0f} s" for c, v in t.get("longest", []))
    parts.append(f"diagnoses {t.get('diagnoses_s', float('nan')):.0f} rank-s (median "
                 f"{s['elapsed_s_median']:.0f} s per case on one rank"
                 + (f"; longest {longest}" if longest else "") + ")")
    if t.get("generation_s") is not None:
        parts.append(f"generation of the truths {t['generation_s']:.0f} rank-s (median "
                     f"{t['generation_s_median']:.0f} s per case, draws that could not be "
                     "solved included)")
    return "- time: " + "; ".join(parts)


def summary_markdown(s: dict) -> str:
    c, si, p, o = (s[k] for k in KINDS)
    lines = ["# Open-world diagnosis benchmark", "",
             f"- cases: {s['cases']}",
             f"- controls, no false alarm: {_pct(c['cases'] - c['false_alarms'], c['cases'])}",
             f"- single effects named: {_pct(si['correct'], si['cases'])} (within a reported "
             f"ambiguity: {_pct(si['within_ambiguity'], si['cases'])})",
             f"- pairs, exact set: {_pct(p['correct'], p['cases'])} (within a reported "
             f"ambiguity: {_pct(p['within_ambiguity'], p['cases'])}; named part and the "
             f"rest within its stated detection limit: {p.get('within_limit', 0)}; named "
             f"part and the rest said to possibly hide behind it: {p.get('said_hidden', 0)})"
             + (f"; of the pairs whose tests separate both effects (each >= {VISIBLE} noise "
                f"SD beside the other; {p['measured']} of {p['cases']} measured): "
                f"{_pct(p['separable_correct'], p['separable'])}"
                if p.get("measured") else ""),
             f"- outside the library, `unexplained`: {_pct(o['correct'], o['cases'])}; "
             f"not `explained`: {_pct(o['not_explained'], o['cases'])}",
             f"- explained cases, RMS after / true noise: median "
             f"{s['explained_rms_over_true_noise_median']:.2f}, max "
             f"{s['explained_rms_over_true_noise_max']:.2f}"
             + (" (above 1.2: " + ", ".join(
                 c + (" (cannot tell)" if c in s.get("explained_above_1.2_cannot_tell", ())
                      else "") for c in s["explained_above_1.2"]) + ")"
                if s["explained_above_1.2"] else ""),
             _doubt_line(s.get("cannot_tell")),
             _time_line(s),
             "- left out (no solvable truth in 5 draws): "
             + (", ".join(s.get("left_out", [])) or "none"),
             "", "Outcomes (rows: the right answer, columns: verdict)", ""]
    lines += _table(s["confusion"], "truth \\ verdict")
    lines += ["", "Status by kind of case", ""]
    lines += _table(s["status_by_kind"], "kind \\ status")
    lines += ["", "Every case", "",
              "| case | kind | truth | verdict | status | noise | misfit | RMS before | "
              "RMS after | after / true noise |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in s["by_case"]:
        verdict = r["verdict"] + (" (cannot tell)" if r.get("cannot_tell") else "")
        lines.append(f"| {r['case']} | {r['kind']} | {r['expected']} | {verdict} | "
                     f"{r['status']} | {r['noise_kinds']} | {r['misfit']:.1f} | "
                     f"{r['rms_before']:.2f} | {r['rms_after']:.2f} | "
                     f"{r['rms_after_over_true_noise']:.2f} |")
    return "\n".join(lines) + "\n"


def rescore_open(out: str | Path) -> dict:
    """Score an open-world benchmark directory again: every case with a label
    (``labels/``) and a blind result (``cases/``), also of a run stopped early."""
    out = Path(out)
    if not (out / "labels").is_dir():
        raise ValueError(f"{out / 'labels'}: not found (not an open-world benchmark "
                         "directory?)")
    labels, results = {}, {}
    for p in sorted((out / "labels").glob("world*.json")):
        name = p.stem
        res_path = out / "cases" / f"{name}_result.json"
        if not res_path.exists():
            continue
        labels[name] = json.loads(p.read_text())
        res = json.loads(res_path.read_text())
        spec = read_specimens(out / "cases" / f"{name}_specimens.csv")
        obs = observations(read_recordings(out / "cases" / f"{name}_recordings.csv", spec))
        res["rms_after_over_true_noise"] = _rms_over_rig_noise(
            obs, res, labels[name]["noise"], labels[name].get("noise_rms"))
        results[name] = res
    if not labels:
        raise ValueError(f"{out}: no case has both a label and a result yet")
    before = out / "summary.json"  # the run's own list of draws left out, if it wrote one,
    # and its wall time
    run = json.loads(before.read_text()) if before.exists() else {}
    summary = score(labels, results)
    summary["left_out"] = run.get("left_out", [])
    if run.get("run") and run.get("cases") == summary["cases"]:
        summary["run"] = run["run"]  # the same cases: the run's own wall time still holds
    write_json_atomic(out / "summary.json", summary, indent=1)
    write_text_atomic(out / "summary.md", summary_markdown(summary))
    return summary
