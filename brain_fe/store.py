"""The sample store: a directory of forward-model results that survives interruptions.

::

    DIR/manifest.json     schema, the full design spec, the parameter values, versions
    DIR/chunks/*.parquet  results, tidy rows; each chunk written by one rank, atomically
    DIR/.lock             held (flock) by rank 0 while a job writes to the store

The manifest is written together with the first result (never before: a run that fails at
set-up leaves no store behind).  A sample's rows are always written in one chunk, through a
temporary file and a rename, so a kill loses at most the sample in progress on each rank and
never leaves a partial or duplicated sample; a run merges its own chunks into one per rank
when it ends.  :func:`load_samples` returns the tidy table (one row per parameter set, test
and step), de-duplicated and checked against the manifest.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .io import fsync_dir, write_bytes_atomic

log = logging.getLogger(__name__)

SCHEMA = "brainmech.samples"
SCHEMA_VERSION = 1

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


def design_hash(design: pd.DataFrame) -> str:
    """sha256 of the float64 bytes of (mu_kPa, alpha), little-endian, row-major."""
    a = np.ascontiguousarray(design[["mu_kPa", "alpha"]].to_numpy(dtype="<f8"))
    return hashlib.sha256(a.tobytes()).hexdigest()


def software_versions() -> dict[str, str]:
    import sys
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": sys.version.split()[0]}
    for key, dist in (("brainmech", "brainmech"), ("dolfinx", "fenics-dolfinx"),
                      ("numpy", "numpy"), ("scipy", "scipy"), ("pandas", "pandas"),
                      ("pyarrow", "pyarrow"), ("petsc4py", "petsc4py"), ("mpi4py", "mpi4py")):
        try:
            out[key] = version(dist)
        except PackageNotFoundError:
            out[key] = "unknown"
    from ._compat import ARCH_FLAGS  # the kernels' instruction set: the last digits

    out["jit_arch_flags"] = " ".join(ARCH_FLAGS)
    return out


# ------------------------------------------------------------------------------ manifest
def _manifest_path(store) -> Path:
    return Path(store) / "manifest.json"


def manifest_path(store) -> Path:
    return _manifest_path(store)


def write_manifest(store, manifest: dict) -> None:
    write_bytes_atomic(_manifest_path(store), (json.dumps(manifest, indent=1) + "\n").encode(),
                       durable=True)


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


# ------------------------------------------------------------------------------ chunks
def _arrow_schema():
    import pyarrow as pa

    types = {c: pa.float64() for c in COLUMNS}
    types.update({c: pa.int64() for c in _INT})
    types.update({c: pa.string() for c in _STR})
    return pa.schema([(c, types[c]) for c in COLUMNS])


def write_chunk(store, rows: list[dict], *, run_id: str, rank: int, seq) -> Path:
    """Write ``rows`` as ``chunks/<run>-r<rank>-<seq>.parquet`` via temp file + rename."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    d = Path(store) / "chunks"
    # A missing text (pandas >= 3 reads it back as NaN) is stored as a null string.
    rows = [{**r, **{c: None for c in _STR if isinstance(r.get(c), float) and r[c] != r[c]}}
            for r in rows]
    table = pa.Table.from_pylist(rows, schema=_arrow_schema())
    meta = {"run_id": run_id, "rank": rank, "seq": seq, "software": software_versions()}
    table = table.replace_schema_metadata({b"brainmech": json.dumps(meta).encode()})
    tag = f"{seq:05d}" if isinstance(seq, int) else str(seq)
    path = d / f"{run_id}-r{rank:05d}-{tag}.parquet"
    tmp = d / f".tmp-{path.name}"
    try:
        pq.write_table(table, tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(d)
    return path


def merge_chunks(store, paths: list[Path], *, run_id: str, rank: int) -> None:
    """Replace one rank's chunks of one run by a single chunk (written first, then the
    parts removed: a kill in between leaves duplicates, which :func:`load_samples` drops)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if len(paths) < 2:
        return
    rows = pa.concat_tables([pq.read_table(p) for p in paths]).to_pylist()
    write_chunk(store, rows, run_id=run_id, rank=rank, seq="all")
    for p in paths:
        p.unlink(missing_ok=True)
    fsync_dir(Path(store) / "chunks")


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


def completed_samples(store, test_names: Sequence[str] | None = None) -> set[int]:
    """Samples with a stored row for every test (ok or failed)."""
    if test_names is None:
        names = {t["name"] for t in read_manifest(store)["spec"]["tests"]}
    else:
        names = set(test_names)
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
