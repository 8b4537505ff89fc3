"""``brainmech import``: TA Instruments (TRIOS) rheometer exports -> the project's tables.

Three shapes of export are read (parallel plates, radius ``radius_mm``, default 4 mm):

* **raw trace** ``.txt`` (tab-separated, one header line ``Name (unit)``: time, gap, normal
  force, ...; ~4 ms sampling, starting at rest before the compression): the contact point
  is found from the force (:func:`recordings.rheometer_segments.find_contact`), the rows
  before it are dropped (they give the baseline noise); H = gap at contact.
* **TRIOS workbook** ``.xls``/``.xlsx``: a ``Details`` sheet and one sheet per procedure
  step (title row, names row, units row, data).  An ``Axial`` step (Gap, Axial force) is a
  compression that starts at contact: H = its first gap.  A ``Peak hold`` step (Stress,
  Shear rate, Step time) after an ``Axial`` preload is a torsion at constant rim shear rate:
  shear = the time integral of the reported rim shear rate (= rate x step time at a constant
  rate); torque from the reported rim stress, T = tau pi R^3 / 2 (TRIOS: tau = 2 T / (pi R^3));
  the torsion runs at the gap the preload left, which is taken as the height H (the
  reference state of the torsion is the preloaded specimen; the gap at the first contact is
  kept as ``contact_gap_mm``, the axial force at the end of the preload as ``preload_mN``).
  TRIOS's ``Normal stress`` is 2 F / (pi R^2) (its normal stress constant), so the nominal
  stress is always computed from the axial force; the recorded normal force of the torsion
  is kept as the extra column ``normal_force_mN`` (it carries the preload and its
  relaxation, not the Poynting effect, so ``axial_force_mN`` stays empty).
* **processed curve** ``.xlsx`` (one sheet, names ``Stretch``/``Shear`` and ``Stress``,
  units ``[-]``/``[kPa]``, loading only at 0.2 %/s): a ``compression_tension`` (tension) or
  ``torsion`` series as given, at a uniform pseudo time (0.2 %/s); the schema requires a
  torque for torsion rows, so it is computed from the stress as above and the stress is
  kept as ``shear_stress_kPa``.  These files hold no gap: the height is ``height_mm`` if
  given, else the mean contact height of the raw files of the same material in the same
  import (``height_source`` says which).

Conventions: compression has stretch = gap / H < 1 and negative nominal stress
-F / (pi R^2) (the instrument's axial force is positive in compression); ``axial_force_mN``
of compression rows is -F; the instrument's zero of the force is kept (no tare).  Loading
moves towards more compression (or more shear/tension), unloading away; a cycle starts with
each loading ramp after an unloading.  Holds (gap nearly constant, or a gap reading that
stalls) are dropped, since the recordings table knows only loading and unloading.  Each ramp
is resampled to ``points`` bin averages of equal width of the control.  The gap of each
point (the reading, interpolated between its refreshes; stretch = gap_mm / H) is kept as
``gap_mm``, so that a wrong contact point stays diagnosable.  ``in_contact`` (1/0, compression
rows) marks the points recorded with the plate on the specimen: after a lift-off on
unloading (the force back at zero within ``CONTACT_BAND`` noise SDs to the ramp's end) and
before the re-contact on reloading it is 0; the events are listed in the specimens table
(``contact_events``) and import.md.  The specimens of raw exports have ``ends = unglued``
(sandblasted plates, no glue: the model lets the top plate lift off instead of pulling);
processed curves, which include tension, ``glued``.  Noise (``noise.json``): see
:func:`_noise`.

Every problem raises :class:`RheometerError` (a ``ValueError``) with one line naming the
file, the sheet and the row (spreadsheet rows as the spreadsheet shows them, from 1) or the
line of a text file.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd

from brain_fe.io import staged_directory, write_json_atomic, write_text_atomic
from brain_fe.vocabulary import (
    AXIAL_FORCE,
    CHANNELS,
    COMPRESSION_TENSION,
    HOLD,
    LOADING,
    NOMINAL_STRESS,
    SHEAR,
    SHEAR_STRESS,
    STRETCH,
    TIME,
    TORQUE,
    TORSION,
    UNLOADING,
    torque_mNmm,
)

from . import rheometer_segments as seg
from .rheometer_segments import RheometerError, Table, read_txt, read_workbook
from .schema import RECORDING_COLUMNS, SPECIMEN_COLUMNS
from .tables import read_recordings, read_specimens, write_table

log = logging.getLogger(__name__)

SUFFIXES = (".txt", ".xls", ".xlsx")
DEFAULT_RADIUS_MM = 4.0
DEFAULT_POINTS = 20
PROCESSED_RATE = 0.002  # 0.2 %/s: the rate of the processed curves (their pseudo time)
MIN_REST = 10  # fewest samples at rest for a rest-noise estimate
TIME_NAMES = ("step time", "time")
FORCE_NAMES = ("normal force", "axial force")
CONTACT_BAND = 3.0  # a resampled force within this many noise SDs of zero: plate off specimen


# ------------------------------------------------------------------------------ one file
def _amplitude(excursion: float) -> float:
    """The largest excursion rounded up to 0.01 (never below the data)."""
    return math.ceil(round(excursion * 100.0, 6)) / 100.0


def _ramps_out(res: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    cycle = np.rint(res["cycle"].to_numpy(float)).astype(np.int64)
    return cycle, seg.ramp_ids(cycle, res["branch"].to_numpy(object))


def _noise(t, y, bins, ramps, res_y, res_ramps, n_per_bin, rest_sd=math.nan) -> dict:
    """Noise of one channel (raw samples ``y`` of the kept ramps, in the channel's unit).

    ``sd`` (written to noise.json): the SD of the mean of m raw samples, m the median
    samples per resampling bin, measured on the raw ramps (:func:`seg.block_sd`), i.e. the
    noise of a resampled point whatever the colour of the raw noise.  For comparison:
    ``moving``, the raw SD within the bins about a straight line in time (drive vibration
    included); ``rest``, the raw SD at rest before contact (linear trend removed);
    ``white``, the rest SD (or the moving SD without a rest) divided by sqrt(n_eff), n_eff
    = m / the channel's repeat factor (sample-and-hold channels refresh every few samples):
    the resampled noise if the raw noise were white; ``check``, the second-difference SD
    of the resampled curve itself.
    """
    m = max(int(round(float(np.median(n_per_bin)))), 1)
    moving = seg.bin_sd(t, y, bins)
    n_eff = max(m / seg.repeat_factor(y), 1.0)
    base = rest_sd if math.isfinite(rest_sd) else moving
    return {"sd": seg.block_sd(y, ramps, m), "m": m, "moving": moving, "rest": rest_sd,
            "white": base / math.sqrt(n_eff), "check": seg.second_diff_sd(res_y, res_ramps)}


def _axial(table: Table, sid: str, radius: float, points: int, detect: bool) -> tuple:
    """A compression trace (raw .txt with contact detection, or an Axial step)."""
    t = table.column(TIME_NAMES, "time")
    table.increasing(t, "time")
    gap = table.column(("gap",), "length")
    force = table.column(FORCE_NAMES, "force")
    if t.size < 2 * MIN_REST:
        raise RheometerError(f"{table.where}: only {t.size} samples")
    gr = seg.reconstruct(t, gap)
    area = math.pi * radius**2
    if detect:
        try:
            c = seg.find_contact(t, gr, force)
        except ValueError as exc:
            raise RheometerError(f"{table.where}: {exc}") from None
        start, h, unc, preload = c.index, c.gap_mm, c.uncertainty_mm, c.baseline_mN
        rest_sd = c.baseline_sd_mN
    else:
        start, h, unc, preload = 0, float(gap[0]), math.nan, float(force[0])
        moved = np.abs(gap - gap[0]) > seg.MOTION_FRACTION * np.ptp(gap)
        n_rest = int(np.argmax(moved)) if moved.any() else gap.size
        rest_sd = seg.detrended_sd(t[:n_rest], force[:n_rest])[0] if n_rest >= MIN_REST \
            else math.nan
    tt, stretch, F = t[start:] - (t[start] if detect else 0.0), gr[start:] / h, force[start:]
    branch, cycle = seg.segment(tt, stretch, -1)
    keep = branch != HOLD
    if not keep.any():
        raise RheometerError(f"{table.where}: the gap never moves after contact")
    ramps = seg.ramp_ids(cycle[keep], branch[keep])
    bins = seg.bin_index(stretch[keep], ramps, points)
    frame = pd.DataFrame({TIME: tt[keep], STRETCH: stretch[keep], "gap_mm": gr[start:][keep],
                          "force": F[keep], "cycle": cycle[keep], "branch": branch[keep]})
    res = seg.resample(frame, bins)
    cyc, runs = _ramps_out(res)
    stress = -res["force"].to_numpy() / area
    amp = _amplitude(1.0 - float(res[STRETCH].min()))
    rows = pd.DataFrame({"specimen": sid, "test": COMPRESSION_TENSION, "amplitude": amp,
                         "cycle": cyc, "branch": res["branch"].to_numpy(object),
                         TIME: res[TIME].to_numpy(), STRETCH: res[STRETCH].to_numpy(),
                         NOMINAL_STRESS: stress, AXIAL_FORCE: -res["force"].to_numpy(),
                         "gap_mm": res["gap_mm"].to_numpy()})
    noise = _noise(tt[keep], -F[keep] / area, bins, ramps, stress, runs, res["n"].to_numpy(),
                   rest_sd / area)
    off = seg.out_of_contact(stress, rows["branch"].to_numpy(object), runs,
                             CONTACT_BAND * noise["sd"])
    rows["in_contact"] = (~off).astype(np.int64)
    events = _contact_events(off, cyc, runs, rows)
    holds = _holds(tt, branch, keep)
    spec = {"height_mm": h, "ends": "unglued", "contact_gap_mm": h,
            "contact_uncertainty_mm": unc,
            "preload_mN": preload, "height_source": "contact" if detect else "first gap",
            "contact_events": "; ".join(events) or "none"}
    if detect:
        k1, k2 = seg.CONTACT_K
        where = (f"contact gap {h:.3f} ± {unc:.3f} mm (k = {k1:g}/{k2:g}"
                 + (", force rose with the first motion: in contact at rest)" if c.at_rest
                    else ")"))
    else:
        where = f"starts at contact, H = first gap {h:.3f} mm"

    info = (f"compression_tension, amplitude {amp:.2f}, {int(cyc.max())} cycle(s), {where}, "
            f"force at start {preload:.1f} mN, {len(rows)} points in {runs.max() + 1} "
            f"ramps, {holds}, "
            + (f"{int(off.sum())} points out of contact ({'; '.join(events)})" if events
               else "in contact throughout"))
    return spec, rows, {"stress": noise}, info


def _contact_events(off: np.ndarray, cyc: np.ndarray, ramps: np.ndarray,
                    rows: pd.DataFrame) -> list[str]:
    """Lift-off (the first point off the specimen on an unloading ramp) and re-contact (the
    first point in contact after a loading ramp's opening points off it), by cycle;
    ``cyc`` and ``ramps``: cycle and ramp number of each row."""
    out = []
    stretch = rows[STRETCH].to_numpy()
    branch = rows["branch"].to_numpy(object)
    for a, b in seg.runs(ramps):
        o = off[a:b]
        if not o.any():
            continue
        if branch[a] == UNLOADING:
            i = a + int(np.argmax(o))
            out.append(f"lift-off in cycle {cyc[a]} at stretch {stretch[i]:.3f}")
        elif not o.all():
            i = a + int(np.argmin(o))
            out.append(f"re-contact in cycle {cyc[a]} at stretch {stretch[i]:.3f}")
        else:
            out.append(f"no contact in cycle {cyc[a]} loading")
    return out


def _holds(t, branch, keep) -> str:
    hold = ~keep
    runs = [(a, b) for a, b in seg.runs(hold.astype(int)) if hold[a]]
    inner = [(a, b) for a, b in runs if a > 0 and b < t.size]
    dur = sum(t[min(b, t.size - 1)] - t[a] for a, b in inner)
    return (f"{len(inner)} hold(s) within the test dropped ({dur:.2f} s)" if inner
            else "no hold within the test")


def _torsion(hold: Table, axial: Table, sid: str, radius: float, points: int) -> tuple:
    """A Peak hold step (constant rim shear rate) after an Axial preload."""
    t = hold.column(TIME_NAMES, "time")
    hold.increasing(t, "step time")
    rate = hold.column(("shear rate",), "rate")
    tau = hold.column(("stress",), "stress")
    gap = axial.column(("gap",), "length")
    fa = axial.column(FORCE_NAMES, "force")
    h, h0, preload = float(gap[-1]), float(gap[0]), float(fa[-1])
    shear = np.concatenate([[rate[0] * t[0]], 0.5 * (rate[1:] + rate[:-1]) * np.diff(t)])
    shear = np.cumsum(shear)
    torque = torque_mNmm(tau, radius)
    branch, cycle = seg.segment(t, shear, +1)
    keep = (branch == LOADING) & (cycle == 1)
    if not keep.any():
        raise RheometerError(f"{hold.where}: the shear never increases")
    frame = pd.DataFrame({TIME: t[keep], SHEAR: shear[keep], TORQUE: torque[keep],
                          SHEAR_STRESS: tau[keep], "cycle": 1, "branch": LOADING})
    if hold.has("normal stress") and axial.has("normal stress"):
        ns_a = axial.column(("normal stress",), "stress")
        ok = np.abs(fa) > 0
        constant = float(np.median(ns_a[ok] / fa[ok])) if ok.any() else math.nan
        frame["normal_force_mN"] = hold.column(("normal stress",), "stress")[keep] / constant
    bins = seg.bin_index(shear[keep], np.zeros(int(keep.sum()), int), points)
    res = seg.resample(frame, bins)
    cyc, runs = _ramps_out(res)
    amp = _amplitude(float(np.abs(res[SHEAR]).max()))
    rows = pd.DataFrame({"specimen": sid, "test": TORSION, "amplitude": amp, "cycle": cyc,
                         "branch": res["branch"].to_numpy(object), TIME: res[TIME].to_numpy(),
                         SHEAR: res[SHEAR].to_numpy(), TORQUE: res[TORQUE].to_numpy(),
                         SHEAR_STRESS: res[SHEAR_STRESS].to_numpy()})
    if "normal_force_mN" in res:
        rows["normal_force_mN"] = res["normal_force_mN"].to_numpy()
    noise = _noise(t[keep], torque[keep], bins, np.zeros(bins.size, int),
                   rows[TORQUE].to_numpy(), runs, res["n"].to_numpy())
    spec = {"height_mm": h, "ends": "unglued", "contact_gap_mm": h0,
            "contact_uncertainty_mm": math.nan,
            "preload_mN": preload, "height_source": "gap after the preload"}
    info = (f"torsion, amplitude {amp:.2f}, loading only, preload {preload:.0f} mN to gap "
            f"{h:.3f} mm (first contact {h0:.3f} mm), shear stress at start "
            f"{tau[0]:.3f} kPa, {len(rows)} points, {int((~keep).sum())} slow start-up "
            "samples dropped")
    return spec, rows, {"torque": noise}, info


def _processed(curve: Table, sid: str, radius: float) -> tuple:
    """A processed curve (Stretch or Shear, Stress [kPa]), loading only."""
    stress = curve.column(("stress",), "stress")
    test = COMPRESSION_TENSION if curve.has("stretch") else TORSION
    x = curve.column(("stretch",) if test == COMPRESSION_TENSION else ("shear",), "ratio")
    exc = np.abs(x - (1.0 if test == COMPRESSION_TENSION else 0.0))
    back = np.flatnonzero(np.diff(exc) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise RheometerError(f"{curve.where}, row {curve.numbers[i]}: the curve turns back "
                             "(a processed curve must be one loading ramp)")
    t = exc / PROCESSED_RATE
    amp = _amplitude(float(exc.max()))
    rows = pd.DataFrame({"specimen": sid, "test": test, "amplitude": amp, "cycle": 1,
                         "branch": LOADING, TIME: t})
    if test == COMPRESSION_TENSION:
        rows[STRETCH] = x
        rows[NOMINAL_STRESS] = stress
        rows[AXIAL_FORCE] = stress * math.pi * radius**2
        ch, values = "stress", stress
    else:
        rows[SHEAR] = x
        rows[TORQUE] = torque_mNmm(stress, radius)
        rows[SHEAR_STRESS] = stress
        ch, values = "torque", rows[TORQUE].to_numpy()
    sd = seg.second_diff_sd(values, np.zeros(values.size, int))
    noise = {"sd": sd, "m": 1, "moving": math.nan, "rest": math.nan, "white": math.nan,
             "check": sd}
    # a tension curve needs a grip: processed curves are taken as glued
    spec = {"height_mm": math.nan, "ends": "glued", "contact_gap_mm": math.nan,
            "contact_uncertainty_mm": math.nan, "preload_mN": math.nan, "height_source": ""}
    kind = "tension" if test == COMPRESSION_TENSION else "shear"
    info = (f"{test} ({kind}, processed curve), amplitude {amp:.2f}, loading only, "
            f"{len(rows)} points as given, pseudo time at {100 * PROCESSED_RATE:g} %/s, no "
            "raw signal: noise from the curve's second differences (a lower bound if the "
            "curve was smoothed)")
    return spec, rows, {ch: noise}, info


def import_file(path, sid: str, radius_mm: float = DEFAULT_RADIUS_MM,
                points: int = DEFAULT_POINTS) -> tuple:
    """(specimens fields, recordings rows, noise per channel, report text) of one export."""
    path = Path(path)
    if path.suffix.lower() == ".txt":
        return _axial(read_txt(path), sid, radius_mm, points, detect=True)
    sheets = read_workbook(path)
    hold = next((s for s in sheets.values() if s.has("shear rate") and s.has("stress")), None)
    axial = next((s for s in sheets.values() if s.has("gap") and s.has(*FORCE_NAMES)), None)
    curve = next((s for s in sheets.values() if s.has("stretch", "shear") and s.has("stress")),
                 None)
    if hold is not None:
        if axial is None:
            raise RheometerError(f"{hold.where}: a torsion step needs the preceding Axial "
                                 "step (Gap, Axial force) for the height and the preload")
        return _torsion(hold, axial, sid, radius_mm, points)
    if axial is not None:
        return _axial(axial, sid, radius_mm, points, detect=False)
    if curve is not None:
        return _processed(curve, sid, radius_mm)
    raise RheometerError(f"{path}: no sheet of a known layout (Gap + Axial force; Stress + "
                         f"Shear rate; Stretch or Shear + Stress); sheets: "
                         f"{', '.join(sheets) or 'none with a header'}")


# ------------------------------------------------------------------------------ many files
def find_exports(paths, region: str | None = None) -> list[tuple[Path, str, str]]:
    """(file, region, brain) of every export under ``paths`` (files or folders, searched
    recursively for .txt/.xls/.xlsx, in sorted order).  ``region`` (the material) is the
    first folder below a given folder when the file lies two or more folders deep in it,
    else that folder's name; for a file given directly, its grandparent folder's name;
    ``region`` overrides.  ``brain`` (the group) is the file's folder."""
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file()
                           and f.suffix.lower() in SUFFIXES and not f.name.startswith((".", "~$")))
            if not found:
                raise RheometerError(f"{p}: no .txt, .xls or .xlsx file in this folder")
            for f in found:
                rel = f.relative_to(p).parts
                out.append((f, region or (rel[0] if len(rel) >= 3 else p.resolve().name),
                            f.parent.name))
        elif p.is_file():
            if p.suffix.lower() not in SUFFIXES:
                raise RheometerError(f"{p}: not a rheometer export (.txt, .xls or .xlsx)")
            out.append((p, region or p.resolve().parent.parent.name, p.resolve().parent.name))
        else:
            raise RheometerError(f"{p}: no such file or folder")
    return out


def _fmt(v: float, spec: str = ".3g") -> str:
    return "n/a" if not math.isfinite(v) else format(v, spec)


def import_exports(paths, out_dir, *, radius_mm: float = DEFAULT_RADIUS_MM,
                   points: int = DEFAULT_POINTS, region: str | None = None,
                   height_mm: float | None = None) -> dict:
    """Import every export under ``paths`` into ``out_dir``: specimens.csv, recordings.csv,
    noise.json (``{specimen: {channel: SD}}`` in the channel's unit, at the resampled level)
    and import.md (one line per file).  The tables are validated with
    :func:`recordings.tables.read_recordings` before anything appears in ``out_dir``;
    nothing is written when any file fails.  ``height_mm`` is the height of processed curves
    (default: the mean contact height of the raw files of the same material).  Returns a
    summary (``specimens``, ``rows``, ``groups``)."""
    if not (math.isfinite(radius_mm) and radius_mm > 0):
        raise RheometerError(f"the plate radius must be a positive number of mm, got {radius_mm}")
    if points < 2:
        raise RheometerError(f"need at least 2 points per ramp, got {points}")
    files = find_exports(paths, region)
    seen: dict[str, Path] = {}
    results = []
    for f, reg, brain in files:
        sid = f"{reg}/{f.stem}"
        if sid in seen:
            raise RheometerError(f"{f}: specimen id {sid!r} again (first from {seen[sid]}); "
                                 "give the files distinct names")
        seen[sid] = f
        spec, rows, noise, info = import_file(f, sid, radius_mm, points)
        log.info("%s: %s", f, info)
        results.append(({"specimen": sid, "region": reg, "brain": brain, "radius_mm": radius_mm,
                         **spec, "source": str(f)}, rows, noise, info))
    _fill_heights(results, height_mm)
    specimens = pd.DataFrame([r[0] for r in results])
    specimens = specimens[[*SPECIMEN_COLUMNS, *[c for c in specimens if c not in
                                                SPECIMEN_COLUMNS]]]
    rec = pd.concat([r[1] for r in results], ignore_index=True)
    rec = rec.reindex(columns=[*RECORDING_COLUMNS, *sorted(set(rec) - set(RECORDING_COLUMNS))])
    noise = {r[0]["specimen"]: {ch: float(v["sd"]) for ch, v in r[2].items()} for r in results}
    report = _report(results, radius_mm, points)
    with staged_directory(out_dir) as stage:
        write_table(specimens, stage / "specimens.csv")
        write_table(rec, stage / "recordings.csv")
        try:
            read_recordings(stage / "recordings.csv", read_specimens(stage / "specimens.csv"))
        except ValueError as exc:
            raise RheometerError(f"the imported tables fail validation: {exc}") from None
        write_json_atomic(stage / "noise.json", noise, indent=2)
        write_text_atomic(stage / "import.md", report)
    groups = specimens.groupby(["region", "brain"], sort=False).size()
    return {"specimens": len(specimens), "rows": len(rec),
            "groups": {f"{r}/{b}": int(n) for (r, b), n in groups.items()}}


def _fill_heights(results, height_mm) -> None:
    """Processed curves have no gap: ``height_mm``, else the mean contact height of the raw
    files of the same material."""
    for spec, _, _, _ in results:
        if math.isfinite(spec["height_mm"]):
            continue
        if height_mm is not None:
            spec["height_mm"], spec["height_source"] = height_mm, "--height-mm"
            continue
        same = [s["height_mm"] for s, *_ in results if s["region"] == spec["region"]
                and s["height_source"] in ("contact", "first gap")]
        if not same:
            raise RheometerError(f"{spec['source']}: a processed curve has no gap and no raw "
                                 f"file of {spec['region']!r} is imported with it; give "
                                 "--height-mm")
        spec["height_mm"] = float(np.mean(same))
        spec["height_source"] = f"assumed: mean of {len(same)} {spec['region']} raw files"


def _report(results, radius_mm: float, points: int) -> str:
    lines = ["# Import of rheometer exports", "",
             f"Plate radius {radius_mm:g} mm; {points} points per ramp (bin averages); "
             "holds dropped; nominal stress -F / (pi R^2), negative in compression.",
             "Noise per channel (noise.json): SD of a resampled point, measured as the scatter "
             "of means of m raw samples along the raw ramps (bins of m); in brackets the raw "
             "SD while moving and at rest before contact, the 'white' conversion (raw SD at "
             "rest, else while moving) / sqrt(n_eff), and the second-difference SD of the "
             "resampled curve as a check.",
             ""]
    for spec, _rows, noise, info in results:
        ns = "; ".join(f"{ch} {_fmt(v['sd'])} {CHANNELS[ch].unit} (bins of {v['m']}; raw "
                       f"moving {_fmt(v['moving'])}, at rest {_fmt(v['rest'])}; white "
                       f"{_fmt(v['white'])}; check {_fmt(v['check'])})"
                       for ch, v in noise.items())
        lines.append(f"- `{spec['source']}` -> `{spec['specimen']}` (region {spec['region']}, "
                     f"brain {spec['brain']}, H {spec['height_mm']:.3f} mm, "
                     f"{spec['height_source']}): {info}; noise {ns}")
    return "\n".join(lines) + "\n"
