"""Recordings of the open world: made on a path the diagnosis does not share.

A *world case* is one specimen with its protocol, its truth (base material, zero to two
library effects, or one effect the library does not contain) and its rig noise.  Its
recordings differ from what the diagnosis computes in every way a real test differs:

* **converged mesh** (refinement 3 by default; the diagnosis works on 1, corrected by 2);
* **sub-stepped time integration**: the FE model steps at ``SUBSTEPS`` points per recorded
  interval (never coarser than ``TRUTH_INCREMENT``) and the channels are interpolated (cubic,
  per monotone segment) at the recorded times;
* **the instrument's clock**: samples at a fixed interval from a random phase with a small
  jitter, so no recorded point sits on an FE step or on a turning point of the protocol;
* **rig noise** per channel (:mod:`recordings.noise`): white, low-pass filtered, wander,
  drift from the tare, quantisation, in the channel's unit (the same load cell for every
  test of a specimen);
* **effects outside the library** (:data:`OUTSIDE`), simulated here and nowhere else:

  - ``axial_fibres``: a tension-only fibre family along the specimen axis
    (:class:`brain_fe.materials.AxialFibres`, k2 drawn in [1, 10]);
  - ``stiffness_drift``: the tissue softens over the test session, mu(t) = mu (1 - d
    t / T) with T the session's duration; exact as a scaling of every load for the glued
    one-term Ogden specimen at fixed nu0 (its energy is proportional to mu, so the
    displacement does not depend on mu);
  - ``permanent_set``: the specimen ratchets: its unloaded height grows shorter with every
    compressive excursion (stretch offset proportional to the compressive path travelled)
    and its unloaded twist follows the twist applied (shear offset proportional to the
    loading path); the rig's encoder reports the nominal plate position.

Library effects use the parametrisation of the closed benchmark
(:func:`diagnosis.benchmark.effect_values`).  Effect sizes are calibrated on the working
mesh (cheap) so that the best base fit to the noiseless recordings leaves a misfit of
``target`` noise SDs (RMS); the final recordings are then made on the converged path.  An
effect that the specimen's tests cannot show (below ``VISIBLE`` noise SDs) draws another
specimen (after ``MAX_DRAWS`` the last draw stands and the right answer leaves it out).
For a pair, the label also says how much of each effect its partner cannot mimic
(:func:`visible_beside`): compressibility beside a soft glue layer, for instance, is
hardly ever separable by compression/tension and torsion of glued specimens.  Such a pair
is kept (the benchmark asks for it), and the summary scores the pairs whose tests
separate both effects apart.  For an outside effect, :func:`closest_library` measures how
near the best base model with each library effect alone comes to the truth (a second
Ogden term follows some axial fibre families to a fraction of the noise); it is too
costly for every draw and is run apart (``benchmarks/mimicked_outside.py``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from mpi4py import MPI
from scipy.interpolate import CubicSpline

from brain_fe import geometry as geo
from brain_fe.materials import MaterialModel
from brain_fe.model import ForwardModel
from brain_fe.parameters import Param
from brain_fe.protocols import Protocol, RecordedPath, Step
from brain_fe.vocabulary import (
    CHANNELS,
    COMPRESSION_TENSION,
    CONTROL,
    LOADING,
    NEUTRAL,
    TEST_CHANNELS,
    TIME,
    TORSION,
)
from recordings.noise import RigNoise, add_noise
from recordings.observations import observations
from recordings.synthetic import recordings_table
from simulators.coordinates import model_point
from simulators.fe import FESimulator

from .benchmark import MAX_SIZE, effect_values
from .effects import library, parameter_names
from .fitting import Fit, fit
from .noise import ChannelNoise, NoiseModel
from .selection import Union, compatible
from .series import groups

log = logging.getLogger(__name__)

NU0 = 0.49  # the compressibility of every truth without the compressibility effect
SUBSTEPS = 2  # FE steps per recorded interval of the truth
TRUTH_INCREMENT = 0.01  # largest FE step of the truth (strain; torsion: scaled by A_t/A)
TRUTH_REFINEMENT = 3
CALIBRATION_REFINEMENT = 1
GAP_S = 60.0  # pause between two tests of a session
JITTER = 0.05  # clock jitter, fraction of the sampling interval

OUTSIDE = ("axial_fibres", "stiffness_drift", "permanent_set")
PAIRS = (("viscoelastic", "mullins"), ("viscoelastic", "ogden_2term"),
         ("compressibility", "imperfect_gluing"), ("artefacts", None))
NOISE_KINDS = ("white", "filtered", "wander", "drift", "quantised")
MAX_OUTSIDE = {"axial_fibres": 10.0, "stiffness_drift": 8.0, "permanent_set": 6.0}
VISIBLE = 1.5  # least base misfit (noise SDs) of a calibrated effect; else drawn again
MAX_DRAWS = 4
CALIBRATION_STEPS = 4  # sizes tried per effect (secant-like steps on the base misfit)


# --------------------------------------------------------------------------- the specimen
@dataclass(frozen=True)
class Specimen:
    """Geometry and protocol of one world specimen."""

    radius_mm: float
    height_mm: float
    ct_amplitude: float | None  # None: no compression/tension test
    torsion_amplitudes: tuple[float, ...]  # () : no torsion test
    cycles: int
    increment: float  # recorded strain interval of the compression/tension test
    rate_per_s: float  # compression/tension rate; torsion ramps take as long

    @property
    def sampling_s(self) -> float:
        return self.increment / self.rate_per_s

    def protocols(self, substeps: int = 1) -> list[Protocol]:
        """The session's protocols in order; the FE steps ``substeps`` times per recorded
        interval (with sub-steps: never coarser than ``TRUTH_INCREMENT``).  The torsion
        ramps take as long as the compression/tension ramps."""
        step = self.increment / substeps
        if substeps > 1:
            step = min(step, TRUTH_INCREMENT)
        ramp_s = (self.ct_amplitude or 0.15) / self.rate_per_s
        out = []
        if self.ct_amplitude:
            a = self.ct_amplitude
            out.append(Protocol(COMPRESSION_TENSION, (1.0, 1.0 - a, 1.0, 1.0 + a, 1.0),
                                rate_per_s=self.rate_per_s, cycles=self.cycles,
                                max_increment=step))
        for a in self.torsion_amplitudes:
            rate = a / ramp_s
            out.append(Protocol(TORSION, (0.0, a, 0.0), rate_per_s=rate, cycles=self.cycles,
                                max_increment=step * rate / self.rate_per_s))
        return out


def draw_specimen(rng) -> Specimen:
    """Radius 3-5 mm, height 3-7 mm; compression/tension only (20 %), torsion only (20 %)
    or both; 1-3 cycles; amplitudes 0.10-0.20 and 0.1-0.4 (torsion: one or two tests);
    4 to 20 recorded points per ramp (interval 0.01-0.05 of strain)."""
    kind = rng.choice(["both", "both", "both", "ct", "torsion"])
    a_ct = float(rng.uniform(0.10, 0.20)) if kind != "torsion" else None
    tors: tuple[float, ...] = ()
    if kind != "ct":
        a = float(rng.uniform(0.1, 0.4))
        tors = (round(a / 2, 4), round(a, 4)) if rng.random() < 0.5 else (round(a, 4),)
    ref = a_ct or 0.15
    inc = float(np.exp(rng.uniform(np.log(0.01), np.log(min(0.05, ref / 4)))))
    return Specimen(round(float(rng.uniform(3.0, 5.0)), 3), round(float(rng.uniform(3.0, 7.0)), 3),
                    None if a_ct is None else round(a_ct, 4), tors, int(rng.integers(1, 4)),
                    inc, float(rng.uniform(0.005, 0.02)))


# --------------------------------------------------------------------------- the truth
@dataclass
class Truth:
    """Base material, library effects (fit coordinates of :mod:`simulators.coordinates`)
    and the outside effects: ``drift`` (fraction of mu lost by the end of the session),
    ``set_stretch`` (stretch offset per unit of compressive path), ``set_shear`` (shear
    offset per unit of twist loading path)."""

    values: dict
    drift: float = 0.0
    set_stretch: float = 0.0
    set_shear: float = 0.0

    def plain(self) -> dict:
        return {**{str(k): float(v) for k, v in self.values.items()},
                "stiffness_drift": self.drift, "set_stretch": self.set_stretch,
                "set_shear": self.set_shear}


def outside_values(effect: str, size: float, shape: dict) -> dict:
    """Truth fields of an outside effect at scalar ``size`` (0 = neutral)."""
    if effect == "axial_fibres":
        return {"values": {Param("fibre_k1"): size * 0.3 * shape["mu"],
                           Param("fibre_k2"): shape["k2"]}}
    if effect == "stiffness_drift":
        return {"drift": min(size * 0.03, 0.5)}
    if effect == "permanent_set":
        return {"set_stretch": size * 0.01, "set_shear": size * 0.01}
    raise ValueError(f"unknown outside effect {effect!r}")


def make_truth(base: dict, effects: dict[str, float], shapes: dict) -> Truth:
    """The truth with every effect at its size (``effects``: name -> size)."""
    t = Truth(dict(base))
    for e, size in effects.items():
        if e in OUTSIDE:
            v = outside_values(e, size, shapes[e])
            t.values.update(v.pop("values", {}))
            for k, x in v.items():
                setattr(t, "drift" if k == "stiffness_drift" else k, x)
        else:
            t.values.update(effect_values(e, size, shapes[e]))
    return t


def _model(models: dict, spec: Specimen, refinement: int, physics) -> ForwardModel:
    g_key = ("geometry", spec.radius_mm, spec.height_mm, refinement)
    if g_key not in models:
        models[g_key] = geo.make("axisymmetric", spec.radius_mm, spec.height_mm, refinement,
                                 comm=MPI.COMM_SELF)
    key = (spec.radius_mm, spec.height_mm, refinement, physics)
    if key not in models:
        material = MaterialModel.build(physics.n_terms, maxwell=physics.maxwell,
                                       softening=physics.softening, laws=physics.laws)
        models[key] = ForwardModel(models[g_key], material,
                                   ends="springs" if physics.springs else "glued")
    return models[key]


def _set_path(prot: Protocol, truth: Truth) -> list[Step]:
    """The FE steps with the permanent set applied: the control the specimen feels."""
    steps = prot.steps()
    rate = truth.set_stretch if prot.test == COMPRESSION_TENSION else truth.set_shear
    if not rate:
        return steps
    out, travelled = [steps[0]], 0.0
    neutral = NEUTRAL[prot.test]
    for a, b in zip(steps[:-1], steps[1:], strict=True):
        if prot.test == COMPRESSION_TENSION:  # compressive path shortens the specimen
            if b.value < neutral and b.value < a.value:
                travelled += a.value - b.value
            shift = rate * travelled
        else:  # the unloaded twist follows the twist applied
            if b.value > a.value:
                travelled += b.value - a.value
            shift = -rate * travelled
        out.append(Step(b.time_s, b.cycle, b.branch, b.value + shift))
    return out


def _segments(prot: Protocol) -> np.ndarray:
    """Times of the turning points of a protocol (start, every waypoint, end)."""
    t, times = 0.0, [0.0]
    for _ in range(prot.cycles):
        for a, b in zip(prot.waypoints[:-1], prot.waypoints[1:], strict=True):
            t += abs(b - a) / prot.rate_per_s
            times.append(t)
    return np.array(times)


def _nominal(prot: Protocol, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(control, cycle, branch) of the nominal protocol at times ``t``."""
    turns = _segments(prot)
    seg = np.clip(np.searchsorted(turns, t, side="right") - 1, 0, len(turns) - 2)
    per_cycle = len(prot.waypoints) - 1
    w = np.array(prot.waypoints)
    i = seg % per_cycle
    a, b = w[i], w[i + 1]
    frac = (t - turns[seg]) / (turns[seg + 1] - turns[seg])
    control = a + (b - a) * frac
    neutral = NEUTRAL[prot.test]
    branch = np.where(np.abs(b - neutral) > np.abs(a - neutral), LOADING, "unloading")
    return control, seg // per_cycle + 1, branch


def record_times(spec: Specimen, prot: Protocol, rng) -> np.ndarray:
    """The instrument's sample times: fixed interval from a random phase, small jitter."""
    dt = spec.sampling_s
    end = _segments(prot)[-1]
    t = rng.uniform(0, dt) + dt * np.arange(int(end / dt) + 2)
    t = t + rng.uniform(-JITTER, JITTER, len(t)) * dt
    return np.sort(t[(t > 0) & (t < end)])


def simulate(spec: Specimen, truth: Truth, times: list[np.ndarray], *, refinement: int,
             substeps: int, models: dict) -> pd.DataFrame:
    """Noiseless recordings table of ``spec`` under ``truth`` at the recorded ``times``
    (one array per protocol): FE steps ``substeps`` per recorded interval, channels
    interpolated per monotone segment."""
    pt = model_point(truth.values, NU0)
    fm = _model(models, spec, refinement, pt.physics)
    prots = spec.protocols(substeps)
    parts, session_t = [], 0.0
    for prot, t in zip(prots, times, strict=True):
        steps = _set_path(prot, truth)
        path = RecordedPath(prot.test, prot.amplitude, steps, prot.rate_per_s)
        resp = fm.solve(path, pt.material, interface=pt.interface, artefacts=pt.artefacts)
        control, cycle, branch = _nominal(prot, t)
        df = pd.DataFrame({"specimen": "", "test": prot.test, "amplitude": prot.amplitude,
                           "cycle": cycle, "branch": branch, TIME: t,
                           CONTROL[prot.test]: control})
        turns = _segments(prot)
        seg = np.clip(np.searchsorted(turns, t, side="right") - 1, 0, len(turns) - 2)
        for ch in TEST_CHANNELS[prot.test]:
            col = CHANNELS[ch].column
            y = np.empty(len(t))
            for s in np.unique(seg):
                inside = (resp.time_s >= turns[s] - 1e-9) & (resp.time_s <= turns[s + 1] + 1e-9)
                tt, yy = resp.time_s[inside], resp.values[col][inside]
                tt, keep = np.unique(tt, return_index=True)
                y[seg == s] = CubicSpline(tt, yy[keep])(t[seg == s]) if len(tt) > 2 else \
                    np.interp(t[seg == s], tt, yy[keep])
            if truth.drift:  # mu(t) = mu (1 - d t / T): every load scales with mu
                y *= 1.0 - truth.drift * (session_t + t) / _session_s(spec)
            df[col] = y
        session_t += turns[-1] + GAP_S
        parts.append(df)
    return recordings_table(parts)


def _session_s(spec: Specimen) -> float:
    return sum(_segments(p)[-1] + GAP_S for p in spec.protocols()) - GAP_S


# --------------------------------------------------------------------------- rig noise
def draw_noise(clean: pd.DataFrame, kinds: tuple[str, ...], rng, spec: Specimen
               ) -> dict[str, RigNoise]:
    """Rig noise per channel, levels relative to the channel's peak over the session:
    white 0.4-1.2 %; filtered 0.3-0.8 % over 1-3 sampling intervals; wander 0.2-0.6 % over
    5-60 s; drift 0.3-1 % over a test; quantisation step 0.3-1 %."""
    dt = spec.sampling_s
    test_s = max(_segments(p)[-1] for p in spec.protocols())
    out = {}
    for ch, c in CHANNELS.items():
        if c.column not in clean or clean[c.column].isna().all():
            continue
        peak = float(np.nanmax(np.abs(clean[c.column])))
        kw = {"white": peak * rng.uniform(0.004, 0.012)}
        if "filtered" in kinds:
            kw.update(filtered=peak * rng.uniform(0.003, 0.008),
                      filter_s=dt * rng.uniform(1.0, 3.0))
        if "wander" in kinds:
            kw.update(wander=peak * rng.uniform(0.002, 0.006),
                      wander_s=float(np.exp(rng.uniform(np.log(5.0), np.log(60.0)))))
        if "drift" in kinds:
            kw.update(drift=peak * rng.uniform(0.003, 0.01) / test_s)
        if "quantised" in kinds:
            kw.update(quantum=peak * rng.uniform(0.003, 0.01))
        out[ch] = RigNoise(**kw)
    return out


def noise_sd(noise: dict[str, RigNoise]) -> dict[str, float]:
    """Per channel: the SD of the stationary noise (quantisation as uniform)."""
    return {ch: math.sqrt(n.stationary_sd() ** 2 + n.quantum**2 / 12) for ch, n in noise.items()}


def noise_statement(noise: dict[str, RigNoise]) -> dict[str, ChannelNoise]:
    """Per channel: the rig's whole noise as a lab that measured its rig would state it
    (``diagnose --noise`` JSON, :func:`diagnosis.noise.statement`): the white part with the
    rounding error (uniform, ``quantum^2 / 12``), the filter and the wander as two
    correlated parts, the drift.  The diagnosis then fits no noise."""
    out = {}
    for ch, n in noise.items():
        n = n if isinstance(n, RigNoise) else RigNoise(**n)
        parts = [(c, s) for c, s in ((n.filtered, n.filter_s), (n.wander, n.wander_s)) if c]
        (corr, corr_s), *more = parts or [(0.0, 1.0)]
        out[ch] = ChannelNoise(white=math.sqrt(n.white**2 + n.quantum**2 / 12), corr=corr,
                               corr_s=corr_s, drift=n.drift, more=tuple(more))
    return out


# --------------------------------------------------------------------------- a case
@dataclass
class WorldCase:
    name: str
    kind: str  # control, single, pair, outside
    effects: list  # truth effect names (library or outside)
    spec: Specimen
    truth: Truth
    noise: dict  # channel -> RigNoise
    noise_kinds: tuple
    sizes: dict = field(default_factory=dict)
    misfits: dict = field(default_factory=dict)  # per effect: calibrated base misfit / noise
    beside: dict = field(default_factory=dict)  # per effect of a pair: misfit / noise left
    # to the best model with the other effect (visible_beside); not a reason to draw again
    noise_rms: dict = field(default_factory=dict)  # per curve/channel: the RMS of the noise
    # actually added (recordings minus the noiseless path)

    def label(self) -> dict:
        from dataclasses import asdict

        return {"kind": self.kind, "effects": list(self.effects),
                "expected": expected(self.kind, [e for e in self.effects if self.misfits.get(
                    e, VISIBLE) >= VISIBLE]),
                "specimen": asdict(self.spec), "truth": self.truth.plain(),
                "noise": {ch: asdict(n) for ch, n in self.noise.items()},
                "noise_kinds": list(self.noise_kinds), "sizes": self.sizes,
                "base_misfit_over_noise": self.misfits,
                "misfit_beside_the_other_over_noise": self.beside,
                "noise_rms": self.noise_rms}


def expected(kind: str, effects: list) -> str:
    """The right answer; ``effects``: those the specimen's tests can show."""
    if kind == "control" or not effects:
        return "none"
    if kind == "outside":
        return "unexplained"
    return "+".join(sorted(effects))


def _shapes(rng, mu: float, spec: Specimen) -> dict:
    tau = {"log10_tau": rng.uniform(0.3, 1.5)}
    return {"viscoelastic": tau, "mullins": {"log10_m": rng.uniform(-2.0, -1.3)},
            "ogden_2term": {"mu": mu, "alpha_1": rng.choice([-1, 1]) * rng.uniform(8, 15)},
            "compressibility": {},
            "imperfect_gluing": {"k": 10 ** rng.uniform(0.5, 1.0) * 5.0 / spec.height_mm},
            "artefacts": {"offset": rng.choice([-1, 1]) * 0.004},
            "axial_fibres": {"mu": mu, "k2": rng.uniform(1.0, 10.0)},
            "stiffness_drift": {}, "permanent_set": {}}


def misfit_left(spec, truth, times, noise_sd_ch, models, beside: tuple = (),
                 start: dict | None = None) -> float:
    """RMS (in noise SDs) of the best base fit to the noiseless recordings, on the
    working mesh (truth and fit alike: the calibration measures the effect only).  With
    library effects ``beside`` (started at their true values, or at ``start``), the best
    fit of the base model with them: what the truth's other effects show beyond those."""
    z = residual_left(spec, truth, times, noise_sd_ch, models, beside, start)
    return float(np.sqrt(np.mean(z**2)))


def clean_observations(spec, truth, times, models) -> pd.DataFrame:
    """The noiseless recordings of ``truth`` on the working mesh, as observations: what
    :func:`misfit_left` fits."""
    clean = simulate(spec, truth, times, refinement=CALIBRATION_REFINEMENT, substeps=1,
                     models=models)
    clean["specimen"] = "calibration"
    return observations(clean)


def residual_left(spec, truth, times, noise_sd_ch, models, beside: tuple = (),
                  start: dict | None = None, obs: pd.DataFrame | None = None) -> np.ndarray:
    """The residual (in noise SDs, one entry per recorded value) of :func:`misfit_left`;
    ``obs``: the truth's :func:`clean_observations` when several fits share them."""
    return fit_left(spec, truth, times, noise_sd_ch, models, beside, start, obs).z


def fit_left(spec, truth, times, noise_sd_ch, models, beside: tuple = (),
             start: dict | None = None, obs: pd.DataFrame | None = None) -> Fit:
    """The best fit of :func:`residual_left` itself (its values start another fit)."""
    if obs is None:
        obs = clean_observations(spec, truth, times, models)
    sim = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=CALIBRATION_REFINEMENT,
                      geometry=_model_geometry(models, spec), models=models.setdefault(
                          ("sim-models", spec.radius_mm, spec.height_mm), {}))
    sigma = obs["channel"].map(noise_sd_ch).to_numpy(float)
    lib = library(sim.kind)
    names = parameter_names(lib, beside)
    given = {Param.parse(k): v for k, v in (start or {}).items()}
    start = {k: given[k] if k in given else truth.values[k] for k in names}
    return fit(sim, obs, sigma, start, names, max_nfev=30, effect="+".join(beside) or "base",
               effect_def=Union(lib, beside) if beside else None)


def _model_geometry(models, spec):
    key = ("geometry", spec.radius_mm, spec.height_mm, CALIBRATION_REFINEMENT)
    if key not in models:
        models[key] = geo.make("axisymmetric", spec.radius_mm, spec.height_mm,
                               CALIBRATION_REFINEMENT, comm=MPI.COMM_SELF)
    return models[key]


def calibrate(effect: str, target: float, spec, base, shapes, times, sd, models
              ) -> tuple[float, float]:
    """(size, misfit): the size of ``effect`` alone whose base misfit is ~``target``
    (within 25 %, else the last size tried, at most the effect's cap); the misfit is
    always that of the size returned."""
    cap = MAX_OUTSIDE.get(effect, MAX_SIZE.get(effect, 10.0))

    def left(size: float) -> float:
        misfit = misfit_left(spec, make_truth(base, {effect: size}, shapes), times, sd,
                             models)
        log.debug("%s size %.3g: base misfit %.2f (target %.2f)", effect, size, misfit, target)
        return misfit

    size = 1.0
    misfit = left(size)
    for _ in range(CALIBRATION_STEPS - 1):
        if abs(misfit / target - 1) < 0.25:
            break
        new = min(size * float(np.clip(target / max(misfit, 1e-3), 0.1, 10.0)), cap)
        if new == size:  # at the cap
            break
        size, misfit = new, left(new)
    return size, misfit


def visible_beside(effects: list, spec, truth: Truth, times, sd, models) -> dict:
    """Per library effect of a combination: the misfit (noise SDs, RMS) the truth leaves
    to the best model with every *other* effect of it (:func:`misfit_left` with
    ``beside``).  Below ``VISIBLE`` its partner mimics it (a compressibility that a soft
    glue layer absorbs in these tests): the recordings cannot show both.  NaN where the
    model with the others cannot be solved (the measure is then not known; the case
    stands as drawn)."""
    out = {}
    for e in effects:
        if e in OUTSIDE:
            continue
        try:
            out[e] = misfit_left(spec, truth, times, sd, models,
                                 beside=tuple(x for x in effects if x != e))
        except (RuntimeError, ValueError) as exc:  # not solved, or not at its start
            log.warning("%s beside %s: not measured (%s)", e, effects, exc)
            out[e] = float("nan")
    return out


def closest_library(spec, truth: Truth, times, sd, models, effects=None, rig=None,
                    pairs: bool = False) -> dict:
    """How near the library comes to a truth: per library effect (``effects``, default
    every one of the cylinder's library) the misfit (noise SDs, RMS) the truth leaves to
    the best base model with that effect alone, on the working mesh (:func:`misfit_left`,
    from each of the effect's own start values, :attr:`diagnosis.effects.Effect.starts`;
    the least; NaN where no start was solved), and the number of recorded values
    (``points``): what :func:`diagnosis.open_benchmark.mimicked` judges.  With ``rig``
    (channel -> the rig's :class:`RigNoise`, or its fields), also that misfit's size under
    the rig's whole noise (``chi2_under_rig_noise``: :func:`misfit_chi2`, what the best
    test aimed at it sees when wander, filter and drift are part of the noise).  With
    ``pairs``, every combination of two of those effects too (key ``a+b``, the names
    sorted; ``pairs`` True in the result), fitted once from both effects' best fits alone
    (the base parameters of the closer one; never above the closer one alone, which the
    pair nests; none where an effect has no fit alone): a verdict of two effects is one the
    diagnosis may give, so a pair that follows the truth mimics it as well.  The cost,
    about ten fits per case (and one per pair), keeps it out of the generator:
    ``benchmarks/mimicked_outside.py`` measures it for a draw's outside cases."""
    lib = library("fe")
    obs = clean_observations(spec, truth, times, models)  # the truth, solved once
    sigma = obs["channel"].map(sd).to_numpy(float)
    rms, chi2, best_fit = {}, {}, {}

    def keep(key: str, f: Fit | None) -> None:
        rms[key] = math.nan if f is None else float(np.sqrt(np.mean(np.square(f.z))))
        if rig is not None:
            chi2[key] = math.nan if f is None else misfit_chi2(obs, f.z * sigma, rig)

    singles = list(lib if effects is None else effects)
    for e in singles:
        left = []
        for s in lib[e].starts:
            try:
                left.append(fit_left(spec, truth, times, sd, models, beside=(e,),
                                     start={str(k): v for k, v in s.items()}, obs=obs))
            except (RuntimeError, ValueError) as exc:  # not solved from this start
                log.warning("closest library effect %s: a start not solved (%s)", e, exc)
        best_fit[e] = min(left, key=lambda f: f.chi2) if left else None
        keep(e, best_fit[e])
    for i, a in enumerate(singles):
        for b in singles[i + 1:] if pairs else ():
            fa, fb = best_fit[a], best_fit[b]
            if not compatible(a, [b]) or fa is None or fb is None:
                continue
            near, far = (fa, fb) if fa.chi2 <= fb.chi2 else (fb, fa)
            start = {str(k): v for k, v in {**far.values, **near.values}.items()}
            try:
                f = fit_left(spec, truth, times, sd, models, beside=tuple(sorted((a, b))),
                             start=start, obs=obs)
            except (RuntimeError, ValueError) as exc:
                log.warning("closest library pair %s+%s: not solved (%s)", a, b, exc)
                f = None
            # the pair nests the closer effect alone (the other at its neutral value): a
            # fit that stopped short of it is not what the pair can do
            keep("+".join(sorted((a, b))), f if f is not None and f.chi2 <= near.chi2 else near)
    out = {"rms_left_over_noise": rms, "points": len(obs)}
    if rig is not None:
        out["chi2_under_rig_noise"] = chi2
    if pairs:
        out["pairs"] = True
    return out


def misfit_chi2(obs: pd.DataFrame, misfit: np.ndarray, rig: dict) -> float:
    """``m^T Sigma^-1 m``: the size of a misfit ``m`` (the channels' units, one value per
    row of ``obs``) under the rig's whole noise (``rig``: channel -> :class:`RigNoise` or
    its fields; white with the rounding, filter, wander and drift, as
    :func:`noise_statement` states them), Sigma block diagonal over the series.  It is the
    non-centrality of the best test aimed at the misfit's own shape; under white noise of
    SD sigma it is ``sum (m / sigma)^2``."""
    stated = noise_statement(rig)
    obs = obs.reset_index(drop=True)
    nm = NoiseModel(obs, {(str(k[1]), str(k[2])): stated[str(k[2])] for k, _ in groups(obs)})
    z = nm.whiten(np.asarray(misfit, float))
    return float(z @ z)


def make_case(name: str, kind: str, effects: list, rng, *, noise_kinds=None,
              models: dict | None = None, truth_refinement: int = TRUTH_REFINEMENT,
              substeps: int = SUBSTEPS, target=(2.5, 8.0)) -> tuple[pd.DataFrame, pd.DataFrame,
                                                                     WorldCase]:
    """One world case: (recordings with rig noise, specimens row, the case)."""
    models = {} if models is None else models
    if noise_kinds is None:
        noise_kinds = ("white",) + tuple(k for k in NOISE_KINDS[1:] if rng.random() < 0.35)
    for draw in range(MAX_DRAWS):
        spec = draw_specimen(rng)
        mu = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        base = {Param("mu", 0): mu, Param("alpha", 0): float(rng.uniform(-25, -8))}
        shapes = _shapes(rng, mu, spec)
        prots = spec.protocols()
        times = [record_times(spec, p, rng) for p in prots]
        # noise levels are drawn on the base response (the channel's peak sets the scale)
        ref = simulate(spec, make_truth(base, {}, shapes), times,
                       refinement=CALIBRATION_REFINEMENT, substeps=1, models=models)
        noise = draw_noise(ref, noise_kinds, rng, spec)
        sd = noise_sd(noise)
        sizes, misfits = {}, {}
        for e in effects:
            tgt = float(np.exp(rng.uniform(*np.log(target))))
            sizes[e], misfits[e] = calibrate(e, tgt, spec, base, shapes, times, sd, models)
            log.info("%s %s: size %.3g, base misfit %.2f noise SD (target %.2f)", name, e,
                     sizes[e], misfits[e], tgt)
        # an effect this specimen's tests cannot show within realistic sizes (e.g. soft
        # glue in compression/tension alone is a change of mu) is no test: draw again
        if all(m >= VISIBLE for m in misfits.values()):
            break
        log.info("%s: %s not visible on this specimen's tests; drawing another (%d)", name,
                 ", ".join(e for e, m in misfits.items() if m < VISIBLE), draw + 1)
    truth = make_truth(base, sizes, shapes)
    # what a pair's tests can separate: measured and labelled, not drawn again (two effects
    # that mimic each other stay a pair whose right answer the tests cannot show whole)
    beside = visible_beside(effects, spec, truth, times, sd, models) \
        if len(effects) > 1 else {}
    clean = simulate(spec, truth, times, refinement=truth_refinement, substeps=substeps,
                     models=models)
    clean["specimen"] = name
    rec = add_noise(clean, noise, rng)
    added = observations(rec).assign(noise=lambda o: o["value"] - observations(clean)["value"])
    noise_rms = {f"{c}/{ch}": float(np.sqrt(np.mean(g["noise"] ** 2)))
                 for (c, ch), g in added.groupby(["curve", "channel"], sort=False)}
    specimens = pd.DataFrame({"specimen": [name], "region": ["synthetic"], "brain": ["B0"],
                              "radius_mm": [spec.radius_mm],
                              "height_mm": [spec.height_mm]})
    return rec, specimens, WorldCase(name, kind, list(effects), spec, truth, noise,
                                     tuple(noise_kinds), sizes, misfits, beside, noise_rms)
