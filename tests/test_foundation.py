"""First end-to-end check on both lanes: a hyperelastic solve on a gmsh mesh against a
closed-form value.

With frictionless (slip) ends the compressed cylinder deforms homogeneously, so the
quadratic elements represent the exact solution and the nominal stress must equal the
semi-analytic uniaxial value (lateral stretch root-solved in references.py). Tolerance
1e-4 relative: the curved second-order boundary approximates pi R^2 to ~1e-5.
"""

import pytest
from mpi4py import MPI
from references import homogeneous_uniaxial


@pytest.mark.mpi
def test_gmsh_cylinder_slip_compression_matches_closed_form():
    from brain_fe import geometry
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    g = geometry.cylinder3d(refinement=1, comm=MPI.COMM_WORLD)
    model = ForwardModel(g, ends="slip")
    params = MaterialParameters(mu=(1.0,), alpha=(-20.0,), kappa=100.0)
    df = model.run(Protocol("compression_tension", (1.0, 0.85), max_increment=0.05), params)
    for lam, p in zip(df.stretch, df.nominal_stress_kPa, strict=True):
        if lam < 1.0:
            assert p == pytest.approx(homogeneous_uniaxial(lam), rel=1e-4)


JIT_FORM = """
import sys
import ufl
from dolfinx import mesh
from mpi4py import MPI
from brain_fe import _compat
msh = mesh.create_unit_square(MPI.COMM_SELF, 2, 2)
V = _compat.scalar_space(msh, 1)
u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
x = ufl.SpatialCoordinate(msh)
_compat.form((1 + float(sys.argv[1]) * x[0]) * u * v * ufl.dx)
print("compiled")
"""


def test_a_compilation_left_unfinished_is_done_again(tmp_path):
    """A process stopped while it compiles a form leaves the form's C file in the JIT cache
    without FFCx's mark of a finished compilation; FFCx then makes every later process
    wait for it and fail (a TimeoutError that a diagnosis took for a candidate whose model
    cannot be solved: 'JIT compilation timed out' on rank 0 of a real run). Under the
    cache's lock such a file can only be a stopped process's: it is moved aside and the
    form compiled again, in seconds."""
    import random
    import subprocess
    import sys

    from brain_fe import jit_cache

    factor = repr(random.uniform(1.0, 2.0))  # a form no earlier run compiled
    cache = jit_cache.cache_dir()

    def compile_it():
        return subprocess.run([sys.executable, "-c", JIT_FORM, factor], capture_output=True,
                              text=True, timeout=120)

    before = set(cache.glob("libffcx_forms_*")) if cache.exists() else set()
    assert compile_it().stdout.strip() == "compiled"
    new = sorted(set(cache.glob("libffcx_forms_*")) - before)
    c_file = next(p for p in new if p.suffix == ".c")
    for p in new:  # as a process stopped during the compilation leaves it: the C file only
        if p != c_file:
            p.unlink()
    assert jit_cache.unfinished(cache).count(c_file) == 1
    again = compile_it()  # without the lock: 900 s of waiting, then a TimeoutError
    assert again.returncode == 0 and again.stdout.strip() == "compiled", again.stderr
    assert c_file.with_suffix(".c.cached").exists()
    assert c_file.with_suffix(".c.failed").exists()
    assert "left unfinished by a stopped process" in again.stderr
    for p in set(cache.glob(c_file.stem + "*")):  # leave the cache as it was
        p.unlink()


JIT_FORM_SAID = JIT_FORM.replace("_compat.form(", "print('making', flush=True)\n_compat.form(")


def test_a_cached_form_is_loaded_while_another_process_compiles(tmp_path):
    """The cache's lock is taken only for a module the cache has not finished: while
    another process holds it (compiling), a form the cache holds is made at once (before:
    every form waited, so on a cold cache one rank idled during the other's compilations),
    and a new form waits for the lock and is compiled once it is free.  The processes use
    a cache of their own (``XDG_CACHE_HOME``), so the user's cache is not touched."""
    import fcntl
    import os
    import subprocess
    import sys
    import time

    from brain_fe import jit_cache

    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path))
    cache = tmp_path / "fenics"

    def start(factor):
        return subprocess.Popen([sys.executable, "-c", JIT_FORM_SAID, factor], text=True,
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    out, err = start("1.5").communicate(timeout=300)  # compiles the element and the form
    assert out.split() == ["making", "compiled"], err
    made = set(cache.glob("libffcx_*"))
    with open(cache / jit_cache.LOCK_NAME, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # as a process compiling another form holds it
        try:
            out, err = start("1.5").communicate(timeout=120)  # before: waited for ever
            assert out.split() == ["making", "compiled"], err
            waiting = start("2.5")
            assert waiting.stdout.readline().strip() == "making"  # imports done, space made
            time.sleep(3)
            assert waiting.poll() is None  # waits for the lock ...
            assert set(cache.glob("libffcx_*")) == made  # ... before making a C file
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
    out, err = waiting.communicate(timeout=300)
    assert waiting.returncode == 0 and out.split() == ["compiled"], err
    assert len(set(cache.glob("libffcx_forms_*.c.cached")) - made) == 1


def test_a_failed_compilation_leaves_the_log_handlers_in_place():
    """FFCx 0.9 replaces the root logger's handlers by a string buffer while its C
    compiler runs and restores them only when the compilation succeeds; after a failed one
    every log line of the run would vanish.  The wrapped compile functions restore them,
    and release the cache's lock, whatever happens."""
    import logging

    from brain_fe import jit_cache

    root = logging.getLogger()
    mine = logging.NullHandler()
    root.addHandler(mine)
    before = list(root.handlers)

    def failing_compile(*args, **kwargs):  # what FFCx 0.9 does when the compiler fails
        root.handlers = [logging.StreamHandler()]
        raise RuntimeError("compiler failed")

    try:
        with pytest.raises(RuntimeError, match="compiler failed"):
            jit_cache._releasing(failing_compile)()
        assert root.handlers == before
        assert jit_cache._held is None
    finally:
        root.removeHandler(mine)


def _set_constant_count(n: int) -> int:
    """Let UFL count the next Constant as ``n`` (UFL 2022: an integer; 2024: a counter), as
    in a process that had made n Constants before; returns the count it replaces."""
    import itertools

    from ufl.constant import Constant

    if hasattr(Constant, "_globalcount"):
        old, Constant._globalcount = Constant._globalcount, n
    else:
        old = 0 if Constant._counter is None else next(Constant._counter)
        Constant._counter = itertools.count(n)
    return old


def test_a_model_compiles_to_the_same_forms_whatever_was_built_before():
    """The JIT cache's key is the form's UFL signature. UFL orders the operands of sums
    canonically and compares Constants by their repr, which ends in a global count, as
    text: a model whose Constants straddle a power of ten (count 97 to 105: '100' sorts
    before '97') got another signature than the same model built first, and compiled again
    (every diagnosis on a fresh cache did, 20-30 s a form). Built after 97 Constants, a
    two-term model must have the signature it has when built first."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    def signature(count: int) -> str:
        _set_constant_count(count)
        g = geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF)  # a mesh of its own
        return ForwardModel(g, n_terms=2).residual_ufl.signature()

    before = _set_constant_count(0)
    try:
        assert signature(97) == signature(0)  # 9 Constants, at 97-105 or at 0-8
    finally:  # later Constants count on from above every earlier one
        _set_constant_count(max(before, _set_constant_count(0)))


def _ffcx_analyse(form) -> None:
    """What FFCx does to a form before it compiles it (the JIT cache missed)."""
    import inspect

    import ffcx.analysis

    params = inspect.signature(ffcx.analysis.analyze_ufl_objects).parameters
    if "scalar_type" in params:  # FFCx >= 0.8
        ffcx.analysis.analyze_ufl_objects([form], "float64")
        return
    from ffcx.parameters import get_parameters  # FFCx 0.5

    ffcx.analysis.analyze_ufl_objects([form], get_parameters())


def test_a_form_has_the_same_key_before_and_after_a_form_on_its_mesh_compiled():
    """FFCx 0.5 gives a mesh's coordinate element the variant 'equispaced' the first time
    it compiles a form on that mesh, and a form's signature (the JIT cache's key) includes
    that element: a model built after any compilation on its mesh got other keys than the
    same model built before, so a diagnosis on a warm cache that compiled one new form
    compiled the following ones again (2 forms of 20-60 s in each of several runs in a
    row). The same model on the same mesh must have one signature either way."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    g = geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF)
    first = ForwardModel(g, maxwell=1)
    before = first.residual_ufl.signature()
    _ffcx_analyse(ForwardModel(g).residual_ufl)  # as on a cache miss
    assert ForwardModel(g, maxwell=1).residual_ufl.signature() == before


def test_a_history_update_has_the_same_key_whatever_was_built_before(monkeypatch):
    """FFCx 0.9 signs a compiled expression (the history update of a viscoelastic model)
    with the global counts of its UFL Labels: the same update got another JIT cache key
    after other models had made variables, and was compiled again. The key (FFCx's own
    ``compute_signature``) must not depend on what was built before."""
    import ffcx.naming

    from brain_fe import geometry
    from brain_fe.history import HistoryState
    from brain_fe.model import ForwardModel

    seen = []
    original = HistoryState.compile_update

    def recording(self, update_ufl):
        seen.append((update_ufl, self.points))
        original(self, update_ufl)

    monkeypatch.setattr(HistoryState, "compile_update", recording)

    def key() -> str:
        g = geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF)
        ForwardModel(g, maxwell=1)
        return ffcx.naming.compute_signature([seen[-1]], "")

    first = key()
    ForwardModel(geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF), n_terms=2)
    assert key() == first


def test_the_kernels_instruction_set_follows_the_cpu_unless_stated():
    """-mavx2 joins the JIT flags (and with them FFCx's module name) where /proc/cpuinfo
    lists AVX2 on x86-64; BRAINMECH_JIT_ARCH replaces the choice (empty: no flag)."""
    import os
    import platform
    import subprocess
    import sys

    from brain_fe import _compat

    code = ("from brain_fe import _compat; "
            "print(' '.join(_compat._jit()['cffi_extra_compile_args']))")
    env = {k: v for k, v in os.environ.items() if k != "BRAINMECH_JIT_ARCH"}
    flags = {}
    for stated in (None, "", "-march=x86-64-v3 -mtune=native"):
        e = env if stated is None else dict(env, BRAINMECH_JIT_ARCH=stated)
        flags[stated] = subprocess.run([sys.executable, "-c", code], env=e, check=True,
                                       capture_output=True, text=True).stdout.split()
    avx2 = platform.machine() == "x86_64" and "avx2" in _compat._cpu_flags()
    assert flags[None] == ["-O3", "-g0", "-ffast-math"] + (["-mavx2"] if avx2 else [])
    assert flags[""] == ["-O3", "-g0", "-ffast-math"]
    assert flags["-march=x86-64-v3 -mtune=native"][-2:] == ["-march=x86-64-v3",
                                                            "-mtune=native"]
