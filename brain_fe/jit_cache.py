"""Safe use of the JIT cache that DOLFINx and FFCx share between processes.

FFCx marks a form being compiled by creating its C file in the cache and the end of the
compilation by a ``.c.cached`` file; a process that needs the same form waits for that
mark at most ``timeout`` seconds (10 by default) and then raises a ``TimeoutError``. Two
things went wrong with that here:

* a spectral Ogden form takes 10-30 s to compile (minutes on loaded cores), so the second
  of two ranks needing a new model at once timed out; inside a diagnosis that failure
  looked like a candidate whose model cannot be solved, so the verdict depended on which
  rank compiled first;
* a process stopped during a compilation leaves its C file without the mark, and every
  later process waited for a compilation that never ends and failed the same way.

So every compilation (:func:`compiling`: of a form, an expression, or the element and
dofmap of a function space, which DOLFINx compiles when the space is made) holds an
exclusive lock on a file of the cache
(``flock``: released when the process ends, however it ends): while it is held no other
process of this project is compiling, so a C file without its mark was left by a stopped
process; it is moved aside (FFCx's own ``.c.failed``) and the form compiled afresh. On a
distributed mesh DOLFINx compiles on rank 0 and the other ranks load the result after a
broadcast: there rank 0 alone takes the lock (another rank holding it while it waits for
rank 0's broadcast would block rank 0 for ever). A program outside this project that
compiles into the same cache does not take the lock: do not run one beside it.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
from pathlib import Path

log = logging.getLogger(__name__)

LOCK_NAME = "brainmech-jit.lock"
# How long FFCx waits for a compilation of another process (one outside this project,
# which does not take the lock): generous, the compilations are long
TIMEOUT_S = 900


def cache_dir() -> Path:
    """The JIT cache directory of DOLFINx (its options, ``~/.cache/fenics`` by default)."""
    from dolfinx import jit

    get = getattr(jit, "get_options", None) or jit.get_parameters  # 0.8+ / 0.5
    return Path(str(get()["cache_dir"])).expanduser()


def _rank(expr) -> int | None:
    """This process's rank in the communicator of the mesh ``expr`` lives on; None when
    it cannot be told."""
    def domains():
        yield lambda: expr.ufl_domain()
        yield lambda: expr.ufl_domains()[0]
        from ufl.domain import extract_unique_domain

        yield lambda: extract_unique_domain(expr)

    for get in domains():
        try:
            return int(get().ufl_cargo().comm.rank)
        except Exception:  # noqa: BLE001, S112 - try the next spelling (UFL versions)
            continue
    return None


def unfinished(cache: Path) -> list[Path]:
    """The C files of ``cache`` without FFCx's mark of a finished compilation."""
    return [c for c in sorted(cache.glob("*.c")) if not c.with_suffix(".c.cached").exists()]


@contextlib.contextmanager
def compiling(expr=None, *, mesh=None):
    """Hold the cache's lock around the compilation of ``expr`` (a form or an expression)
    or of the element and dofmap of a function space on ``mesh`` (on rank 0 of the mesh)
    after moving aside what stopped processes left unfinished."""
    if (mesh.comm.rank if mesh is not None else _rank(expr)) != 0:
        yield
        return
    cache = cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / LOCK_NAME, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            for c in unfinished(cache):
                log.warning("JIT cache: %s was left unfinished by a stopped process; moved "
                            "aside, the form is compiled afresh", c.name)
                c.replace(c.with_suffix(".c.failed"))
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
