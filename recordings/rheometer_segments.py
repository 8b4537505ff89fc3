"""Reading and signal processing of rheometer exports for :mod:`recordings.rheometer`.

* :func:`read_txt`, :func:`read_workbook`: the tables of a tab-separated trace or of a
  TRIOS workbook's step sheets (:class:`Table`: column names, units, cells, and the line or
  spreadsheet row of each data row for the one-line :class:`RheometerError`);
  :meth:`Table.column` converts a column to the project's units (mm, mN, kPa, s, 1/s).

The signal functions below take plain arrays in the project's units and never touch files.

* :func:`reconstruct`: a sample-and-hold reading (the gap of a TRIOS export is refreshed
  only every few samples) as the piecewise-linear path through its update instants; a
  reading that stalls for longer than ``STALL_FACTOR`` update intervals stays flat (it is a
  hold, or the reading froze) and is not bridged by a ramp.
* :func:`find_contact`: the contact point from the normal force (see its docstring).
* :func:`segment`: cycles and branches from the control signal; holds are marked.
* :func:`resample`: bin averages, ``n`` bins of equal width of the control per ramp.
* :func:`out_of_contact`: the resampled points recorded while the plate was off the
  specimen (lift-off on unloading, before re-contact on reloading).
* :func:`detrended_sd`, :func:`bin_sd`, :func:`second_diff_sd`, :func:`repeat_factor`:
  the noise of a channel at rest, within the resampling bins, and of a resampled curve.
"""

from __future__ import annotations

import codecs
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from brain_fe.vocabulary import HOLD, LOADING, UNLOADING

log = logging.getLogger(__name__)

CONTACT_K = (3.0, 10.0)  # the two thresholds (baseline SDs) of the contact detection
SMOOTH = 5  # samples of the centred moving average applied to the force for the detection
MIN_BASELINE = 20  # fewest samples of a pre-contact baseline
STALL_FACTOR = 5.0  # a reading not refreshed for this many median update intervals: a stall
HOLD_FRACTION = 0.05  # slower than this fraction of the typical ramp speed: a hold
MIN_RUN = 3  # shorter runs of one direction are holds (single-sample jumps of the reading)
MOTION_FRACTION = 1e-3  # the plate starts moving when the gap leaves its first value by this
# fraction of the whole travel (a reading at rest flickers by its resolution)
PRELOAD_SECANT = 5.0  # preloaded traces: secant stiffness from the preload to 5x the preload
OFF_SHARE = 0.8  # lift-off / before re-contact: this share of the points within the band
MIN_BIN = 4  # fewest samples of a bin used for the within-bin noise
_TRUNC_3 = 1.0 - 6.0 * math.exp(-4.5) / math.sqrt(2.0 * math.pi) / math.erf(3.0 / math.sqrt(2.0))


_UNITS = {  # unit text -> factor to the project's unit
    "length": {"µm": 1e-3, "μm": 1e-3, "um": 1e-3, "mm": 1.0, "m": 1e3},
    "force": {"N": 1e3, "mN": 1.0},
    "stress": {"Pa": 1e-3, "kPa": 1.0, "MPa": 1e3},
    "time": {"s": 1.0, "ms": 1e-3, "min": 60.0},
    "rate": {"1/s": 1.0, "s-1": 1.0, "s^-1": 1.0},
    "ratio": {"-": 1.0, "": 1.0, "%": 0.01},
}


class RheometerError(ValueError):
    """An export cannot be imported; one line naming the file, sheet and row or line."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


# ------------------------------------------------------------------------------ reading
def _empty(cell) -> bool:
    return cell is None or (isinstance(cell, float) and math.isnan(cell)) or \
        (isinstance(cell, str) and not cell.strip())


@dataclass
class Table:
    """One table of an export: names and units of its columns, cells as read, and where each
    data row is (``line N`` of a text file, ``row N`` of a sheet)."""

    where: str
    place: str
    header: int
    unit_row: int
    names: list[str]
    units: list[str]
    cells: np.ndarray
    numbers: np.ndarray

    def _find(self, aliases) -> int | None:
        low = [n.strip().lower() for n in self.names]
        return next((low.index(a) for a in aliases if a in low), None)

    def has(self, *aliases: str) -> bool:
        return self._find(aliases) is not None

    def column(self, aliases: tuple[str, ...], kind: str) -> np.ndarray:
        """The numbers of a column in the project's unit (mm, mN, kPa, s, 1/s, fraction)."""
        j = self._find(aliases)
        if j is None:
            raise RheometerError(f"{self.where}, {self.place} {self.header}: no column "
                                 f"{aliases[0]!r} (columns: {', '.join(self.names)})")
        name, unit = self.names[j], self.units[j].strip().strip("[]").strip()
        factors = _UNITS[kind]
        if unit not in factors:
            raise RheometerError(f"{self.where}, {self.place} {self.unit_row}: column {name!r} "
                                 f"has unit {self.units[j]!r}; expected one of "
                                 f"{', '.join(repr(u) for u in factors)}")
        raw = self.cells[:, j]
        num = pd.to_numeric(pd.Series(raw, dtype=object), errors="coerce").to_numpy(float)
        bad = ~np.isfinite(num)
        if bad.any():
            i = int(np.argmax(bad))
            what = "is empty" if _empty(raw[i]) else f"not a number ({str(raw[i]).strip()!r})"
            raise RheometerError(f"{self.where}, {self.place} {self.numbers[i]}: column "
                                 f"{name!r} {what}")
        return num * factors[unit]

    def increasing(self, t: np.ndarray, name: str) -> None:
        back = np.flatnonzero(np.diff(t) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise RheometerError(f"{self.where}, {self.place} {self.numbers[i]}: column "
                                 f"{name!r} does not increase ({t[i]:g} after {t[i - 1]:g})")


def _split_unit(text: str) -> tuple[str, str]:
    m = re.match(r"^(.*?)\s*\(([^()]*)\)\s*$", text)
    return (m.group(1).strip(), m.group(2).strip()) if m else (text.strip(), "")


def _decode(data: bytes) -> str:
    """The text of an export: UTF-16 (with its byte-order mark, or without one when every
    other byte of the start is zero, as Windows writes "Unicode" text), else UTF-8 (a
    mark allowed), else Latin-1."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return data.decode("utf-16")
    head = data[:400]
    if len(head) >= 4:
        for zeros, codec in ((head[1::2], "utf-16-le"), (head[0::2], "utf-16-be")):
            if zeros.count(0) == len(zeros):
                return data.decode(codec, errors="replace")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


_DECIMAL_COMMA = re.compile(r"^\s*[+-]?\d*,\d+(?:[eE][+-]?\d+)?\s*$")


def _decimal_commas(rows: list[list[str]]) -> bool:
    """Whether the numbers of a tab-separated export are written with decimal commas (a
    European setting of the instrument's PC): some cell is a number with one comma, and
    no cell holds a decimal point."""
    cells = [c for r in rows for c in r]
    return not any("." in c for c in cells) and any(_DECIMAL_COMMA.match(c) for c in cells)


def read_txt(path) -> Table:
    """A tab-separated export: one header line of ``Name (unit)``, then numbers (decimal
    points, or decimal commas throughout the file); UTF-8, Latin-1 or UTF-16 text."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise RheometerError(f"{path}: cannot read ({e.strerror or e})") from None
    lines = _decode(data).splitlines()
    header = [h.strip() for h in lines[0].split("\t")] if lines else []
    while header and not header[-1]:
        header.pop()
    if len(header) < 2:
        raise RheometerError(f"{path}, line 1: not a tab-separated export (expected a header "
                             "line of column names separated by tabs)")
    rows, numbers = [], []
    for i, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        f = line.split("\t")
        if any(e.strip() for e in f[len(header):]):
            raise RheometerError(f"{path}, line {i}: {len(f)} fields, but the header names "
                                 f"{len(header)} columns")
        rows.append(f[:len(header)] + [""] * (len(header) - len(f)))
        numbers.append(i)
    if not rows:
        raise RheometerError(f"{path}: no data lines below the header")
    if _decimal_commas(rows):
        log.info("%s: numbers with decimal commas", path)
        rows = [[c.replace(",", ".") for c in r] for r in rows]
    names, units = zip(*(_split_unit(h) for h in header), strict=True)
    return Table(str(path), "line", 1, 1, list(names), list(units),
                 np.array(rows, dtype=object), np.array(numbers))


def read_workbook(path) -> dict[str, Table]:
    """The step sheets of a TRIOS workbook (all but ``Details``), each with a names row and a
    units row (a title row above them is skipped)."""
    try:
        sheets = pd.read_excel(path, sheet_name=None, header=None, dtype=object,
                               keep_default_na=False)  # a cell "n/a" is named as such
    except Exception as exc:  # noqa: BLE001 - xlrd/openpyxl/zip errors of a damaged file
        msg = " ".join(str(exc).split())[:120]
        raise RheometerError(f"{path}: cannot read as an Excel workbook "
                             f"({type(exc).__name__}: {msg})") from None
    out = {}
    for name, raw in sheets.items():
        if str(name).strip().lower() == "details":
            continue
        cells = raw.to_numpy(object)
        filled = np.array([[not _empty(c) for c in row] for row in cells], dtype=bool)
        heads = np.flatnonzero(filled.sum(axis=1) >= 2) if cells.size else []
        if len(heads) == 0:
            continue
        h = int(heads[0])
        cols = np.flatnonzero(filled[h])
        names = [str(c).strip() for c in cells[h, cols]]
        units = [("" if h + 1 >= len(cells) or _empty(c) else str(c).strip())
                 for c in (cells[h + 1, cols] if h + 1 < len(cells) else [None] * len(cols))]
        data = cells[h + 2:, :][:, cols]
        rows = np.arange(h + 2, len(cells)) + 1
        keep = filled[h + 2:, :][:, cols].any(axis=1)
        where = f"{path}, sheet {str(name)!r}"
        if not keep.any():
            raise RheometerError(f"{where}, row {h + 1}: no data rows below the header")
        out[str(name)] = Table(where, "row", h + 1, h + 2, names, units, data[keep], rows[keep])
    return out


# ------------------------------------------------------------------------------ signals
def reconstruct(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The path of a sample-and-hold reading ``x(t)``: linear between the samples where the
    reading changes, flat across stalls (no refresh for ``STALL_FACTOR`` times the median
    refresh interval of the moving parts)."""
    x = np.asarray(x, float)
    knots = np.concatenate([[0], np.flatnonzero(np.diff(x) != 0) + 1])
    if knots.size < 3:
        return x.copy()
    dtk = np.diff(t[knots])
    step = np.abs(np.diff(x[knots]))
    moving = step > 0.1 * np.median(step)  # not the flicker of a reading at rest
    stall = STALL_FACTOR * float(np.median(dtk[moving] if moving.any() else dtk))
    k = np.searchsorted(knots, np.arange(x.size), side="right") - 1
    nxt = np.minimum(k + 1, knots.size - 1)
    a, b = knots[k], knots[nxt]
    span = t[b] - t[a]
    bridge = (b > a) & (span <= stall)
    frac = np.where(bridge, (t - t[a]) / np.where(span > 0, span, 1.0), 0.0)
    return x[a] + frac * (x[b] - x[a])


def moving_average(y: np.ndarray, w: int = SMOOTH) -> np.ndarray:
    """Centred moving average of ``w`` samples (shorter at the ends)."""
    y = np.asarray(y, float)
    if w <= 1 or y.size < w:
        return y.copy()
    c = np.concatenate([[0.0], np.cumsum(y)])
    h = w // 2
    lo = np.clip(np.arange(y.size) - h, 0, y.size)
    hi = np.clip(np.arange(y.size) + h + 1, 0, y.size)
    return (c[hi] - c[lo]) / (hi - lo)


def detrended_sd(t: np.ndarray, y: np.ndarray) -> tuple[float, int]:
    """SD of ``y`` about its straight-line fit in ``t`` (``n - 2`` degrees of freedom), and
    the degrees of freedom; NaN and 0 for fewer than 4 samples."""
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if y.size < 4 or np.ptp(t) == 0:
        return math.nan, 0
    r = y - np.polyval(np.polyfit(t - t.mean(), y, 1), t - t.mean())
    return math.sqrt(float(r @ r) / (y.size - 2)), y.size - 2


def pooled(parts: list[tuple[float, int]]) -> float:
    """Pooled SD of several (SD, degrees of freedom) estimates; NaN without any."""
    ok = [(s, d) for s, d in parts if d > 0 and math.isfinite(s)]
    if not ok:
        return math.nan
    return math.sqrt(sum(s * s * d for s, d in ok) / sum(d for _, d in ok))


@dataclass(frozen=True)
class Contact:
    """The contact point of a raw trace (indices into the trace)."""

    index: int  # first sample in contact (gap at or below ``gap_mm``)
    gap_mm: float  # the specimen height H
    uncertainty_mm: float  # the gap range between the two detections
    baseline: slice  # the pre-contact samples used for the baseline
    baseline_mN: float  # mean force of the baseline (at its end, trend included)
    baseline_sd_mN: float  # its SD about a straight line (raw samples)
    at_rest: bool  # the force rose with the first motion: in contact (preloaded) at rest


def find_contact(t, gap, force, k: tuple[float, float] = CONTACT_K,
                 smooth: int = SMOOTH) -> Contact:
    """Contact from the normal force of a trace that starts before contact (or at rest).

    The baseline is the rest before the plate first moves (by more than ``MOTION_FRACTION``
    of the whole travel; at least ``MIN_BASELINE``
    samples; if the plate moves from the start, the first fifth of the samples up to the
    force peak).  On the force smoothed over ``smooth`` samples, the detection for a
    threshold ``k`` is the first sample after which the force stays above the baseline
    (its straight-line trend at the end of the window) by ``k`` SDs of the smoothed baseline
    until the peak force of the first compression.  With the two thresholds k1 < k2 the
    detections give gaps g1 >= g2; the force rises about linearly after contact, so the
    contact gap is extrapolated to zero excess force, ``H = g1 + (g1 - g2) k1 / (k2 - k1)``
    (not above the gap at which the plate started, nor below g2), and its uncertainty is
    ``g1 - g2`` (the range over which the criterion is ambiguous), at least the travel
    over ``smooth // 2 + 1`` samples before the first detection (the time resolution of
    the smoothed detection).  When the force rises with the very first
    motion (``at_rest``), the plate already touched the specimen at rest under the baseline
    force (a preload): H is then the rest gap, and the uncertainty is at least the
    compression that preload caused, extrapolated with the secant stiffness of the first
    loading up to ``PRELOAD_SECANT`` times the preload.  Raises ``ValueError``
    when the force never rises clearly above the baseline.
    """
    t, gap, force = (np.asarray(a, float) for a in (t, gap, force))
    n = gap.size
    still = np.abs(gap - gap[0]) <= MOTION_FRACTION * np.ptp(gap)
    start = int(np.argmin(still)) if not still.all() else n
    fs = moving_average(force, smooth)
    # the first compression: from the start of motion to the first minimum of the gap
    lo_gap = start + int(np.argmin(gap[start:])) if start < n else n - 1
    peak = start + int(np.argmax(fs[start:lo_gap + 1])) if start < n else n - 1
    if start >= MIN_BASELINE:
        base = slice(0, start)
    else:
        base = slice(0, max(MIN_BASELINE, peak // 5))
        start = base.stop
    if base.stop >= peak or base.stop > n:
        raise ValueError("no pre-contact baseline before the force peak "
                         f"(need {MIN_BASELINE} samples at rest before the compression)")
    tb = t[base]
    coef = np.polyfit(tb - tb.mean(), fs[base], 1)
    level = float(np.polyval(coef, tb[-1] - tb.mean()))
    sd_s = float(np.std(fs[base] - np.polyval(coef, tb - tb.mean()), ddof=2))
    sd_raw, _ = detrended_sd(tb, force[base])
    sd_s = max(sd_s, 1e-12 * max(1.0, abs(level)))
    hits = []
    for kk in k:
        above = fs[start:peak + 1] > level + kk * sd_s
        if not above[-1]:
            raise ValueError(f"no contact: the normal force never rises {kk:g} baseline SDs "
                             f"({kk * sd_s:.3g} mN) above its pre-contact level "
                             f"{level:.3g} mN")
        below = np.flatnonzero(~above)
        hits.append(start + (int(below[-1]) + 1 if below.size else 0))
    g1, g2 = float(gap[hits[0]]), float(gap[hits[1]])
    top = float(gap[base.stop - 1])
    h = g1 + (g1 - g2) * k[0] / (k[1] - k[0])
    h = min(max(h, g2), top)
    # never finer than the travel over the smoothing half-window and one sample before the
    # first detection (the moving average can shift a detection by that much)
    back = max(hits[0] - smooth // 2 - 1, 0)
    step = float(gap[back] - gap[hits[0]])
    unc = max(g1 - g2, step, 0.0)
    at_rest = hits[0] <= start
    if at_rest and level > 0:  # preloaded: how far the rest force compressed the specimen
        up = np.flatnonzero(fs[hits[0]:peak + 1] >= PRELOAD_SECANT * level)
        j = hits[0] + int(up[0]) if up.size else peak
        if fs[j] > level and j > hits[0]:
            unc = max(unc, level * float(gap[hits[0]] - gap[j]) / float(fs[j] - level))
    index = base.stop + int(np.argmax(gap[base.stop:] <= h + 1e-12))
    return Contact(index=index, gap_mm=h, uncertainty_mm=unc, baseline=base,
                   baseline_mN=level, baseline_sd_mN=sd_raw, at_rest=at_rest)


def segment(t, x, loading_sign: int, hold_fraction: float = HOLD_FRACTION,
            min_run: int = MIN_RUN) -> tuple[np.ndarray, np.ndarray]:
    """Branch (``loading``, ``unloading``, ``hold``) and cycle of every sample of a control
    signal ``x(t)`` (already reconstructed).  ``loading_sign`` is the sign of dx/dt when
    loading (-1: compression, the gap or stretch decreases; +1: tension or shear).  Holds:
    speed below ``hold_fraction`` of the typical ramp speed (the median speed of the samples
    moving faster than 1 % of the fastest), or runs of one direction shorter than
    ``min_run`` samples.  A cycle starts with each loading run that follows an unloading."""
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    v = np.gradient(x, t) if x.size > 1 else np.zeros(x.size)
    speed = np.abs(v)
    moving = speed > 0.01 * speed.max() if speed.size else speed > 0
    ref = float(np.median(speed[moving])) if moving.any() else 0.0
    d = np.where(speed > hold_fraction * ref, np.sign(v) * loading_sign, 0).astype(int)
    if ref == 0.0:
        d[:] = 0
    for a, b in runs(d):
        if d[a] != 0 and b - a < min_run:
            d[a:b] = 0
    branch = np.full(x.size, HOLD, dtype=object)
    branch[d > 0] = LOADING
    branch[d < 0] = UNLOADING
    cycle = np.ones(x.size, dtype=np.int64)
    c, unloaded = 1, False
    for a, b in runs(d):
        if d[a] > 0 and unloaded:
            c, unloaded = c + 1, False
        elif d[a] < 0:
            unloaded = True
        cycle[a:b] = c
    return branch, cycle


def runs(v: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs of equal consecutive values."""
    if v.size == 0:
        return []
    edges = np.flatnonzero(v[1:] != v[:-1]) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [v.size]])
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def ramp_ids(cycle: np.ndarray, branch: np.ndarray) -> np.ndarray:
    """Number of the ramp of each sample: runs of one (cycle, branch) in order."""
    key = np.array([f"{c}/{b}" for c, b in zip(cycle, branch, strict=True)], dtype=object)
    ids = np.zeros(key.size, dtype=np.int64)
    if key.size:
        ids[1:] = np.cumsum(key[1:] != key[:-1])
    return ids


def out_of_contact(force: np.ndarray, branch: np.ndarray, ramps: np.ndarray,
                   tol: float, share: float = OFF_SHARE) -> np.ndarray:
    """Which points of a compression were recorded with the plate off the specimen.

    ``force`` is the resampled force (any unit, zero when nothing touches the plate),
    ``tol`` its noise band (e.g. 3 noise SDs).  On an unloading ramp the specimen has lifted
    off at the first point within ``tol`` of zero from which on at least ``share`` of the
    ramp's points are (a moist specimen may first pull on the plate: that is still contact;
    a spike of the drive at the turn does not end the lift-off); on a loading ramp the
    points up to the last within ``tol`` before which at least ``share`` are, are before the
    re-contact.
    """
    off = np.zeros(force.size, dtype=bool)
    small = np.abs(force) <= tol
    for a, b in runs(ramps):
        s = small[a:b]
        if branch[a] == UNLOADING:
            tail = np.cumsum(s[::-1])[::-1] / np.arange(s.size, 0, -1)  # share from i on
            ok = np.flatnonzero(s & (tail >= share))
            if ok.size:
                off[a + ok[0]:b] = True
        elif branch[a] == LOADING:
            head = np.cumsum(s) / np.arange(1, s.size + 1)  # share up to i
            ok = np.flatnonzero(s & (head >= share))
            if ok.size:
                off[a:a + ok[-1] + 1] = True
    return off


def bin_index(x: np.ndarray, ramps: np.ndarray, n: int) -> np.ndarray:
    """Global bin number of every sample: per ramp, ``n`` bins of equal width of ``x``
    between the ramp's extremes (every sample its own bin when a ramp has at most ``n``)."""
    out = np.empty(x.size, dtype=np.int64)
    next_bin = 0
    for a, b in runs(ramps):
        xr = x[a:b]
        if b - a <= n or np.ptp(xr) == 0:
            out[a:b] = next_bin + np.arange(b - a)
            next_bin += b - a
            continue
        edges = np.linspace(xr.min(), xr.max(), n + 1)
        k = np.clip(np.searchsorted(edges, xr, side="right") - 1, 0, n - 1)
        if xr[-1] < xr[0]:  # bins numbered in the direction of travel
            k = n - 1 - k
        out[a:b] = next_bin + k
        next_bin += n
    return out


def resample(frame: pd.DataFrame, bins: np.ndarray) -> pd.DataFrame:
    """Mean of every column of ``frame`` (numbers) per bin, in bin order, plus ``n`` (the
    samples per bin); first-of-bin for object columns (branch)."""
    g = frame.groupby(bins, sort=True)
    num = [c for c in frame.columns if frame[c].dtype.kind in "fiu"]
    out = g[num].mean()
    for c in frame.columns:
        if c not in num:
            out[c] = g[c].first()
    out["n"] = g.size()
    return out.reset_index(drop=True)[[*frame.columns, "n"]]


def bin_sd(t: np.ndarray, y: np.ndarray, bins: np.ndarray) -> float:
    """Noise SD of the raw samples within the resampling bins: the residuals about a
    straight line in time per bin (bins of at least ``MIN_BIN`` samples), pooled."""
    parts = []
    for _, idx in pd.Series(np.arange(bins.size)).groupby(bins):
        if idx.size >= MIN_BIN:
            parts.append(detrended_sd(t[idx.to_numpy()], y[idx.to_numpy()]))
    return pooled(parts)


def repeat_factor(y: np.ndarray) -> float:
    """Mean length of the runs of repeated values (1 for a signal refreshed every sample):
    a sample-and-hold channel has only ``len / factor`` independent samples."""
    y = np.asarray(y)
    if y.size == 0:
        return 1.0
    return y.size / (1 + int(np.count_nonzero(y[1:] != y[:-1])))


def second_diff_sd(y: np.ndarray, ramps: np.ndarray) -> float:
    """Noise SD of a (resampled) curve from its second differences within runs (white noise
    of SD s gives var d = 6 s^2; robust scale of :func:`_mad_sd`)."""
    return _mad_sd(_second_diffs(np.asarray(y, float), np.asarray(ramps)))


def block_sd(y: np.ndarray, ramps: np.ndarray, m: int) -> float:
    """SD of the mean of ``m`` consecutive raw samples, measured on the raw ramps: per ramp
    and for every start offset 0..m-1, the means of consecutive blocks of ``m`` samples and
    their second differences, pooled (robust scale of :func:`_mad_sd`).  No assumption on the
    colour of the noise: vibration that averages out faster than 1/sqrt(m), or slow wander
    that averages out slower, is measured as it is."""
    y = np.asarray(y, float)
    m = max(int(m), 1)
    d = []
    for a, b in runs(np.asarray(ramps)):
        for o in range(min(m, b - a)):
            k = (b - a - o) // m
            if k >= 3:
                means = y[a + o:a + o + k * m].reshape(k, m).mean(axis=1)
                d.append(means[:-2] - 2.0 * means[1:-1] + means[2:])
    return _mad_sd(np.concatenate(d)) if d else math.nan


def _second_diffs(y: np.ndarray, ramps: np.ndarray) -> np.ndarray:
    if y.size < 3:
        return np.empty(0)
    same = ramps[1:] == ramps[:-1]
    return (y[:-2] - 2.0 * y[1:-1] + y[2:])[same[:-1] & same[1:]]


def _mad_sd(d: np.ndarray) -> float:
    """SD of white noise from its second differences ``d``: a MAD scale, then the SD of the
    d within 3 MAD-SDs of the median (truncated-normal consistency factor), / sqrt(6)."""
    if d.size < 3:
        return math.nan
    med = float(np.median(d))
    dev = np.abs(d - med)
    s0 = 1.4826 * float(np.median(dev))
    if s0 <= 0.0:
        return float(np.sqrt(np.mean(dev**2))) / math.sqrt(6.0)
    kept = dev[dev <= 3.0 * s0]
    return math.sqrt(float(np.mean(kept**2)) / _TRUNC_3) / math.sqrt(6.0)
