"""The one way the tool writes files: atomically, and only once everything succeeded.

* ``write_*_atomic``: a file is written through a temporary file in its directory, flushed
  and renamed over the target, so readers see the old file or the whole new one.
* :func:`check_output_file` / :func:`check_output_dir`: an output is checked for
  writability *before* any work, so a typo in ``--out`` costs nothing.
* :func:`staged_directory`: the files of one result are written into a hidden sibling
  directory and moved into place only when the whole result succeeded; on failure nothing
  is left behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pandas as pd

TABLE_SUFFIXES = (".csv", ".parquet")


class OutputError(ValueError):
    """An output location cannot be used; the message names it in one line."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def fsync_dir(d) -> None:
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


def write_atomic(path, write: Callable, *, binary: bool = True, durable: bool = False) -> None:
    """Call ``write(fh)`` on a temporary file beside ``path`` and rename it over ``path``;
    permissions follow the umask.  ``durable`` also fsyncs the file and its directory (a
    store that must survive a power loss)."""
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise OutputError(f"{path}: output directory does not exist ({d})")
    fd, tmp = tempfile.mkstemp(dir=d, prefix=f".tmp-{uuid.uuid4().hex[:8]}-")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb" if binary else "w") as fh:
            write(fh)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    if durable:
        fsync_dir(d)


def write_bytes_atomic(path, data: bytes, *, durable: bool = False) -> None:
    write_atomic(path, lambda fh: fh.write(data), durable=durable)


def write_text_atomic(path, text: str) -> None:
    write_atomic(path, lambda fh: fh.write(text), binary=False)


def write_json_atomic(path, obj, **kw) -> None:
    """JSON document (``json.dumps`` options in ``kw``)."""
    write_text_atomic(path, json.dumps(obj, **kw))


def write_table_atomic(df: pd.DataFrame, path, *, float_format: str | None = None) -> None:
    """``df`` without its index as CSV or Parquet (by extension).  CSV floats keep
    round-trip precision unless ``float_format`` is given."""
    suffix = Path(path).suffix.lower()
    if suffix not in TABLE_SUFFIXES:
        raise OutputError(f"{path}: expected a .csv or .parquet file name")
    if suffix == ".csv":
        text = df.to_csv(index=False, lineterminator="\n", float_format=float_format)
        write_bytes_atomic(path, text.encode("utf-8"))
    else:
        write_atomic(path, lambda fh: df.to_parquet(fh, index=False))


def write_figure_atomic(fig, path, **kw) -> None:
    """A matplotlib figure (format from the suffix)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    write_atomic(path, lambda fh: fig.savefig(fh, format=fmt, **kw))


# ------------------------------------------------------------------------------ checks
def _probe(d: Path, what: str) -> None:
    try:
        fd, tmp = tempfile.mkstemp(dir=d, prefix=".probe-")
    except OSError as e:
        raise OutputError(f"{what}: cannot write in {d} ({e.strerror or e})") from None
    os.close(fd)
    os.unlink(tmp)


def check_output_file(path, *, suffixes: tuple[str, ...] | None = None) -> None:
    """Refuse, before any work, an output file that cannot be written: missing or
    unwritable directory, a directory in its place, a wrong suffix."""
    p = Path(path)
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise OutputError(f"{path}: expected a file name ending in {' or '.join(suffixes)}")
    if p.is_dir():
        raise OutputError(f"{path}: is a directory, expected a file name")
    d = p.parent if str(p.parent) else Path(".")
    if not d.is_dir():
        raise OutputError(f"{path}: output directory does not exist ({d})")
    _probe(d, str(path))


def check_output_dir(path) -> None:
    """Refuse, before any work, an output directory that cannot be created or written."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{path}: exists and is not a directory")
    parent = p if p.exists() else p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{path}: {parent} is not a directory")
    _probe(parent, str(path))


@contextlib.contextmanager
def staged_directory(final) -> Iterator[Path]:
    """Yield a hidden directory beside ``final`` to write a result into; on success its
    files replace those of ``final`` (created if missing), on failure it is removed and
    ``final`` is untouched."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.stage-"))
    try:
        yield stage
    except (OSError, ValueError) as exc:  # name the user's path, never the stage
        shutil.rmtree(stage, ignore_errors=True)
        msg = str(exc)
        if str(stage) not in msg:
            raise
        raise OutputError(msg.replace(str(stage), str(final))) from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    try:
        if not final.exists():
            os.replace(stage, final)
            return
        for src in sorted(stage.rglob("*"), key=lambda q: len(q.parts)):
            dst = final / src.relative_to(stage)
            if src.is_dir():
                dst.mkdir(exist_ok=True)
            else:
                os.replace(src, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
