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

So every compilation (inside :func:`compiling`: of a form, an expression, or the element
and dofmap of a function space, which DOLFINx 0.5 compiles when the space is made) holds an
exclusive lock on a file of the cache
(``flock``: released when the process ends, however it ends): while it is held no other
process of this project is compiling, so a C file without its mark was left by a stopped
process; it is moved aside (FFCx's own ``.c.failed``) and the form compiled afresh. The
lock is taken only when FFCx is about to look for a module the cache has not finished
(FFCx's ``get_cached_module``, wrapped here): a form the cache holds is loaded without it,
so that on a cold cache one rank does not wait for the other's compilation of another form
each time it makes a form it has (measured: one core idle while the other compiled). On a
distributed mesh DOLFINx compiles on rank 0 and the other ranks load the result after a
broadcast: there rank 0 alone takes the lock (another rank holding it while it waits for
rank 0's broadcast would block rank 0 for ever). A program outside this project that
compiles into the same cache does not take the lock: do not run one beside it.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
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


class _Lock:
    """The cache's lock, taken when first needed (:meth:`take`) and held until :meth:`drop`."""

    def __init__(self, cache: Path):
        self.cache = cache
        self.fh = None

    def take(self) -> None:
        if self.fh is not None:
            return
        self.cache.mkdir(parents=True, exist_ok=True)
        fh = open(self.cache / LOCK_NAME, "a")
        fcntl.flock(fh, fcntl.LOCK_EX)
        self.fh = fh
        for c in unfinished(self.cache):
            log.warning("JIT cache: %s was left unfinished by a stopped process; moved "
                        "aside, the form is compiled afresh", c.name)
            c.replace(c.with_suffix(".c.failed"))

    def drop(self) -> None:
        if self.fh is not None:
            fh, self.fh = self.fh, None
            fcntl.flock(fh, fcntl.LOCK_UN)
            fh.close()


_held: _Lock | None = None  # the lock of the compilation in progress (one per process)


def _locking(get_cached_module):
    """FFCx's ``get_cached_module`` that first takes the lock of :func:`compiling` unless
    the module is finished (its ``.c.cached`` mark exists): then it only loads it."""
    @functools.wraps(get_cached_module)
    def wrapped(module_name, object_names, cache_dir, timeout):
        ready = Path(cache_dir) / f"{module_name}.c.cached"
        if _held is not None and not ready.exists():
            _held.take()
        return get_cached_module(module_name, object_names, cache_dir, timeout)

    wrapped.brainmech_locking = True
    return wrapped


def _wrap_ffcx() -> None:
    """Route FFCx's cache look-ups through :func:`_locking` (once per process)."""
    from ffcx.codegeneration import jit

    if not getattr(jit.get_cached_module, "brainmech_locking", False):
        jit.get_cached_module = _locking(jit.get_cached_module)


@contextlib.contextmanager
def compiling(expr=None, *, mesh=None):
    """Let the compilation of ``expr`` (a form or an expression) or of the element and
    dofmap of a function space on ``mesh`` hold the cache's lock (on rank 0 of the mesh)
    from the moment FFCx needs a module the cache has not finished until the end of the
    block, after moving aside what stopped processes left unfinished."""
    global _held
    if _held is not None or (mesh.comm.rank if mesh is not None else _rank(expr)) != 0:
        yield  # nested in a compilation that holds the lock when needed, or not rank 0
        return
    _wrap_ffcx()
    _held = _Lock(cache_dir())
    try:
        yield
    finally:
        lock, _held = _held, None
        lock.drop()
