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

So every compilation (of a form, an expression, or the element and dofmap of a function
space, which DOLFINx 0.5 compiles when the space is made) holds an exclusive lock on a file
of the cache (``flock``: released when the process ends, however it ends): while it is held
no other process of this project is compiling, so a C file without its mark was left by a
stopped process; it is moved aside (FFCx's own ``.c.failed``) and the form compiled
afresh. :func:`install` wraps FFCx's look-up of a module (``get_cached_module``, where FFCx
creates the C file of a module it is about to compile) so that it takes the lock unless the
module is finished, and FFCx's ``compile_*`` functions so that they release it when they
return. A form the cache holds is thus loaded without the lock (on a cold cache one rank
no longer waits for the other's compilation of another form each time it makes a form it
has), and the lock is never held across a collective call: on a distributed mesh DOLFINx
compiles on rank 0 and the other ranks load the module after rank 0 has finished. A program
outside this project that compiles into the same cache does not take the lock: do not run
one beside it.
"""

from __future__ import annotations

import fcntl
import functools
import logging
from pathlib import Path

log = logging.getLogger(__name__)

LOCK_NAME = "brainmech-jit.lock"
# How long FFCx waits for a compilation of another process (one outside this project,
# which does not take the lock): generous, the compilations are long
TIMEOUT_S = 900
COMPILERS = ("compile_forms", "compile_expressions", "compile_elements")  # those FFCx has


def cache_dir() -> Path:
    """The JIT cache directory of DOLFINx (its options, ``~/.cache/fenics`` by default)."""
    from dolfinx import jit

    get = getattr(jit, "get_options", None) or jit.get_parameters  # 0.8+ / 0.5
    return Path(str(get()["cache_dir"])).expanduser()


def unfinished(cache: Path) -> list[Path]:
    """The C files of ``cache`` without FFCx's mark of a finished compilation."""
    return [c for c in sorted(cache.glob("*.c")) if not c.with_suffix(".c.cached").exists()]


def _lock(cache: Path):
    """Take the lock of ``cache`` (waiting for it), move aside what stopped processes left
    unfinished, and return the open lock file (unlocked by closing it)."""
    cache.mkdir(parents=True, exist_ok=True)
    fh = open(cache / LOCK_NAME, "a")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX)
    except BaseException:
        fh.close()
        raise
    for c in unfinished(cache):
        log.warning("JIT cache: %s was left unfinished by a stopped process; moved "
                    "aside, the form is compiled afresh", c.name)
        c.replace(c.with_suffix(".c.failed"))
    return fh


_held = None  # the lock file taken by a look-up, closed when its compile_* call returns


def _looking_up(get_cached_module):
    """FFCx's ``get_cached_module`` that first takes the cache's lock unless the module is
    finished (its C file and ``.c.cached`` mark both exist): then it only loads it."""
    @functools.wraps(get_cached_module)
    def wrapped(module_name, object_names, cache_dir, timeout, *args, **kwargs):
        global _held
        c_file = Path(cache_dir) / f"{module_name}.c"
        ready = c_file.with_suffix(".c.cached")
        if not (c_file.exists() and ready.exists()):
            if _held is None:
                _held = _lock(Path(cache_dir))
            if ready.exists() and not c_file.exists():  # FFCx would compile and then fail
                log.warning("JIT cache: %s has a mark but no C file; mark moved aside, the "
                            "form is compiled afresh", ready.name)
                ready.replace(ready.with_suffix(".cached.orphan"))
        return get_cached_module(module_name, object_names, cache_dir, timeout, *args,
                                 **kwargs)

    wrapped.brainmech_wrapped = True
    return wrapped


def _releasing(compile_objects):
    """FFCx's ``compile_forms`` (or expressions, elements) that drops the cache's lock when
    it returns (compiled, loaded or failed), and gives the root logger its handlers back:
    FFCx 0.9 swaps them for a string buffer while the C compiler runs and does not restore
    them when the compilation raises, so every later log line would be lost."""
    @functools.wraps(compile_objects)
    def wrapped(*args, **kwargs):
        global _held
        root = logging.getLogger()
        handlers = list(root.handlers)
        try:
            return compile_objects(*args, **kwargs)
        finally:
            root.handlers = handlers
            fh, _held = _held, None
            if fh is not None:
                fh.close()  # closing the file releases its flock

    wrapped.brainmech_wrapped = True
    return wrapped


def install() -> None:
    """Route FFCx's module look-ups and compilations through the cache's lock (once per
    process; called when ``brain_fe._compat`` is imported)."""
    from ffcx.codegeneration import jit

    if not getattr(jit.get_cached_module, "brainmech_wrapped", False):
        jit.get_cached_module = _looking_up(jit.get_cached_module)
    for name in COMPILERS:
        fn = getattr(jit, name, None)
        if fn is not None and not getattr(fn, "brainmech_wrapped", False):
            setattr(jit, name, _releasing(fn))
