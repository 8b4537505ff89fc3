"""Parallel, resumable generation of forward-model samples (training data for surrogates).

A *store* is a directory::

    DIR/manifest.json     schema, the full design spec, the parameter values, versions
    DIR/chunks/*.parquet  results, tidy rows; each chunk written by one rank, atomically
    DIR/.lock             held (flock) by rank 0 while a job writes to the store

Every rank builds one :class:`~brain_fe.model.ForwardModel` on ``MPI.COMM_SELF`` and takes
the next pending sample index from a shared counter in rank 0's MPI window (one-sided
``Fetch_and_op``), so work is balanced dynamically without a master rank.  A sample is
*complete* when a row for each of its tests is stored (status ``ok`` or ``failed``); a
re-run of the same command computes exactly the incomplete samples.  A sample's rows are
always written in the same chunk, through a temporary file and ``os.replace``, so a kill
loses at most the samples buffered since the last chunk and never leaves a partial or
duplicated sample.

Parameter design: mu [kPa] log-uniform in ``mu_range``, alpha uniform in ``alpha_range``,
from a scrambled Sobol sequence or a Latin hypercube seeded by ``seed``; a pure function of
``(n, seed, design, ranges)``.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import sys
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

log = logging.getLogger(__name__)

SCHEMA = "brainmech.samples"
SCHEMA_VERSION = 1
DESIGNS = ("sobol", "lhs")
MODELS = ("axisymmetric", "3d")
DEFAULT_TESTS = "compression_tension,torsion:0.15,torsion:0.30"
DEFAULT_AMPLITUDE = {"compression_tension": 0.15, "torsion": 0.30}

# Column order of the chunks and of load_samples(); float columns not applicable to a test
# are null (NaN after loading).
COLUMNS = ("sample", "mu_kPa", "alpha", "nu0", "test", "amplitude", "step", "time_s",
           "cycle", "branch", "stretch", "shear", "nominal_stress_kPa", "torque_mNmm",
           "shear_stress_kPa", "axial_force_mN", "status", "reason", "newton_iterations",
           "cutbacks", "wall_time_s")
VALUE_COLUMNS = ("time_s", "stretch", "shear", "nominal_stress_kPa", "torque_mNmm",
                 "shear_stress_kPa", "axial_force_mN")
_INT = ("sample", "step", "cycle", "newton_iterations", "cutbacks")
_STR = ("test", "branch", "status", "reason")


class StoreError(ValueError):
    """The store cannot be used (corrupted or foreign manifest, unreadable chunk, busy)."""


# ------------------------------------------------------------------------------ the spec
@dataclass(frozen=True)
class TestSpec:
    """One protocol of every sample: ``kind`` (compression_tension | torsion), amplitude."""

    kind: str
    amplitude: float

    @property
    def name(self) -> str:
        """``compression_tension`` (default amplitude) or ``torsion_0.15``-style names."""
        if self.kind == "compression_tension" and math.isclose(self.amplitude, 0.15):
            return "compression_tension"
        return f"{self.kind}_{self.amplitude:.2f}"

    def protocol(self):
        from .api import make_protocol

        return make_protocol(self.kind, self.amplitude)


def parse_tests(text: str | Sequence[str]) -> tuple[TestSpec, ...]:
    """``"compression_tension,torsion:0.15,torsion:0.30"`` -> test specs (``kind[:amplitude]``)."""
    items = [t.strip() for t in (text.split(",") if isinstance(text, str) else text)]
    out = []
    for item in items:
        if not item:
            continue
        kind, _, amp = item.partition(":")
        kind = kind.strip()
        if kind not in DEFAULT_AMPLITUDE:
            raise ValueError(f"unknown test {kind!r} in --tests; expected compression_tension "
                             "or torsion[:amplitude]")
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
        object.__setattr__(self, "mu_range", tuple(float(v) for v in self.mu_range))
        object.__setattr__(self, "alpha_range", tuple(float(v) for v in self.alpha_range))
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
        for name, r in (("mu range", self.mu_range), ("alpha range", self.alpha_range)):
            if len(r) != 2 or not all(map(math.isfinite, r)) or not r[0] < r[1]:
                raise ValueError(f"{name} must be two finite numbers lo < hi, got {r}")
        if self.mu_range[0] <= 0:
            raise ValueError(f"mu range must be positive (log-uniform), got {self.mu_range}")
        if not -1.0 < self.nu0 < 0.5:
            raise ValueError(f"nu0 must lie in (-1, 0.5), got {self.nu0}")
        if self.radius_mm <= 0 or self.height_mm <= 0:
            raise ValueError("radius and height must be positive")
        if self.ends == "slip" and any(t.kind == "torsion" for t in self.tests):
            raise ValueError("torsion needs glued ends (frictionless plates cannot twist)")
        if self.refinement is None:
            from .geometry import DEFAULT_REFINEMENT

            object.__setattr__(self, "refinement",
                               DEFAULT_REFINEMENT if self.model == "axisymmetric" else 2)
        if int(self.refinement) != self.refinement or self.refinement < 0:
            raise ValueError(f"refinement must be a non-negative integer, got {self.refinement}")
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

    spec = SampleSpec(n=n, seed=seed, design=design, mu_range=tuple(mu_range),
                      alpha_range=tuple(alpha_range), refinement=0)
    if spec.design == "sobol":
        with warnings.catch_warnings():  # n need not be a power of two
            warnings.simplefilter("ignore", UserWarning)
            u = qmc.Sobol(d=2, scramble=True, seed=spec.seed).random(spec.n)
    else:
        u = qmc.LatinHypercube(d=2, seed=spec.seed).random(spec.n)
    lo, hi = np.log(spec.mu_range[0]), np.log(spec.mu_range[1])
    mu = np.clip(np.exp(lo + (hi - lo) * u[:, 0]), *spec.mu_range)
    a0, a1 = spec.alpha_range
    alpha = a0 + (a1 - a0) * u[:, 1]
    return pd.DataFrame({"sample": np.arange(spec.n, dtype=np.int64), "mu_kPa": mu,
                         "alpha": alpha})


def design_hash(design: pd.DataFrame) -> str:
    """sha256 of the float64 bytes of (mu_kPa, alpha), little-endian, row-major."""
    a = np.ascontiguousarray(design[["mu_kPa", "alpha"]].to_numpy(dtype="<f8"))
    return hashlib.sha256(a.tobytes()).hexdigest()


# ------------------------------------------------------------------------------ manifest
def software_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": sys.version.split()[0]}
    for key, dist in (("brainmech", "brainmech"), ("dolfinx", "fenics-dolfinx"),
                      ("numpy", "numpy"), ("scipy", "scipy"), ("pandas", "pandas"),
                      ("pyarrow", "pyarrow"), ("petsc4py", "petsc4py"), ("mpi4py", "mpi4py")):
        try:
            out[key] = version(dist)
        except PackageNotFoundError:
            out[key] = "unknown"
    return out


def make_manifest(spec: SampleSpec) -> dict:
    d = make_design(spec.n, spec.seed, spec.design, spec.mu_range, spec.alpha_range)
    return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "spec": spec.as_dict(),
            "parameters": {"mu_kPa": d.mu_kPa.tolist(), "alpha": d.alpha.tolist(),
                           "sha256": design_hash(d)},
            "software": software_versions(),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}


def _manifest_path(store) -> Path:
    return Path(store) / "manifest.json"


def read_manifest(store) -> dict:
    """The validated manifest of ``store``; :class:`StoreError` (one line) when unusable."""
    path = _manifest_path(store)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise StoreError(f"{store} is not a sample store (no manifest.json)") from None
    try:
        man = json.loads(text)
    except json.JSONDecodeError as exc:
        raise StoreError(f"{path} is corrupted (not valid JSON: {exc}); refusing to use "
                         "this store") from None
    if not isinstance(man, dict) or man.get("schema") != SCHEMA:
        found = man.get("schema") if isinstance(man, dict) else type(man).__name__
        raise StoreError(f"{path} is not a brainmech sample manifest (schema {found!r}, "
                         f"expected {SCHEMA!r}); refusing to use this store")
    if man.get("schema_version") != SCHEMA_VERSION:
        raise StoreError(f"{path} has schema version {man.get('schema_version')!r}; this "
                         f"brainmech reads version {SCHEMA_VERSION}")
    try:
        spec, par = man["spec"], man["parameters"]
        n = int(spec["n"])
        mu, alpha = np.asarray(par["mu_kPa"], dtype=float), np.asarray(par["alpha"], float)
        ok = mu.shape == alpha.shape == (n,)
        digest = design_hash(pd.DataFrame({"mu_kPa": mu, "alpha": alpha})) if ok else None
    except (KeyError, TypeError, ValueError) as exc:
        raise StoreError(f"{path} is corrupted (missing or malformed field {exc}); refusing "
                         "to use this store") from None
    if not ok or digest != par.get("sha256"):
        raise StoreError(f"{path} is corrupted (parameter values do not match their "
                         "count or checksum); refusing to use this store")
    return man


def check_manifest(stored: dict, wanted: dict, store) -> None:
    """Refuse a store made with other options, naming the first differing field."""
    s, w = stored["spec"], wanted["spec"]

    def show(key, v):
        if key == "tests" and isinstance(v, list):
            try:
                return ",".join(t["name"] for t in v)
            except (KeyError, TypeError):
                pass
        return repr(v)

    for key in w:
        if s.get(key) != w[key]:
            raise StoreError(
                f"{store} holds samples made with a different {key} (stored "
                f"{show(key, s.get(key))}, requested {show(key, w[key])}); use another --out "
                "directory")
    extra = sorted(set(s) - set(w))
    if extra:
        raise StoreError(f"{store} holds samples with an unknown option {extra[0]!r}; "
                         "use another --out directory")
    if stored["parameters"]["sha256"] != wanted["parameters"]["sha256"]:
        raise StoreError(
            f"{store}: the parameter design computed here differs from the stored one "
            f"(scipy {stored['software'].get('scipy')} -> {wanted['software'].get('scipy')}?)"
            "; use another --out directory")
    for key, v in wanted["software"].items():
        if stored.get("software", {}).get(key) != v:
            log.warning("%s was started with %s %s, continuing with %s", store, key,
                        stored.get("software", {}).get(key), v)


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".tmp-{uuid.uuid4().hex}-{path.name}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


# ------------------------------------------------------------------------------ chunks
def _arrow_schema():
    import pyarrow as pa

    types = {c: pa.float64() for c in COLUMNS}
    types.update({c: pa.int64() for c in _INT})
    types.update({c: pa.string() for c in _STR})
    return pa.schema([(c, types[c]) for c in COLUMNS])


def write_chunk(store, rows: list[dict], *, run_id: str, rank: int, seq: int) -> Path:
    """Write ``rows`` as ``chunks/<run>-r<rank>-<seq>.parquet`` via temp file + rename."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    d = Path(store) / "chunks"
    table = pa.Table.from_pylist(rows, schema=_arrow_schema())
    meta = {"run_id": run_id, "rank": rank, "seq": seq, "software": software_versions()}
    table = table.replace_schema_metadata({b"brainmech": json.dumps(meta).encode()})
    path = d / f"{run_id}-r{rank:05d}-{seq:05d}.parquet"
    tmp = d / f".tmp-{path.name}"
    try:
        pq.write_table(table, tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(d)
    return path


def chunk_files(store) -> list[Path]:
    """Completed chunks (temporary files of interrupted writes start with a dot)."""
    d = Path(store) / "chunks"
    return sorted(p for p in d.glob("*.parquet") if not p.name.startswith(".")) \
        if d.is_dir() else []


def read_chunks(store, columns: Sequence[str] | None = None, *,
                with_file: bool = False) -> pd.DataFrame:
    """All stored rows, *not* de-duplicated (see :func:`load_samples`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = _arrow_schema()
    cols = list(columns) if columns is not None else list(COLUMNS)
    tables = []
    for p in chunk_files(store):
        try:
            t = pq.read_table(p, columns=cols)
        except (OSError, pa.ArrowException, KeyError) as exc:
            raise StoreError(f"cannot read chunk {p}: {exc}") from None
        if with_file:
            t = t.append_column("chunk", pa.array([p.name] * t.num_rows, pa.string()))
        tables.append(t)
    if not tables:
        empty = pa.Table.from_pylist([], schema=pa.schema([schema.field(c) for c in cols]))
        if with_file:
            empty = empty.append_column("chunk", pa.array([], pa.string()))
        tables = [empty]
    return pa.concat_tables(tables).to_pandas()


def completed_samples(store, spec: SampleSpec | None = None) -> set[int]:
    """Samples with a stored row for every test (ok or failed)."""
    if spec is None:
        names = {t["name"] for t in read_manifest(store)["spec"]["tests"]}
    else:
        names = set(spec.test_names)
    df = read_chunks(store, ["sample", "test"])
    if df.empty:
        return set()
    df = df[df.test.isin(names)].drop_duplicates()
    counts = df.groupby("sample").test.nunique()
    return set(int(i) for i in counts.index[counts == len(names)])


# ------------------------------------------------------------------------------ loading
def load_samples(store, *, include_failed: bool = False) -> pd.DataFrame:
    """One tidy DataFrame: one row per parameter set, test and step.

    Columns: ``sample, mu_kPa, alpha, nu0, test, amplitude, step, time_s, cycle, branch,
    stretch, shear, nominal_stress_kPa, torque_mNmm, shear_stress_kPa, axial_force_mN,
    status, reason, newton_iterations, wall_time_s`` (NaN where a column does not apply to
    the test).  Rows of failed (sample, test) pairs (one row each, status ``failed`` and the
    reason, no steps) are left out unless ``include_failed``; :func:`summarize` counts them.
    Should a (sample, test) pair ever be stored twice, the copy in the first chunk (by
    name) is kept.  Stored parameters are checked against the manifest.
    """
    man = read_manifest(store)
    df = read_chunks(store, with_file=True)
    order = {t["name"]: k for k, t in enumerate(man["spec"]["tests"])}
    if not df.empty:
        first = df.groupby(["sample", "test"]).chunk.transform("min")
        df = df[df.chunk == first]
        mu = np.asarray(man["parameters"]["mu_kPa"])
        alpha = np.asarray(man["parameters"]["alpha"])
        s = df["sample"].to_numpy()
        bad = (s < 0) | (s >= len(mu)) | ~df.test.isin(order).to_numpy()
        if not bad.any():
            bad = (df.mu_kPa.to_numpy() != mu[s]) | (df.alpha.to_numpy() != alpha[s])
        if bad.any():
            row = df[bad].iloc[0]
            raise StoreError(f"chunk {row.chunk} of {store} holds a row (sample {row['sample']}"
                             f", test {row.test}) that does not belong to its manifest")
    if not include_failed:
        df = df[df.status == "ok"]
    df = df.assign(_t=df.test.map(order)).sort_values(["sample", "_t", "step"], kind="stable")
    df = df.drop(columns=["_t", "chunk"]).reset_index(drop=True)
    df = df.astype({c: "Int64" for c in _INT})
    if not include_failed:
        df = df.astype({c: "int64" for c in ("sample", "step", "cycle")})
    return df[list(COLUMNS)]


@dataclass
class SampleSummary:
    """Counts of a store: samples complete (ok or with a failed test), failed, missing."""

    total: int
    done: int
    failed: int
    missing: int
    failures: list[tuple[int, str, str]]  # (sample, test, reason)
    computed: int = 0  # samples computed by the run that returned this summary
    elapsed_s: float = 0.0  # wall time of that run's sampling loop (after set-up)

    @property
    def ok(self) -> int:
        return self.done - self.failed

    def line(self) -> str:
        return (f"{self.done}/{self.total} samples stored ({self.ok} ok, {self.failed} "
                f"failed), {self.missing} missing")


def summarize(store) -> SampleSummary:
    man = read_manifest(store)
    n = int(man["spec"]["n"])
    df = read_chunks(store, ["sample", "test", "status", "reason"])
    df = df.drop_duplicates(["sample", "test"])
    done = completed_samples(store)
    fails = df[(df.status == "failed") & df["sample"].isin(done)]
    fails = fails.sort_values(["sample", "test"])
    failures = [(int(r["sample"]), r.test, r.reason) for _, r in fails.iterrows()]
    return SampleSummary(total=n, done=len(done), failed=int(fails["sample"].nunique()),
                         missing=n - len(done), failures=failures)


# ------------------------------------------------------------------------------ solving
def solve_sample(model, spec: SampleSpec, sample: int, mu: float, alpha: float) -> list[dict]:
    """Rows of one parameter set: one per (test, step), or one ``failed`` row per test."""
    from .model import MaterialParameters
    from .protocols import CONTROL
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


class _Counter:
    """Shared int64 counters in rank 0's MPI window, updated with atomic ``Fetch_and_op``.

    Slots: 0 next position in the pending list, 1 samples done, 2 samples failed.
    """

    def __init__(self, comm):
        from mpi4py import MPI

        self.MPI = MPI
        self.win = MPI.Win.Allocate(3 * 8 if comm.rank == 0 else 0, 8, comm=comm)
        if comm.rank == 0:
            np.frombuffer(self.win.tomemory(), dtype=np.int64)[:] = 0
        comm.Barrier()

    def add(self, slot: int, value: int = 1) -> int:
        MPI = self.MPI
        one = np.array([value], dtype=np.int64)
        res = np.zeros(1, dtype=np.int64)
        self.win.Lock(0, MPI.LOCK_SHARED)
        self.win.Fetch_and_op([one, MPI.INT64_T], [res, MPI.INT64_T], 0, slot, MPI.SUM)
        self.win.Unlock(0)
        return int(res[0])

    def read(self, slot: int) -> int:
        return self.add(slot, 0)

    def free(self):
        self.win.Free()


def _prepare_store(spec: SampleSpec, store: Path):
    """Rank 0: create or check the manifest, take the lock, clean temp files, list the work.

    Returns (manifest, pending sample indices, lock file object).
    """
    import fcntl

    wanted = make_manifest(spec)
    store.mkdir(parents=True, exist_ok=True)
    (store / "chunks").mkdir(exist_ok=True)
    lock = open(store / ".lock", "a")  # noqa: SIM115 - held for the whole run
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        lock.close()
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            raise StoreError(f"{store} is in use by another sampling job") from None
        raise
    try:
        if _manifest_path(store).exists():
            man = read_manifest(store)
            check_manifest(man, wanted, store)
        else:
            if chunk_files(store):
                raise StoreError(f"{store} holds chunks but no manifest.json; refusing to "
                                 "use this store")
            _write_atomic(_manifest_path(store),
                          (json.dumps(wanted, indent=1) + "\n").encode())
            man = wanted
        for p in list((store / "chunks").glob(".tmp-*")) + list(store.glob(".tmp-*")):
            log.info("removing %s (left by an interrupted run)", p.name)
            p.unlink(missing_ok=True)
        done = completed_samples(store, spec)
    except BaseException:
        lock.close()
        raise
    pending = [i for i in range(spec.n) if i not in done]
    return man, pending, lock


def run_sampling(spec: SampleSpec, store, *, comm=None, chunk_size: int = 16,
                 flush_seconds: float = 120.0, progress: bool = True,
                 model_factory: Callable | None = None) -> SampleSummary:
    """Compute every sample of ``spec`` missing from ``store``; collective over ``comm``.

    Each rank builds one model on ``MPI.COMM_SELF`` (rank 0 first, so the JIT cache is
    filled once), then repeatedly takes the next pending index from the shared counter.
    A rank writes its results as a chunk every ``chunk_size`` samples or ``flush_seconds``,
    and at the end.  Returns the store's summary (on every rank).
    """
    from mpi4py import MPI

    comm = MPI.COMM_WORLD if comm is None else comm
    store = Path(store)
    if chunk_size < 1:
        raise ValueError("chunk size must be at least 1")
    payload, lock = None, None
    if comm.rank == 0:
        try:
            man, pending, lock = _prepare_store(spec, store)
            payload = (pending, man["parameters"]["mu_kPa"], man["parameters"]["alpha"])
        except (ValueError, OSError) as exc:
            payload = exc if isinstance(exc, StoreError) else StoreError(str(exc))
    payload = comm.bcast(payload, root=0)
    if isinstance(payload, Exception):
        raise payload
    pending, mu, alpha = payload
    run_id = comm.bcast(time.strftime("%Y%m%dT%H%M%S-") + uuid.uuid4().hex[:8]
                        if comm.rank == 0 else None, root=0)
    log.info("%s: %d of %d samples to compute on %d rank(s)", store, len(pending), spec.n,
             comm.size)
    try:
        return _run(spec, store, comm, pending, mu, alpha, run_id, chunk_size, flush_seconds,
                    progress, model_factory)
    finally:
        if lock is not None:
            lock.close()


def _build_model(spec: SampleSpec):
    from mpi4py import MPI

    from .api import make_geometry
    from .model import ForwardModel

    g = make_geometry(spec.model, spec.radius_mm, spec.height_mm, spec.refinement,
                      comm=MPI.COMM_SELF)
    return ForwardModel(g, n_terms=1, volumetric=spec.volumetric, ends=spec.ends)


def _run(spec, store, comm, pending, mu, alpha, run_id, chunk_size, flush_seconds, progress,
         model_factory):
    factory = model_factory or _build_model
    t_setup = time.perf_counter()
    model = None
    if pending:
        # Rank 0 compiles (or loads) the forms first; the others then find them in the
        # on-disk JIT cache instead of racing to write the same files.
        if comm.rank == 0:
            model = factory(spec)
        comm.Barrier()
        if comm.rank != 0:
            model = factory(spec)
    counter = _Counter(comm)
    bar = None
    if progress and comm.rank == 0:
        from tqdm import tqdm

        bar = tqdm(total=spec.n, initial=spec.n - len(pending), unit="sample",
                   desc="samples", disable=None, dynamic_ncols=True)
        bar.set_postfix(failed=0)
    t0 = time.perf_counter()
    log.debug("rank %d set up in %.1f s", comm.rank, t0 - t_setup)
    buffer: list[dict] = []
    seq, computed, t_flush = 0, 0, time.perf_counter()
    seen = [0, 0]

    def update_bar():
        if bar is None:
            return
        done, failed = counter.read(1), counter.read(2)
        if done != seen[0] or failed != seen[1]:
            bar.update(done - seen[0])
            bar.set_postfix(failed=failed)
            seen[:] = [done, failed]

    def flush():
        nonlocal buffer, seq, t_flush
        if buffer:
            write_chunk(store, buffer, run_id=run_id, rank=comm.rank, seq=seq)
            seq += 1
            buffer = []
        t_flush = time.perf_counter()

    try:
        while True:
            pos = counter.add(0)
            if pos >= len(pending):
                break
            i = pending[pos]
            rows = solve_sample(model, spec, i, mu[i], alpha[i])
            buffer.extend(rows)
            computed += 1
            failed = any(r["status"] == "failed" for r in rows)
            if len(buffer) and (computed % chunk_size == 0
                                or time.perf_counter() - t_flush > flush_seconds):
                flush()
            counter.add(1)
            if failed:
                counter.add(2)
            update_bar()
        flush()
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
        if bar is not None:
            bar.close()
    elapsed = time.perf_counter() - t0
    counter.free()
    comm.Barrier()
    summary = summarize(store) if comm.rank == 0 else None
    summary = comm.bcast(summary, root=0)
    summary.computed = comm.allreduce(computed)
    summary.elapsed_s = comm.allreduce(elapsed, op=_max_op())
    log.info("%s: %s; computed %d in %.1f s", store, summary.line(), summary.computed,
             summary.elapsed_s)
    for s, t, reason in summary.failures[:5]:
        log.warning("sample %d, %s failed: %s", s, t, reason)
    if len(summary.failures) > 5:
        log.warning("... and %d more failed tests (load_samples(..., include_failed=True))",
                    len(summary.failures) - 5)
    return summary


def _max_op():
    from mpi4py import MPI

    return MPI.MAX
