"""Diagnose the specimens of a recordings table: shared among MPI ranks, resumable.

* One specimen: its results go to ``DIR`` itself, and the candidate fits are shared among
  the ranks of ``comm``.
* Several: one folder per specimen (``DIR/<specimen>/``), each written atomically when its
  diagnosis is complete; the specimens are handed out one at a time to whichever rank is
  free (:func:`brain_fe.parallel.dynamic_items`), each rank working alone, so the same
  command scales from 2 cores to a cluster under ``mpirun``/``srun``.  ``DIR/config.json``
  records the settings and the engine's version; a re-run with the same (after an
  interruption, say) diagnoses only the specimens without a result, and one with other
  settings or another engine is refused.
  ``DIR/diagnosis.json`` and ``DIR/summary.md`` gather the verdicts.
* ``check_digits``: every specimen is diagnosed a second time with its recorded numbers
  changed in their last digits; a verdict that moves is *cannot tell*
  (:mod:`diagnosis.determinacy`).
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
from brain_fe.parallel import Progress, SharedCounter, as_progress, dynamic_items, gather_all
from brain_fe.vocabulary import COMPRESSION_TENSION, CONTROL, LOADING, TIME
from recordings.observations import observations
from recordings.rheometer_segments import ramp_ids
from recordings.tables import read_recordings, read_specimens
from simulators.fe import FESimulator

from . import determinacy, report
from .engine import ENGINE_VERSION, diagnose

log = logging.getLogger(__name__)


def _diagnose_one(name, rec, specs, target: Path, *, refinement, effects, nu0, noise, comm,
                  progress, check_digits=False) -> dict:
    row = specs.set_index("specimen").loc[name]
    obs = observations(rec[rec.specimen == name])
    obs.attrs["radius_mm"] = float(row.radius_mm)
    R, H = float(row.radius_mm), float(row.height_mm)
    ends = str(row.get("ends", "glued"))
    with as_progress(progress, None, f"diagnose {name}", "fit", comm) as bar:
        def run(obs):
            sim = FESimulator(obs, R, H, refinement=refinement, nu0=nu0, ends=ends)
            fine = FESimulator(obs, R, H, refinement=refinement + 1, nu0=nu0, ends=ends)
            return diagnose(sim, obs, fine_sim=fine, effects=effects, comm=comm, noise=noise,
                            progress=lambda what: bar.update(1, what))
        d = run(obs)
        if check_digits:
            determinacy.check(d, run)
    log.info("%s: verdict %s", name, d.verdict)
    return report.write(d, target, title=f"Diagnosis of specimen {name}", comm=comm)


def diagnose_recordings(recordings: str, specimens: str, out: str, *,
                        specimen: str | None = None, refinement: int = 1,
                        effects=None, nu0: float = 0.49, noise: dict | None = None,
                        check_digits: bool = False, comm=MPI.COMM_WORLD,
                        progress=None) -> dict:
    """Diagnose every specimen of a recordings table (see the module docstring).

    Returns ``{specimen: diagnosis.json content}`` on rank 0 (every specimen, reused or
    new; each with ``"reused": bool``) and ``{}`` on the other ranks."""
    specs = read_specimens(specimens)
    rec = read_recordings(recordings, specs)  # validated before any output is written
    names = list(dict.fromkeys(rec["specimen"]))
    if specimen is not None:
        if specimen not in names:
            raise ValueError(f"{recordings}: no recordings of specimen {specimen!r}")
        names = [specimen]
    out = Path(out)
    kw = dict(refinement=refinement, effects=effects, nu0=nu0, check_digits=check_digits)
    if len(names) == 1:
        res = _diagnose_one(names[0], rec, specs, out, comm=comm, progress=progress,
                            noise=noise_of(noise, names[0]), **kw)
        comm.Barrier()
        return {names[0]: dict(res, reused=False)} if comm.rank == 0 else {}
    config = {"engine": ENGINE_VERSION,
              "refinement": refinement, "effects": sorted(effects) if effects else None,
              "nu0": nu0, "noise": noise, "recordings": str(Path(recordings).resolve())}
    if check_digits:  # the answers differ (cannot tell where the digits move them)
        config["check_digits"] = True
    if "ends" in specs:  # the end conditions are part of the model: recorded when given
        config["ends"] = {n: e for n, e in zip(specs.specimen, specs.ends, strict=True)
                          if e != "glued" and n in names}
    error = None
    if comm.rank == 0:
        error = _claim(out, config)
    error = comm.bcast(error, root=0)
    if error:
        raise ValueError(error)
    pending = [n for n in names if not _done(out / str(n))]
    log.info("%s: %d of %d specimens to diagnose on %d rank(s)", out, len(pending),
             len(names), comm.size)
    counter = SharedCounter(comm, slots=2)
    done_here = []
    self_comm = MPI.COMM_SELF
    with Progress(len(names), "diagnose", "specimen", enabled=bool(progress), comm=comm,
                  initial=len(names) - len(pending)) as bar:
        for name in dynamic_items(pending, counter):
            t0 = time.perf_counter()
            with rank_local():  # this rank's specimen: its warnings are said
                try:
                    res = _diagnose_one(name, rec, specs, out / str(name), comm=self_comm,
                                        progress=None, noise=noise_of(noise, name), **kw)
                except (RuntimeError, ValueError) as exc:  # this specimen, not the batch
                    log.error("%s: not diagnosed: %s", name, exc)
                    res = {"verdict": "not diagnosed", "error": str(exc)}
                    (out / str(name)).mkdir(parents=True, exist_ok=True)
                    write_json_atomic(out / str(name) / FAILED, res, indent=1)
            done_here.append(name)
            counter.add(1)
            bar.update(1, f"{name}: {res['verdict']} ({time.perf_counter() - t0:.0f} s)")
        if comm.rank == 0:
            seen = counter.read(1)
            while seen < len(pending):  # keep the bar moving while the others finish
                time.sleep(0.2)
                now = counter.read(1)
                bar.update(now - seen, None)
                seen = now
    new = set(gather_all(comm, done_here))
    counter.free()
    if comm.rank != 0:
        return {}
    results = {n: dict(json.loads(_done(out / str(n)).read_text()), reused=n not in new)
               for n in names}
    write_json_atomic(out / "diagnosis.json", {n: _digest(r) for n, r in results.items()},
                      indent=1)
    groups = groups_of(specs, names)
    rows = specs.set_index("specimen")
    regions = {n: str(rows.loc[n, "region"]) for n in names}
    # by material/protocol, also where groups_of merged one-specimen groups into the region
    signatures = signatures_markdown(results, groups_of(specs, names, merge=False), regions,
                                     protocol_facts(rec))
    write_text_atomic(out / "summary.md", summary_markdown(results) + "\n" + groups_markdown(
        results, groups) + ("\n" + signatures if signatures else "")
        + "\n![across specimens](summary.png)\n")
    from .figures import across_specimens

    across_specimens(results, groups, out / "summary.png")
    return results


def groups_of(specs, names: list, merge: bool = True) -> dict:
    """Specimen -> group: ``region/brain`` of the specimens table (for imported rheometer
    exports: material/protocol, e.g. ``fungi_steak/2s``), or (``merge``) the region alone
    when every such group would hold one specimen."""
    rows = specs.set_index("specimen")
    fine = {n: f"{rows.loc[n, 'region']}/{rows.loc[n, 'brain']}" for n in names}
    if merge and len(set(fine.values())) == len(names) and len(names) > 1:
        return {n: str(rows.loc[n, "region"]) for n in names}
    return fine


def groups_markdown(results: dict, groups: dict) -> str:
    """Across the specimens of each group: verdicts, how often each effect is named, the
    refit parameters (median and range), RMS against the noise before and after, and what
    the final models leave."""
    lines = ["# Across specimens, by group", "",
             "| group | n | verdicts | effects named | RMS/noise before, median (range) | "
             "after | after <= before / 2 where named | what remains (most often) |",
             "|---|---|---|---|---|---|---|---|"]
    params_lines = ["", "Refit parameters per group: median (min - max) over the specimens",
                    "", "| group | parameter | n | median | min | max |",
                    "|---|---|---|---|---|---|"]
    for g in dict.fromkeys(groups.values()):
        verdicts = _counts(_verdict(results[n]) for n in results if groups.get(n) == g)
        rs = [results[n] for n in results if groups.get(n) == g and "error" not in results[n]]
        if not rs:
            lines.append(f"| {g} | 0 | {_fmt(verdicts)} | - | - | - | - | - |")
            continue
        effects = _counts(e for r in rs for e in r.get("effects", []))
        tried = _counts("+".join(sorted(r["tried"])) for r in rs if r.get("tried"))
        before = np.array([r["rms_before"] for r in rs])
        after = np.array([r["rms_after"] for r in rs])
        named = [r for r in rs if r.get("effects")]
        halved = sum(r["rms_after"] <= 0.5 * r["rms_before"] for r in named)
        left = _counts((r.get("remaining", {}).get("located") or [{}])[0].get("segment", "-")
                       for r in rs if r.get("status") in ("partially explained", "unexplained"))
        lines.append(
            f"| {g} | {len(rs)} | {_fmt(verdicts)} | {_fmt(effects) or '-'}"
            + (f" (tried, not named: {_fmt(tried)})" if tried else "") + " | "
            f"{np.median(before):.2f} ({before.min():.2f}-{before.max():.2f}) | "
            f"{np.median(after):.2f} ({after.min():.2f}-{after.max():.2f}) | "
            f"{f'{halved}/{len(named)}' if named else '-'} | {_fmt(left) or '-'} |")
        names = dict.fromkeys(k for r in rs for k in r.get("refit_parameters", {}))
        for k in names:
            v = np.array([r["refit_parameters"][k] for r in rs
                          if k in r.get("refit_parameters", {})])
            params_lines.append(f"| {g} | {k} | {len(v)} | {np.median(v):.4g} | "
                                f"{v.min():.4g} | {v.max():.4g} |")
    return "\n".join(lines + params_lines) + "\n"


RATE_STEP = 1.5  # groups of one material whose loading rates differ by this factor or more


def protocol_facts(rec: pd.DataFrame) -> dict:
    """Per specimen, from its recordings: the median loading rate [1/s] of the ramps of its
    first test (sorted by name; strain, or amount of shear, per second), each ramp a run of
    consecutive loading rows (a compression and a tension ramp of one cycle apart), its
    largest number of cycles and its tests."""
    out = {}
    for name, g in rec.groupby("specimen", sort=False):
        tests = sorted(g["test"].astype(str).unique())
        rates = []
        for _, c in g[g["test"] == tests[0]].groupby("amplitude", sort=False):
            ramp = ramp_ids(c["cycle"].to_numpy(), c["branch"].to_numpy(object))
            loading = (c["branch"] == LOADING).to_numpy()
            for _, r in c[loading].groupby(ramp[loading]):
                x = r[CONTROL[tests[0]]].to_numpy(float)
                x = np.abs(x - 1.0) if tests[0] == COMPRESSION_TENSION else np.abs(x)
                t = r[TIME].to_numpy(float)
                ok = np.isfinite(x) & np.isfinite(t)
                if ok.sum() > 1 and np.ptp(t[ok]) > 0:
                    rates.append(np.ptp(x[ok]) / np.ptp(t[ok]))
        out[name] = {"rate_per_s": float(np.median(rates)) if rates else float("nan"),
                     "cycles": int(g["cycle"].max()), "tests": "+".join(tests)}
    return out


def _tested(r: dict, effect: str) -> str:
    """How a diagnosis met a candidate: ``named``, ``untestable`` (its model could not be
    solved for the score or the fit), ``absent`` (not a candidate) or ``tested``."""
    if effect in r.get("effects", []):
        return "named"
    rows = [t for t in ((r.get("rounds") or [{}])[0].get("table") or [])
            if t.get("effect") == effect]
    if not rows:
        return "absent"
    return "untestable" if rows[0].get("score_failed") or rows[0].get("fit_failed") \
        else "tested"


def _range(v: list, fmt: str = ".3g") -> str:
    return (f"{np.median(v):{fmt}} ({min(v):{fmt}}-{max(v):{fmt}})" if len(v) > 1
            else f"{v[0]:{fmt}}") if v else "-"


def signatures_markdown(results: dict, groups: dict, regions: dict, facts: dict) -> str:
    """What the diagnoses make of the two signatures a rheometer series shows: rate
    dependence across groups of one material tested with the same tests and cycles at
    different loading rates (is the
    viscoelastic candidate named at each speed, with which relaxation time; or could it
    not be tested), and the first cycle against the next in tests of several cycles (is
    Mullins softening named, tried, or not testable).  ``regions``: specimen -> material;
    ``facts``: :func:`protocol_facts`.  Empty when the batch has neither."""
    ok = {n: r for n, r in results.items() if "error" not in r}
    lines: list[str] = []
    by_region: dict = {}
    for n in ok:
        f = facts.get(n, {})
        key = (regions.get(n), f.get("tests"), f.get("cycles"))
        by_region.setdefault(key, {}).setdefault(groups.get(n), []).append(n)
    for (region, tests, cycles), gs in by_region.items():
        rate = {}
        for g, ns in gs.items():
            v = [facts[n]["rate_per_s"] for n in ns if n in facts]
            v = [x for x in v if np.isfinite(x)]
            if v:
                rate[g] = float(np.median(v))
        if len(rate) < 2 or max(rate.values()) < RATE_STEP * min(rate.values()):
            continue
        lines += ["", f"## Rate dependence: {region} ({tests}, {cycles} cycle"
                  f"{'s' if cycles != 1 else ''})", "",
                  "| group | loading rate [1/s] | n | viscoelastic named | tau [s] | beta | "
                  "tried, not named (unexplained) | not testable (model not solved) |",
                  "|---|---|---|---|---|---|---|---|"]
        said = []
        for g in sorted(rate, key=rate.get, reverse=True):
            rs = [ok[n] for n in gs[g]]
            named = [r for r in rs if "viscoelastic" in r.get("effects", [])]
            tried = sum("viscoelastic" in r.get("tried", []) for r in rs)
            taus = [10 ** r["refit_parameters"]["log10_tau_0"] for r in named]
            betas = [r["refit_parameters"]["beta_0"] for r in named]
            how = [_tested(r, "viscoelastic") for r in rs]
            blind, absent = how.count("untestable"), how.count("absent")
            lines.append(f"| {g} | {rate[g]:.3g} | {len(rs)} | {len(named)} | {_range(taus)} "
                         f"| {_range(betas)} | {tried} | {blind} |")
            if 2 * len(named) > len(rs):
                said.append(f"{g}: viscoelastic in {len(named)} of {len(rs)}, tau "
                            f"{_range(taus)} s")
            elif 2 * (len(named) + tried) > len(rs):
                said.append(f"{g}: viscoelastic named in {len(named)} of {len(rs)}, fitted "
                            f"but not named in {tried} more (beside a misfit the library "
                            "does not explain)")
            elif 2 * absent >= len(rs):
                said.append(f"{g}: not tested (viscoelastic not a candidate in {absent} of "
                            f"{len(rs)})")
            elif 2 * (blind + absent) >= len(rs):
                said.append(f"{g}: cannot tell (the viscoelastic model could not be solved "
                            f"along the recorded path in {blind} of {len(rs)})")
            else:
                said.append(f"{g}: no rate effect named ({len(named)} of {len(rs)})")
        lines += ["", "What the diagnoses make of it: " + "; ".join(said) + "."]
    multi = [n for n in ok if facts.get(n, {}).get("cycles", 1) >= 2]
    if multi:
        lines += ["", "## First cycle against the next (tests of two or more cycles)", "",
                  "| group | n | Mullins named | with viscoelastic | softening d | "
                  "Mullins not testable | viscoelastic named |", "|---|---|---|---|---|---|---|"]
        for g in dict.fromkeys(groups.get(n) for n in multi):
            rs = [ok[n] for n in multi if groups.get(n) == g]
            mul = [r for r in rs if "mullins" in r.get("effects", [])]
            lines.append(
                f"| {g} | {len(rs)} | {len(mul)} | "
                f"{sum('viscoelastic' in r['effects'] for r in mul)} | "
                f"{_range([r['refit_parameters']['softening'] for r in mul], '.2f')} | "
                f"{sum(_tested(r, 'mullins') == 'untestable' for r in rs)} | "
                f"{sum('viscoelastic' in r.get('effects', []) for r in rs)} |")
        lines += ["", "A cycle-to-cycle difference that Mullins softening does not take (a "
                  "set, damage, adhesion) stays in the final model's misfit: see what remains "
                  "per specimen above."]
    return "\n".join(lines).lstrip("\n") + ("\n" if lines else "")


def _verdict(r: dict) -> str:
    return r["verdict"] + (" (cannot tell)" if r.get("cannot_tell") else "")


def _counts(items) -> dict:
    out: dict = {}
    for x in items:
        out[x] = out.get(x, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _fmt(counts: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items())


FAILED = "not_diagnosed.json"  # beside where diagnosis.json would be: why it is not


def _done(folder: Path) -> Path | None:
    """The result file of a specimen's folder (its diagnosis, or why there is none)."""
    for name in ("diagnosis.json", FAILED):
        if (folder / name).exists():
            return folder / name
    return None


def noise_of(noise: dict | None, specimen: str) -> dict | None:
    """The stated noise of ``specimen``: ``noise`` is None (estimate it), ``{channel: SD}``
    for every specimen, or ``{"by_specimen": {specimen: {channel: SD}}}`` (a specimen it
    does not list takes the entry ``"*"``, else has its noise estimated, and the log says
    so).  A channel's value may state its whole noise (:func:`diagnosis.noise.statement`)."""
    if not noise or "by_specimen" not in noise:
        return noise or None
    listed = noise["by_specimen"]
    mine = listed.get(str(specimen), listed.get("*"))
    if mine is None:
        log.warning("%s: no stated noise for this specimen; estimated from its recordings",
                    specimen)
    return mine


def _claim(out: Path, config: dict) -> str | None:
    """Create ``out`` with its config, or check that an existing one has the same."""
    path = out / "config.json"
    if path.exists():
        old = json.loads(path.read_text())
        diff = [k for k in config if old.get(k) != config[k]]
        if diff:
            return (f"{out} holds diagnoses made with another {diff[0]} ({old.get(diff[0])!r}"
                    f", now {config[diff[0]]!r}); use another output directory")
        return None
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, config, indent=1)
    return None


def _digest(r: dict) -> dict:
    keys = ("verdict", "effects", "status", "tried", "cannot_tell", "rms_before", "rms_after",
            "error")
    return {k: r[k] for k in keys if k in r}


def summary_markdown(results: dict) -> str:
    """One line per specimen: verdict, RMS before and after, the worst located segment."""
    lines = ["# Diagnosis of every specimen", "",
             "| specimen | verdict | status | RMS/noise before -> after | where the base model "
             "misfits | what remains |", "|---|---|---|---|---|---|"]
    for n, r in results.items():
        if "error" in r:
            lines.append(f"| {n} | not diagnosed | - | - | - | {r['error']} |")
            continue
        where = r["located"][0]["segment"] if r.get("located") else "-"
        left = r.get("remaining", {}).get("located") or []
        lines.append(f"| {n} | {_verdict(r)} | {r.get('status', '-')} | "
                     f"{r['rms_before']:.2f} -> {r['rms_after']:.2f} | {where} | "
                     f"{left[0]['segment'] if left else '-'} |")
    counts: dict[str, int] = {}
    for r in results.values():
        counts[_verdict(r)] = counts.get(_verdict(r), 0) + 1
    lines += ["", "Verdicts: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))]
    return "\n".join(lines) + "\n"
