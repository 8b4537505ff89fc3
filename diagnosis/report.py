"""Outputs of a diagnosis: DIR/diagnosis.json, DIR/report.md and its figures."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from brain_fe.io import staged_directory, write_atomic, write_json_atomic, write_text_atomic
from brain_fe.logs import rank_local

from .effects import EFFECTS
from .engine import EXPLAINS_FRACTION
from .figures import before_after_png, mismatch_map
from .remaining import trend_change

log = logging.getLogger(__name__)


FIGURE_TAG = 1601  # the MPI tag of the before/after figure drawn by rank 1


def write(d, out: str | Path, *, title: str = "diagnosis", comm=None) -> dict:
    """Write DIR/diagnosis.json, DIR/report.md, DIR/mismatch_map.png, DIR/before_after.png,
    all at once (staged, then moved into place: a result is complete or absent).

    ``comm``: the ranks that diagnosed ``d`` together (every one of them calls this).  Rank
    1 then draws the before/after figure while rank 0 draws the mismatch map (0.3 s of a
    diagnosis of ~20 s on 2 ranks); rank 0 writes every file and returns the result, the
    other ranks return {}.  The files are the same bit for bit."""
    helper = comm is not None and comm.size > 1
    if helper and comm.rank != 0:
        if comm.rank == 1:
            comm.send(_drawn(d), dest=0, tag=FIGURE_TAG)
        return {}
    received = []

    def before_after_figure() -> bytes | None:
        if helper and not received:
            received.append(comm.recv(source=1, tag=FIGURE_TAG))
        return received[0] if helper else None

    try:
        with staged_directory(out) as stage:
            return _write(d, stage, title, before_after_figure)
    finally:
        before_after_figure()  # rank 1 waits in its send until it is received


def _drawn(d) -> bytes | None:
    """The before/after figure as PNG bytes; None when it could not be drawn here (this
    rank says why, and rank 0 draws it)."""
    try:
        return before_after_png(d)
    except Exception as exc:  # noqa: BLE001 - rank 0 must hear from this rank in any case
        with rank_local():
            log.error("before/after figure not drawn on this rank: %s: %s",
                      type(exc).__name__, exc)
        return None


STATUS_TEXT = {
    "none": "the base model fits at the noise level: nothing systematic to explain",
    "explained": "the named physics removes the located mismatch: what remains is noise",
    "partially explained": "the named physics removes part of the mismatch; a systematic "
    "misfit remains (below)",
    "unexplained": "a systematic misfit that no candidate of the library removes",
}
TRIED_TEXT = "a systematic misfit the library does not explain: its closest model, {}, {}"
TRIED_HALF = "leaves more than half of the RMS misfit"
TRIED_TREND = ("leaves a stiffness change with time, which no effect of the library makes "
               "and which the effects fitted beside it may stand in for")


def _tried_text(d, res: dict) -> str:
    """Why the effects of the library's closest model are tried, not named
    (``res``: the diagnosis as in diagnosis.json)."""
    why = [TRIED_HALF] if res["rms_after"] > EXPLAINS_FRACTION * res["rms_before"] else []
    if d.remaining.get("trend", {}).get("significant", False):
        why.append(TRIED_TREND)
    return TRIED_TEXT.format("+".join(sorted(d.tried)), " and ".join(why)
                             + ", so no effect is named")


def _segments(rows, limit=12) -> list[str]:
    out = ["| axis | segment | n | RMS/noise | p |", "|---|---|---|---|---|"]
    for s in rows[:limit]:
        out.append(f"| {s['axis']} | {s['segment']} | {s['n']} | {s['rms_z']:.2f} | "
                   f"{s['p_value']:.2g} |")
    if not rows:
        out.append("| - | no systematic segment | | | |")
    return out


def _write(d, out: Path, title: str, drawn_elsewhere) -> dict:
    """``drawn_elsewhere()``: the before/after figure's PNG bytes drawn by another rank
    (None: drawn here)."""
    res = d.to_json()
    r = d.base.residual(d.obs)
    mismatch_map(d.obs, d.noise.whiten(r), np.ones(len(r)), d.located,
                 out / "mismatch_map.png")
    png = drawn_elsewhere()
    if png is None:
        png = before_after_png(d)
    else:
        log.debug("before/after figure drawn by rank 1")
    write_atomic(out / "before_after.png", lambda fh: fh.write(png))
    write_json_atomic(out / "diagnosis.json", res, indent=1, default=float)
    named = " + ".join(EFFECTS[e].description if e in EFFECTS else e for e in d.effects)
    lines = [f"# {title}", "", f"**Verdict: {d.verdict}** ({d.status})"
             + (f" — {named}" if named else ""), "",
             (_tried_text(d, res) if d.tried else STATUS_TEXT[d.status]) + ".", ""]
    if d.cannot_tell:
        lines += [f"**Cannot tell**: {d.cannot_tell}.", ""]
    if d.last_digits.get("same"):
        lines += ["The same verdict with the recorded numbers changed in their last digits "
                  "(checked).", ""]
    lines += [f"Residual RMS / noise: {res['rms_before']:.2f} (base) -> "
              f"{res['rms_after']:.2f} (after modelling); 1 = noise level.", "",
              "## Where the base model misfits", "",
              "Residuals whitened by the rig's noise model (white noise, wander, drift; "
              "estimated from the final model's residual).", ""]
    lines += _segments(res["located"])
    lines += ["", "![mismatch map](mismatch_map.png)", "", "## What remains", ""]
    rem = res["remaining"]
    rep = rem["reproducible"]
    verdict = "significant" if rep["significant"] else "not significant"
    lines += [f"Reproducible misfit (the same at every repetition, repeats: "
              f"{rep['repeats']}): chi2 gain {rep['gain']:.1f} on {rep['dof']} parameters, "
              f"p = {rep['p_value']:.2g}, {verdict}.", ""]
    tr = rem.get("trend")
    if tr and tr["dof"]:
        lines += [f"Stiffness trending with time (one rate in every test of several cycles): "
                  f"chi2 gain {tr['gain']:.1f} "
                  f"on {tr['dof']} parameters, p = {tr['p_value']:.2g}, "
                  f"{'significant' if tr['significant'] else 'not significant'}"
                  + (f"; modelled, the stiffness changes by {trend_change(tr)}"
                     if "change" in tr else "") + ".", ""]
    lines += _segments(rem["located"])
    if res["closest"]:
        lines += ["", "Closest candidates: " + ", ".join(
            f"{c['effect']} (LRT {c['lrt']:.1f}, dBIC {c['delta_bic']:.1f})"
            for c in res["closest"])]
    for n in res["notes"]:
        lines += ["", f"Note: {n}."]
    lines += ["", "## Rounds of selection", "",
              "Each round adds the significant effect of lowest BIC to the model (LRT p < "
              "alpha / candidates and a BIC gain beyond the margin, under the rig's noise "
              "model); 'screened out': its score could not reach significance; 'could not be "
              "solved': its fit failed (the FE model could not follow it); 'not scored': "
              "the FE model could not follow it at any design point.", ""]
    for rnd in res["rounds"]:
        lines += _round_lines(rnd)
    for a in res["ambiguous"]:
        lines += [f"**Cannot tell apart** {a['effects'][0]} and {a['effects'][1]} "
                  f"(dBIC {a['delta_bic']:.1f}); would separate them: {a['separating_test']}.",
                  ""]
    lines += _limit_lines(res)
    lines += ["## Before and after", "", "![before/after](before_after.png)", "",
              "| parameter | base fit | refit | bias of the base fit |", "|---|---|---|---|"]
    for n, b in res["base_bias"].items():
        lines.append(f"| {n} | {b['base']:.4g} | {b['refit']:.4g} | {100 * b['relative']:+.1f} % |")
    disc = res["discretisation"]
    if disc.get("corrected"):
        lines += ["", f"Discretisation: the k = {disc['refinement']} mesh is corrected by "
                  f"{disc['richardson_factor']:.3f} times its difference to k = "
                  f"{disc['reference_refinement']} at the base fit (the Richardson limit of "
                  f"order 3; correction max {disc['max_over_noise']:.2f}, RMS "
                  f"{disc['rms_over_noise']:.2f} noise standard deviations)."]
    elif disc.get("not_corrected_because"):
        lines += ["", "Discretisation: **not corrected** (" + disc["not_corrected_because"]
                  + "); the working mesh's discretisation error may be part of the misfit."]
    lines += ["", f"Elapsed: {res['elapsed_s']:.0f} s{_where_the_time_went(res)}."]
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    return res


def _round_lines(rnd: dict) -> list[str]:
    """One round of selection: what it added and dropped, and its table."""
    back = rnd["added"] is not None and rnd["added"] in rnd["dropped"]
    lines = [f"From **{rnd['from']}**: added {rnd['added'] or 'nothing'}"
             + (f", dropped {', '.join(rnd['dropped'])}" if rnd["dropped"] else "")
             + (" (it lost its place when re-tested beside the others from the joint "
                "fit's values)" if back else ""), "",
             "| effect | score | dBIC | LRT p | significant | parameters |",
             "|---|---|---|---|---|---|"]
    for e in rnd["table"]:
        pars = ", ".join(f"{k} = {v:.4g}" for k, v in e["parameters"].items())
        sig = "screened out" if e.get("screened_out") else (
            "could not be solved" if e.get("fit_failed") else (
                "not scored" if e.get("score_failed") else (
                    "yes" if e["significant"] else "no")))
        lines.append(f"| {e['effect']} | {e['score']:.1f} | {e['delta_bic']:.1f} | "
                     f"{e['p_value']:.2g} | {sig} | {pars} |")
    return [*lines, ""]


def _limit_lines(res: dict) -> list[str]:
    """The detection limits of the candidates not named, and those the named effects mask."""
    lines = []
    for m in res.get("masked", []):
        lines += [f"**Cannot tell whether {m['effect']} is also present**: beside "
                  f"{' + '.join(m['beside'])}, no allowed value of it would show in these "
                  f"tests; would tell: {m['separating_test']}.", ""]
    for h in res.get("hidden", []):
        without = ", ".join(f"{x:.4g}" for x in h["would_show_without"])
        beside = ", ".join(f"{x:.4g}" for x in h["would_show_at"])
        beside = (f"only from {beside} (its variance inflated {h['inflation']:.3g} times: "
                  "these tests can hardly tell the two apart)" if beside else
                  "no allowed value would (these tests cannot tell the two apart)")
        lines += [f"**{h['effect']} could hide behind {h['behind']}**: without "
                  f"{h['behind']} in the model, {h['parameter']} would show from {without}; "
                  f"beside it, {beside}; would tell: {h['separating_test']}.", ""]
    limits = res.get("detection_limits") or {}
    if limits:
        lines += ["How large the candidates not named would have to be to show beside the final "
                  "model (linearised at their neutral value, an effect with a time, exponent or "
                  "softening scale of its own at each point of the generic design, a glue "
                  "layer solved; beyond the bounds: never):",
                  "",
                  "| effect | parameter | from | would show at |", "|---|---|---|---|"]
        glue = []
        for e, d in limits.items():
            for n, v in d.items():
                at = ", ".join(f"{x:.4g}" for x in v["would_show_at"]) or "no allowed value"
                lines.append(f"| {e} | {n} | {v['from']:.4g} | {at} |")
                if v.get("solved_at") and v["would_show_at"]:
                    glue.append(f"{e}: a glue layer softer than k = "
                                f"{10.0 ** v['would_show_at'][0]:.3g} kPa/mm would show "
                                "(solved with the layer at log10_k = " + ", ".join(
                                    f"{k:.3g}" for k in v["solved_at"]) + ", not "
                                "linearised: its misfit is far from linear in 1/k).")
        lines += [""] + [x for g in glue for x in (g, "")]
    return lines


def _where_the_time_went(res: dict) -> str:
    t = res.get("timings_s") or {}
    if not t:
        return ""
    parts = [f"base fit and discretisation correction {t['base_fit_and_correction']:.0f} s"]
    for i, r in enumerate(t["rounds"], 1):
        fits = ", ".join(f"{e} {v['s']:.0f} s/{v['evaluations']} evaluations"
                         for e, v in r["fit_per_candidate"].items())
        tie = ", ".join(f"{e} {v['s']:.0f} s/{v['evaluations']} evaluations"
                        for e, v in r.get("near_tie_completion", {}).items())
        parts.append(f"round {i}: scores {r['scores']:.0f} s, fits {r['fits']:.0f} s"
                     + (f" ({fits})" if fits else "")
                     + (f", near tie completed: {tie}" if tie else ""))
    return " (" + "; ".join(parts) + ")"
