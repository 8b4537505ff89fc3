"""Atomic table output: readers never see a partial file, a failure leaves the old one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pandas as pd


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_table_atomic(df: pd.DataFrame, path, *, float_format: str | None = None) -> None:
    """Write ``df`` without its index as CSV or Parquet (by extension) through a temporary
    file in the same directory, fsync and ``os.replace``; permissions follow the umask.
    CSV floats keep round-trip precision unless ``float_format`` is given."""
    path = os.fspath(path)
    suffix = Path(path).suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise ValueError(f"{path}: expected a .csv or .parquet file name")
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise FileNotFoundError(f"{path}: output directory does not exist ({d})")
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp-", suffix=suffix)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as fh:
            if suffix == ".csv":
                text = df.to_csv(index=False, lineterminator="\n", float_format=float_format)
                fh.write(text.encode("utf-8"))
            else:
                df.to_parquet(fh, index=False)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_text_atomic(path, text: str) -> None:
    """Write ``text`` through a temporary file in the same directory and ``os.replace``:
    readers see the old file or the whole new one, never a partial one."""
    path = os.fspath(path)
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), prefix=".tmp-")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(path, obj, **kw) -> None:
    """JSON document (``json.dumps`` options in ``kw``) written with write_text_atomic."""
    import json

    write_text_atomic(path, json.dumps(obj, **kw))
