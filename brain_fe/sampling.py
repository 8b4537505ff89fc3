"""Parallel, resumable generation of forward-model samples (training data for surrogates).

Every rank builds one :class:`~brain_fe.model.ForwardModel` on ``MPI.COMM_SELF`` and takes
the next pending sample index from a shared counter (:mod:`brain_fe.parallel`), so work is
balanced dynamically without a master rank.  A sample is *complete* when a row for each of
its tests is stored (status ``ok`` or ``failed``); a re-run of the same command computes
exactly the incomplete samples.  Results go to a store (:mod:`brain_fe.store`).

Parameter design: mu [kPa] log-uniform in ``mu_range``, alpha uniform in ``alpha_range``,
from a scrambled Sobol sequence or a Latin hypercube seeded by ``seed``; a pure function of
``(n, seed, design, ranges)``.
"""

from __future__ import annotations

import errno
import logging
import math
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from . import store as st
from .parallel import Progress, SharedCounter, dynamic_items, rank0_first
from .store import VALUE_COLUMNS, SampleSummary, StoreError, chunk_files, design_hash, summarize
from .vocabulary import CONTROL, DEFAULT_AMPLITUDE, TESTS, test_key

log = logging.getLogger(__name__)

DESIGNS = ("sobol", "lhs")
MODELS = ("axisymmetric", "3d")
DEFAULT_TESTS = "compression_tension,torsion:0.15,torsion:0.30"


# ------------------------------------------------------------------------------ the spec
@dataclass(frozen=True)
class TestSpec:
    """One protocol of every sample: ``kind`` (compression_tension | torsion), amplitude."""

    kind: str
    amplitude: float

    @property
    def name(self) -> str:
        return test_key(self.kind, self.amplitude)

    def protocol(self):
        from .protocols import make

        return make(self.kind, self.amplitude)


def parse_tests(text: str | Sequence[str]) -> tuple[TestSpec, ...]:
    """``"compression_tension,torsion:0.15,torsion:0.30"`` -> test specs (``kind[:amplitude]``)."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text)]
    out = []
    for item in items:
        if not item:
            continue
        kind, _, amp = item.partition(":")
        kind = kind.strip()
        if kind not in TESTS:
            raise ValueError(f"unknown test {kind!r} in the test list; expected "
                             "compression_tension or torsion[:amplitude]")
        try:
            a = float(amp) if amp.strip() else DEFAULT_AMPLITUDE[kind]
        except ValueError:
            raise ValueError(f"bad amplitude {amp!r} for test {kind}") from None
        if not (a > 0 and math.isfinite(a)) or (kind == "compression_tension" and a >= 1):
            raise ValueError(f"bad amplitude {a:g} for test {kind}")
        out.append(TestSpec(kind, a))
    if not out:
        raise ValueError("give at least one test")
    names = [t.name for t in out]
    if len(set(names)) != len(names):
        raise ValueError(f"tests repeat a name: {', '.join(names)}")
    return tuple(out)


def _check_ranges(mu_range, alpha_range) -> tuple[tuple[float, float], tuple[float, float]]:
    mu_range = tuple(float(v) for v in mu_range)
    alpha_range = tuple(float(v) for v in alpha_range)
    for name, r in (("mu range", mu_range), ("alpha range", alpha_range)):
        if len(r) != 2 or not all(map(math.isfinite, r)) or not r[0] < r[1]:
            raise ValueError(f"{name} must be two finite numbers lo < hi, got {r}")
    if mu_range[0] <= 0:
        raise ValueError(f"mu range must be positive (log-uniform), got {mu_range}")
    if alpha_range[0] <= 0.0 <= alpha_range[1]:
        raise ValueError(f"alpha range must not contain 0 (the Ogden exponent is non-zero), "
                         f"got {alpha_range}")
    return mu_range, alpha_range


@dataclass(frozen=True)
class SampleSpec:
    """Everything that determines the stored values (recorded in the manifest)."""

    n: int
    seed: int = 0
    design: str = "sobol"
    mu_range: tuple[float, float] = (0.1, 5.0)
    alpha_range: tuple[float, float] = (-40.0, -2.0)
    nu0: float = 0.49
    tests: tuple[TestSpec, ...] = field(default_factory=lambda: parse_tests(DEFAULT_TESTS))
    model: str = "axisymmetric"
    radius_mm: float = 4.0
    height_mm: float = 5.0
    refinement: int | None = None
    ends: str = "glued"
    volumetric: str = "quadratic"

    def __post_init__(self):
        if isinstance(self.tests, str):
            object.__setattr__(self, "tests", parse_tests(self.tests))
        mu_r, al_r = _check_ranges(self.mu_range, self.alpha_range)
        object.__setattr__(self, "mu_range", mu_r)
        object.__setattr__(self, "alpha_range", al_r)
        if int(self.n) != self.n or self.n < 1:
            raise ValueError(f"n must be a positive integer, got {self.n}")
        if self.design not in DESIGNS:
            raise ValueError(f"design must be one of {', '.join(DESIGNS)}, got {self.design!r}")
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")
        if self.ends not in ("glued", "slip"):
            raise ValueError(f"ends must be glued or slip, got {self.ends!r}")
        if self.volumetric not in ("quadratic", "log"):
            raise ValueError(f"volumetric must be quadratic or log, got {self.volumetric!r}")
        if not (math.isfinite(self.nu0) and 0.0 <= self.nu0 < 0.5):
            raise ValueError(f"nu0 must lie in [0, 0.5), got {self.nu0}")
        for name in ("radius_mm", "height_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")
        from .ends import check_ends

        for t in self.tests:
            check_ends(self.ends, self.model, t.kind)
        if self.refinement is None:
            from .geometry import DEFAULT_REFINEMENT

            object.__setattr__(self, "refinement", DEFAULT_REFINEMENT[self.model])
        if int(self.refinement) != self.refinement or self.refinement < 1:
            raise ValueError(f"refinement must be a whole number >= 1, got {self.refinement}")
        object.__setattr__(self, "n", int(self.n))
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "refinement", int(self.refinement))

    def as_dict(self) -> dict:
        return {"n": self.n, "seed": self.seed, "design": self.design,
                "mu_range_kPa": list(self.mu_range), "alpha_range": list(self.alpha_range),
                "nu0": float(self.nu0),
                "tests": [{"name": t.name, "test": t.kind, "amplitude": t.amplitude}
                          for t in self.tests],
                "model": self.model, "radius_mm": float(self.radius_mm),
                "height_mm": float(self.height_mm), "refinement": self.refinement,
                "ends": self.ends, "volumetric": self.volumetric, "n_terms": 1}

    @property
    def test_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.tests)


# ------------------------------------------------------------------------------ the design
def make_design(n: int, seed: int = 0, design: str = "sobol",
                mu_range: Sequence[float] = (0.1, 5.0),
                alpha_range: Sequence[float] = (-40.0, -2.0)) -> pd.DataFrame:
    """Parameter sets ``sample, mu_kPa, alpha``: mu log-uniform, alpha uniform.

    A pure function of its arguments: u in [0, 1)^2 from a scrambled Sobol sequence (its
    first n points) or a Latin hypercube, both seeded with ``seed``; then
    mu = mu_lo (mu_hi / mu_lo)^u_0 and alpha = alpha_lo + (alpha_hi - alpha_lo) u_1.
    """
    import warnings

    from scipy.stats import qmc

    mu_range, alpha_range = _check_ranges(mu_range, alpha_range)
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n}")
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {', '.join(DESIGNS)}, got {design!r}")
    n, seed = int(n), int(seed)
    if design == "sobol":
        with warnings.catch_warnings():  # n need not be a power of two
            warnings.simplefilter("ignore", UserWarning)
            u = qmc.Sobol(d=2, scramble=True, seed=seed).random(n)
    else:
        u = qmc.LatinHypercube(d=2, seed=seed).random(n)
    lo, hi = np.log(mu_range[0]), np.log(mu_range[1])
    mu = np.clip(np.exp(lo + (hi - lo) * u[:, 0]), *mu_range)
    a0, a1 = alpha_range
    alpha = a0 + (a1 - a0) * u[:, 1]
    return pd.DataFrame({"sample": np.arange(n, dtype=np.int64), "mu_kPa": mu,
                         "alpha": alpha})


def make_manifest(spec: SampleSpec) -> dict:
    d = make_design(spec.n, spec.seed, spec.design, spec.mu_range, spec.alpha_range)
    return {"schema": st.SCHEMA, "schema_version": st.SCHEMA_VERSION, "spec": spec.as_dict(),
            "parameters": {"mu_kPa": d.mu_kPa.tolist(), "alpha": d.alpha.tolist(),
                           "sha256": design_hash(d)},
            "software": st.software_versions(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


# ------------------------------------------------------------------------------ solving
def solve_sample(model, spec: SampleSpec, sample: int, mu: float, alpha: float) -> list[dict]:
    """Rows of one parameter set: one per (test, step), or one ``failed`` row per test."""
    from .materials import MaterialParameters
    from .solver import ConvergenceError

    rows = []
    base = {"sample": int(sample), "mu_kPa": float(mu), "alpha": float(alpha),
            "nu0": float(spec.nu0)}
    for t in spec.tests:
        head = {**base, "test": t.name, "amplitude": float(t.amplitude)}
        t0 = time.perf_counter()
        try:
            params = MaterialParameters(mu=(mu,), alpha=(alpha,), nu0=spec.nu0)
            df = model.run(t.protocol(), params)
        except (ConvergenceError, ValueError, ArithmeticError, RuntimeError) as exc:
            # RuntimeError includes PETSc errors (e.g. a zero pivot in LU)
            reason = f"{type(exc).__name__}: {exc}"
            log.debug("sample %d %s failed: %s", sample, t.name, reason)
            rows.append({**head, "status": "failed", "reason": reason,
                         "wall_time_s": time.perf_counter() - t0})
            continue
        wall = time.perf_counter() - t0
        control = CONTROL[t.kind]
        for k, rec in enumerate(df.to_dict("records")):
            row = {**head, "step": k, "time_s": rec["time_s"], "cycle": int(rec["cycle"]),
                   "branch": rec["branch"], control: rec[control],
                   "status": "ok", "reason": None,
                   "newton_iterations": int(getattr(model, "iterations", -1)),
                   "cutbacks": getattr(model, "cutbacks", None),
                   "wall_time_s": wall}
            for c in VALUE_COLUMNS:
                if c in rec and c != control:
                    row[c] = float(rec[c])
            rows.append(row)
    return rows


def _lock(store: Path):
    import fcntl

    lock = open(store / ".lock", "a")  # noqa: SIM115 - held for the whole run
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        lock.close()
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            raise StoreError(f"{store} is in use by another sampling job") from None
        raise
    return lock


def _prepare_store(spec: SampleSpec, store: Path):
    """Rank 0: check an existing manifest (a new one is written with the first result),
    take the lock, clean temp files, list the work.  Returns (manifest, pending, lock,
    created) with ``created`` the directories this run made."""
    wanted = make_manifest(spec)
    created = [d for d in (store, store / "chunks") if not d.exists()]
    store.mkdir(parents=True, exist_ok=True)
    (store / "chunks").mkdir(exist_ok=True)
    lock = _lock(store)
    try:
        if st.manifest_path(store).exists():
            man = st.read_manifest(store)
            st.check_manifest(man, wanted, store)
        else:
            if chunk_files(store):
                raise StoreError(f"{store} holds chunks but no manifest.json; refusing to "
                                 "use this store")
            man = wanted
        for p in list((store / "chunks").glob(".tmp-*")) + list(store.glob(".tmp-*")):
            log.info("removing %s (left by an interrupted run)", p.name)
            p.unlink(missing_ok=True)
        done = (st.completed_samples(store, spec.test_names)
                if st.manifest_path(store).exists() else set())
    except BaseException:
        lock.close()
        _remove_created(store, created)
        raise
    return man, [i for i in range(spec.n) if i not in done], lock, created


def _remove_created(store: Path, created: list[Path]) -> None:
    """Undo the directories of a run that stored nothing (no store is left behind)."""
    if created and not chunk_files(store) and not st.manifest_path(store).exists():
        (store / ".lock").unlink(missing_ok=True)
        for d in reversed(created):
            try:
                d.rmdir()
            except OSError:
                pass


def run_sampling(spec: SampleSpec, store, *, comm=None, chunk_size: int = 1,
                 flush_seconds: float = 120.0, progress: bool = True,
                 model_factory: Callable | None = None) -> SampleSummary:
    """Compute every sample of ``spec`` missing from ``store``; collective over ``comm``.

    Each rank builds one model on ``MPI.COMM_SELF`` (rank 0 first, so the JIT cache is
    filled once), then repeatedly takes the next pending index from the shared counter.
    A rank writes its results as a chunk every ``chunk_size`` samples (default 1: a kill
    loses at most the sample in progress) or ``flush_seconds``, and merges its chunks of
    this run into one at the end.  Returns the store's summary (on every rank).
    """
    from mpi4py import MPI

    comm = MPI.COMM_WORLD if comm is None else comm
    store = Path(store)
    if chunk_size < 1:
        raise ValueError("chunk size must be at least 1")
    payload, lock, created = None, None, []
    if comm.rank == 0:
        try:
            man, pending, lock, created = _prepare_store(spec, store)
            payload = (pending, man)
        except (ValueError, OSError) as exc:
            payload = exc if isinstance(exc, StoreError) else StoreError(str(exc))
    payload = comm.bcast(payload, root=0)
    if isinstance(payload, Exception):
        raise payload
    pending, man = payload
    run_id = comm.bcast(time.strftime("%Y%m%dT%H%M%S-") + uuid.uuid4().hex[:8]
                        if comm.rank == 0 else None, root=0)
    log.info("%s: %d of %d samples to compute on %d rank(s)", store, len(pending), spec.n,
             comm.size)
    try:
        return _run(spec, store, comm, pending, man, run_id, chunk_size, flush_seconds,
                    progress, model_factory or _build_model)
    except BaseException:
        if comm.rank == 0:
            _remove_created(store, created)
        raise
    finally:
        if lock is not None:
            lock.close()


def _build_model(spec: SampleSpec):
    from mpi4py import MPI

    from .geometry import make
    from .model import ForwardModel

    g = make(spec.model, spec.radius_mm, spec.height_mm, spec.refinement,
                      comm=MPI.COMM_SELF)
    return ForwardModel(g, n_terms=1, volumetric=spec.volumetric, ends=spec.ends)


def _run(spec, store, comm, pending, man, run_id, chunk_size, flush_seconds, progress,
         factory):
    t_setup = time.perf_counter()
    mu, alpha = man["parameters"]["mu_kPa"], man["parameters"]["alpha"]
    model = rank0_first(comm, lambda: factory(spec)) if pending else None
    counter = SharedCounter(comm, slots=3)  # next position, samples done, samples failed
    bar = Progress(spec.n, "samples", "sample", enabled=progress, comm=comm,
                   initial=spec.n - len(pending))
    t0 = time.perf_counter()
    log.debug("rank %d set up in %.1f s", comm.rank, t0 - t_setup)
    buffer: list[dict] = []
    written: list[Path] = []
    seq, computed, t_flush = 0, 0, time.perf_counter()
    seen = [0, 0]

    def update_bar():
        done, failed = counter.read(1), counter.read(2)
        if done != seen[0] or failed != seen[1]:
            bar.update(done - seen[0], f"failed={failed}")
            seen[:] = [done, failed]

    def flush():
        nonlocal buffer, seq, t_flush
        if buffer:
            if not st.manifest_path(store).exists():  # with the first valid result
                st.write_manifest(store, man)
            written.append(st.write_chunk(store, buffer, run_id=run_id, rank=comm.rank,
                                          seq=seq))
            seq += 1
            buffer = []
        t_flush = time.perf_counter()

    try:
        for i in dynamic_items(pending, counter, 0):
            rows = solve_sample(model, spec, i, mu[i], alpha[i])
            buffer.extend(rows)
            computed += 1
            if computed % chunk_size == 0 or time.perf_counter() - t_flush > flush_seconds:
                flush()
            counter.add(1)
            if any(r["status"] == "failed" for r in rows):
                counter.add(2)
            update_bar()
        flush()
        st.merge_chunks(store, written, run_id=run_id, rank=comm.rank)
        if comm.rank == 0:
            # Keep the bar moving while the other ranks finish their last samples.
            while counter.read(1) < len(pending):
                update_bar()
                time.sleep(0.2)
            update_bar()
    except Exception as exc:
        if comm.size > 1:  # the other ranks would wait forever; the store stays consistent
            log.critical("rank %d: %s: %s; aborting the job", comm.rank,
                         type(exc).__name__, exc)
            sys.stderr.write(f"brainmech sample: rank {comm.rank}: {exc}; aborting\n")
            sys.stderr.flush()
            comm.Abort(1)
        raise
    finally:
        bar.close()
    elapsed = time.perf_counter() - t0
    counter.free()
    comm.Barrier()
    summary = summarize(store) if comm.rank == 0 and st.manifest_path(store).exists() else None
    summary = comm.bcast(summary, root=0)
    if summary is None:  # nothing to compute and nothing stored (n = 0 cannot happen)
        summary = SampleSummary(spec.n, 0, 0, spec.n, [])
    from mpi4py import MPI

    summary.computed = comm.allreduce(computed)
    summary.elapsed_s = comm.allreduce(elapsed, op=MPI.MAX)
    log.info("%s: %s; computed %d in %.1f s", store, summary.line(), summary.computed,
             summary.elapsed_s)
    for s, t, reason in summary.failures[:5]:
        log.warning("sample %d, %s failed: %s", s, t, reason)
    if len(summary.failures) > 5:
        log.warning("... and %d more failed tests (load_samples(..., include_failed=True))",
                    len(summary.failures) - 5)
    return summary

