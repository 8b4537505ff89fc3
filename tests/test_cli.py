"""`brainmech` command line: columns, units, atomic output and one-line errors."""

import math

import pandas as pd
import pytest
from references import homogeneous_uniaxial

from brainmech.main import main


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith("brainmech ")


def test_simulate_compression_tension_csv(tmp_path):
    """Slip ends, homogeneous: the CSV's nominal stress equals the semi-analytic value
    (0.1 %) and axial force = stress * pi R^2 (1e-9)."""
    out = tmp_path / "ct.csv"
    rc = main(["simulate", "--test", "compression_tension", "--amplitude", "0.1", "--mu", "1",
               "--alpha", "-20", "--kappa", "100", "--ends", "slip", "--refinement", "1",
               "--radius-mm", "3", "--height-mm", "4", "--out", str(out)])
    assert rc == 0
    df = pd.read_csv(out)
    assert list(df.columns) == ["time_s", "cycle", "branch", "stretch", "nominal_stress_kPa",
                                "axial_force_mN"]
    assert set(df.branch) == {"loading", "unloading"}
    i = df.stretch.idxmin()
    assert df.stretch[i] == pytest.approx(0.9)
    assert df.nominal_stress_kPa[i] == pytest.approx(homogeneous_uniaxial(0.9), rel=1e-3)
    assert (df.axial_force_mN / df.nominal_stress_kPa).dropna().iloc[1:].to_numpy() == \
        pytest.approx(math.pi * 9, rel=1e-9)


def test_simulate_torsion_columns_and_shear_stress(tmp_path):
    out = tmp_path / "t.csv"
    assert main(["simulate", "--test", "torsion", "--amplitude", "0.1", "--refinement", "1",
                 "--out", str(out)]) == 0
    df = pd.read_csv(out)
    assert list(df.columns) == ["time_s", "cycle", "branch", "shear", "torque_mNmm",
                                "shear_stress_kPa", "axial_force_mN"]
    # shear stress = 2 T / (pi R^3), R = 4 mm
    assert df.shear_stress_kPa.to_numpy() == pytest.approx(
        2 * df.torque_mNmm.to_numpy() / (math.pi * 64), rel=1e-9, abs=1e-15)
    assert df.shear.max() == pytest.approx(0.1)
    # time stamps: rate 0.01 /s -> 0 -> 0.1 -> 0 takes 20 s
    assert df.time_s.iloc[-1] == pytest.approx(20.0)


@pytest.mark.parametrize("args, fragment", [
    (["--nu0", "0.5"], "nu0 must lie in [0, 0.5)"),
    (["--alpha", "0"], "alpha must be non-zero"),
    (["--mu", "1,2", "--alpha", "-20"], "as many mu values as alpha"),
    (["--test", "torsion", "--ends", "slip"], "torsion needs glued ends"),
    (["--amplitude", "1.5"], "amplitude must lie in (0, 1)"),
])
def test_bad_input_is_one_line_no_file(tmp_path, capsys, args, fragment):
    out = tmp_path / "x.csv"
    rc = main(["simulate", "--refinement", "1", "--out", str(out), *args])
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1 and fragment in err
    assert "Traceback" not in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_unparsable_argument_exits_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--mu", "abc"])
    assert e.value.code == 2
    assert "expected comma-separated numbers" in capsys.readouterr().err


def test_other_ranks_say_their_own_warnings_only():
    """Rank 0 logs everything; another rank only the warnings and errors of work it does
    on its own (a specimen of a batch, an item of shared work: ``rank_local``), marked
    with its rank. Before, every record of rank 1 was dropped, so the failed candidate
    fits and the specimens of half a batch under ``mpirun -n 2`` went unsaid."""
    import logging

    from brain_fe.logs import RankFilter, rank_local

    def rec(level, msg="fit of %s failed"):
        return logging.LogRecord("diagnosis", level, __file__, 1, msg, ("mullins",), None)

    zero, one = RankFilter(0), RankFilter(1)
    assert zero.filter(rec(logging.INFO)) and zero.filter(rec(logging.WARNING))
    assert not one.filter(rec(logging.WARNING))  # all ranks do the same: rank 0 says it
    with rank_local():
        assert not one.filter(rec(logging.INFO))
        r = rec(logging.WARNING)
        assert one.filter(r) and r.getMessage() == "[rank 1] fit of mullins failed"
        assert one.filter(rec(logging.ERROR))
    assert not one.filter(rec(logging.ERROR))


def test_an_internal_error_on_one_rank_ends_the_whole_mpirun(tmp_path):
    """Under ``mpirun -n 2`` an unexpected exception on one rank (here raised by rank 1
    while rank 0 waits for it in a collective call, as a gather of results does) prints
    its traceback and ends every rank with a non-zero exit, instead of leaving rank 0
    waiting and rank 1 spinning in PETSc's finalisation for ever (an open benchmark run
    lost a rank that way and could never have finished)."""
    import subprocess
    import sys

    from launch import child_env

    script = tmp_path / "fails_on_rank_1.py"
    script.write_text(
        "import sys\n"
        "from mpi4py import MPI\n"
        "import brainmech.commands.benchmark_diagnosis as bd\n"
        "def run(args):\n"
        "    if MPI.COMM_WORLD.rank == 1:\n"
        "        raise RuntimeError('an internal error on rank 1')\n"
        "    MPI.COMM_WORLD.Barrier()\n"
        "    return 0\n"
        "bd.run = run\n"
        "from brainmech.main import main\n"
        "sys.exit(main(['benchmark-diagnosis', '--cases', '1', '--out', 'x']))\n")
    r = subprocess.run(["mpirun", "-n", "2", sys.executable, str(script)], env=child_env(),
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode != 0
    assert "RuntimeError: an internal error on rank 1" in r.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("content, expected", [
    # the message after the column is Python's own (3.11 and 3.13 word it differently)
    ('{"seed": 9,\n "cases": [1, 2,]}', r"bad\.json: line 2 column 1[67]: \w"),
    (None, r"No such file or directory: '[^']*bad\.json'"),
    ('{"seed": 9}', r"bad\.json: no field 'cases'"),
])
def test_a_benchmark_script_ends_on_bad_input_with_one_line(tmp_path, content, expected):
    """A benchmark script (here benchmarks/mimicked_outside.py --rescore) given a malformed
    JSON file, a missing one or one without a field it reads: one line on stderr naming the
    file (and the line and column), exit status 1, no traceback, no output file."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    from launch import child_env

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "mimicked_outside.py"
    bad = tmp_path / "bad.json"
    if content is not None:
        bad.write_text(content)
    out = tmp_path / "out.json"
    r = subprocess.run([sys.executable, str(script), "--rescore", str(bad), "--out", str(out)],
                       env=child_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("mimicked_outside.py: error: "), r.stderr
    assert re.search(expected, lines[-1]) and str(bad) in lines[-1], lines[-1]
    assert "Traceback" not in r.stderr
    assert not out.exists()
