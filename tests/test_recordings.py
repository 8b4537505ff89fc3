"""Reading and validating specimens and recordings tables (recordings.tables).

Fixtures are written in tmp_path from pandas (rows in file order: data row i, counted from
0, is on CSV line i + 2) or as literal text where the exact layout matters.  Every error
test compares the whole one-line message.
"""

import logging
import math
import os

import numpy as np
import pandas as pd
import pytest

from brain_fe import sampling
from brain_fe.protocols import compression_tension, torsion
from brain_fe.vocabulary import test_key as key_for_test
from recordings.cells import RecordingsError
from recordings.schema import RECORDING_COLUMNS
from recordings.tables import read_recordings, read_specimens, series
from recordings.tables import write_table as write_table_atomic


def _specimens() -> pd.DataFrame:
    return pd.DataFrame({"specimen": ["S1", "S2", "S3"],
                         "region": ["cortex", "cortex", "basal ganglia"],
                         "brain": [1, 1, 2],
                         "radius_mm": [4.0, 4.1, 3.9],
                         "height_mm": [5.0, 4.8, 5.2],
                         "notes": ["first", "small tear, glued twice", "ok"]})


def _recordings() -> pd.DataFrame:
    """Rows 0-40: S1 compression_tension 0.15; 41-61: S1 torsion 0.30; 62-82: S2 torsion 0.15."""
    rows = []
    for sid, protocol in (("S1", compression_tension(0.15)), ("S1", torsion(0.30)),
                          ("S2", torsion(0.15))):
        amp = round(protocol.amplitude, 12)
        for st in protocol.steps():
            row = dict(specimen=sid, test=protocol.test, amplitude=amp, cycle=st.cycle,
                       branch=st.branch, time_s=st.time_s)
            if protocol.test == "torsion":
                row.update(shear=st.value, torque_mNmm=100.0 * st.value,
                           axial_force_mN=-20.0 * st.value**2)
            else:
                row.update(stretch=st.value, nominal_stress_kPa=3.0 * (st.value - 1.0))
            rows.append(row)
    return pd.DataFrame(rows)


def _csv(tmp_path, df, name) -> str:
    path = tmp_path / name
    df.to_csv(path, index=False)
    return str(path)


def _fail(fn, *args, **kw) -> str:
    with pytest.raises(RecordingsError) as info:
        fn(*args, **kw)
    msg = str(info.value)
    assert "\n" not in msg and "Traceback" not in msg
    return msg


# ------------------------------------------------------------------------------ valid input
def test_valid_csv_pair_round_trips(tmp_path):
    spec_path = _csv(tmp_path, _specimens(), "specimens.csv")
    rec_path = _csv(tmp_path, _recordings(), "recordings.csv")
    spec = read_specimens(spec_path)
    assert list(spec.columns) == ["specimen", "region", "brain", "radius_mm", "height_mm",
                                  "notes"]
    assert spec["specimen"].tolist() == ["S1", "S2", "S3"]
    assert spec["brain"].tolist() == ["1", "1", "2"]  # ids become text
    assert spec["radius_mm"].dtype == np.float64 and spec["radius_mm"].tolist() == [4.0, 4.1, 3.9]
    assert spec["notes"].iloc[1] == "small tear, glued twice"

    rec = read_recordings(rec_path, spec)
    assert tuple(rec.columns) == RECORDING_COLUMNS
    assert len(rec) == 41 + 21 + 21
    assert rec["cycle"].dtype == np.int64
    for c in ("amplitude", "time_s", "stretch", "shear", "nominal_stress_kPa", "torque_mNmm",
              "axial_force_mN"):
        assert rec[c].dtype == np.float64, c
    ref = _recordings()
    assert rec["specimen"].tolist() == ref["specimen"].tolist()  # row order kept
    np.testing.assert_array_equal(rec["time_s"], ref["time_s"])
    np.testing.assert_array_equal(rec["stretch"], ref["stretch"])
    assert rec["stretch"].min() == pytest.approx(0.85) and rec["stretch"].max() == \
        pytest.approx(1.15)
    assert rec["torque_mNmm"].iloc[41 + 10] == pytest.approx(30.0)  # at gamma = 0.30
    assert math.isnan(rec["shear"].iloc[0]) and math.isnan(rec["torque_mNmm"].iloc[0])


def test_parquet_gives_the_same_tables(tmp_path):
    spec_csv = read_specimens(_csv(tmp_path, _specimens(), "specimens.csv"))
    rec_csv = read_recordings(_csv(tmp_path, _recordings(), "recordings.csv"), spec_csv)
    _specimens().to_parquet(tmp_path / "specimens.parquet", index=False)
    _recordings().to_parquet(tmp_path / "recordings.parquet", index=False)
    spec_pq = read_specimens(tmp_path / "specimens.parquet")
    rec_pq = read_recordings(tmp_path / "recordings.parquet", spec_pq)
    assert spec_pq["brain"].tolist() == ["1", "1", "2"]  # int64 ids become text
    pd.testing.assert_frame_equal(spec_pq, spec_csv)
    pd.testing.assert_frame_equal(rec_pq, rec_csv)


def test_optional_and_not_applicable_values(tmp_path):
    rec = _recordings()
    rec = rec[rec["test"] == "torsion"].drop(columns=["stretch", "nominal_stress_kPa"])
    rec["axial_force_mN"] = rec["axial_force_mN"].astype(object)
    rec.iloc[0, rec.columns.get_loc("axial_force_mN")] = " NaN "
    rec.iloc[1, rec.columns.get_loc("axial_force_mN")] = ""
    rec["rig"] = "R2"
    out = read_recordings(_csv(tmp_path, rec, "torsion.csv"), require_specimens=False)
    assert tuple(out.columns) == RECORDING_COLUMNS + ("rig",)
    assert out["stretch"].isna().all() and out["nominal_stress_kPa"].isna().all()
    assert out["axial_force_mN"].isna().tolist()[:3] == [True, True, False]
    assert out["axial_force_mN"].iloc[2] == pytest.approx(-20.0 * 0.06**2)
    assert out["rig"].tolist() == ["R2"] * 42


def test_hand_written_csv_with_blanks_and_multiline_notes():
    path = os.path.join(os.path.dirname(__file__), "data", "specimens_multiline.csv")
    spec = read_specimens(path)
    assert spec["specimen"].tolist() == ["C1", "C2", "B7"]
    assert spec["notes"].iloc[0] == "two lines\nof notes"
    assert spec["radius_mm"].tolist() == [4.0, 4.0, 3.95]
    assert spec["brain"].tolist() == ["07", "07", "12"]  # text ids are kept as written


def test_series_keys_follow_testspec_names(tmp_path):
    spec = read_specimens(_csv(tmp_path, _specimens(), "specimens.csv"))
    rec = read_recordings(_csv(tmp_path, _recordings(), "recordings.csv"), spec)
    curves = series(rec)
    assert list(curves) == [("S1", "compression_tension"), ("S1", "torsion_0.30"),
                            ("S2", "torsion_0.15")]
    assert [len(v) for v in curves.values()] == [41, 21, 21]
    assert curves[("S1", "torsion_0.30")].index[0] == 41  # original row positions
    assert curves[("S2", "torsion_0.15")]["shear"].max() == pytest.approx(0.15)
    for test, a in (("compression_tension", 0.15), ("compression_tension", 0.1),
                    ("torsion", 0.15), ("torsion", 0.3)):
        assert key_for_test(test, a) == sampling.TestSpec(test, a).name
    assert key_for_test("compression_tension", 0.1) == "compression_tension_0.10"
    assert key_for_test("torsion", 0.3) == "torsion_0.30"


def test_write_table_atomic(tmp_path):
    rec = _recordings()
    for name in ("out.csv", "out.parquet"):
        write_table_atomic(rec, tmp_path / name)
        back = read_recordings(tmp_path / name, require_specimens=False)
        np.testing.assert_array_equal(back["time_s"], rec["time_s"])  # exact round trip
        np.testing.assert_array_equal(back["shear"].fillna(-1), rec["shear"].fillna(-1))
    assert sorted(os.listdir(tmp_path)) == ["out.csv", "out.parquet"]  # no temporary left
    with pytest.raises(RecordingsError, match=r"out\.xlsx: unsupported file type '\.xlsx'"):
        write_table_atomic(rec, tmp_path / "out.xlsx")
    with pytest.raises(RecordingsError, match="output directory does not exist"):
        write_table_atomic(rec, tmp_path / "nowhere" / "out.csv")
    assert sorted(os.listdir(tmp_path)) == ["out.csv", "out.parquet"]


# ------------------------------------------------------------------------------ file errors
def test_file_level_errors(tmp_path):
    p = str(tmp_path / "recordings.csv")
    assert _fail(read_recordings, p, require_specimens=False) == f"{p}: file not found"
    x = str(tmp_path / "recordings.xlsx")
    assert _fail(read_specimens, x) == (f"{x}: unsupported file type '.xlsx'; expected a .csv "
                                        "or .parquet file")
    open(p, "w").close()
    assert _fail(read_recordings, p, require_specimens=False) == f"{p}: file is empty"
    with open(p, "w") as fh:
        fh.write("specimen,test,amplitude,cycle,branch,time_s\n\n")
    assert _fail(read_recordings, p, require_specimens=False) == \
        f"{p} line 1: no data rows (only a header)"
    with open(p, "wb") as fh:
        fh.write(b"specimen,region\nS1,Gro\xdfhirn\n")
    assert _fail(read_specimens, p) == (f"{p} line 2: not UTF-8 text (byte 0xdf); save the "
                                        "file as UTF-8 CSV")
    q = str(tmp_path / "specimens.parquet")
    with open(q, "w") as fh:
        fh.write("specimen,region\n")
    msg = _fail(read_specimens, q)
    assert msg.startswith(f"{q}: cannot read as Parquet (")
    d = tmp_path / "dir.csv"
    d.mkdir()
    assert _fail(read_specimens, d) == f"{d}: is a directory, not a file"


def test_csv_structure_errors(tmp_path):
    p = str(tmp_path / "specimens.csv")
    with open(p, "w") as fh:
        fh.write("specimen,region,brain,radius_mm,height_mm\nS1,cortex,1,4,5\n"
                 "S2,cortex,1,4,5\nS3,cortex,2,3,95,5\n")
    assert _fail(read_specimens, p) == (f"{p} line 4: 6 fields but the header has 5 columns "
                                        "(a stray comma, or a decimal comma instead of a point?)")
    with open(p, "w") as fh:
        fh.write("specimen,region,brain,radius_mm,height_mm\nS1,cortex,1,4,5\nS2,cortex,1\n")
    assert _fail(read_specimens, p) == (f"{p} line 3, column radius_mm: missing field (the "
                                        "line has 3 fields, the header 5; truncated line?)")
    with open(p, "w") as fh:
        fh.write("specimen,region,brain,radius_mm,height_mm,region\nS1,cortex,1,4,5,x\n")
    assert _fail(read_specimens, p) == (f"{p} line 1, column region: the column appears "
                                        "twice (columns 2 and 6)")
    with open(p, "w") as fh:
        fh.write("specimen;region;brain;radius_mm;height_mm\nS1;cortex;1;4,0;5,0\n")
    assert _fail(read_specimens, p) == (f"{p} line 1: the columns must be separated by commas, "
                                        "not ';' (header 'specimen;region;brain;radius_mm;"
                                        "height_mm')")


def test_nothing_is_written_on_bad_input(tmp_path):
    spec = _specimens()
    spec.loc[1, "radius_mm"] = -4.0
    p = _csv(tmp_path, spec, "specimens.csv")
    before = sorted(os.listdir(tmp_path))
    _fail(read_specimens, p)
    assert sorted(os.listdir(tmp_path)) == before


# ------------------------------------------------------------------------------ specimens
@pytest.mark.parametrize("edit, expected", [
    (lambda d: d.drop(columns="height_mm"),
     "line 1, column height_mm: missing required column; the columns are: specimen, region, "
     "brain, radius_mm, notes"),
    (lambda d: d.assign(radius_mm=["4", "0", "3.9"]),
     "line 3, column radius_mm: expected a positive number, got 0"),
    (lambda d: d.assign(height_mm=["5", "4.8", "abc"]),
     "line 4, column height_mm: expected a positive number, got 'abc'"),
    (lambda d: d.assign(height_mm=["5", "inf", "5"]),
     "line 3, column height_mm: expected a finite number, got inf"),
    (lambda d: d.assign(radius_mm=["4", "4,1", "3.9"]),
     "line 3, column radius_mm: expected a positive number, got '4,1' (use a decimal point, "
     "not a comma)"),
    (lambda d: d.assign(region=["cortex", "", "x"]),
     "line 3, column region: missing value (required)"),
    (lambda d: d.assign(specimen=["S1", "S2", "S1"]),
     "line 4, column specimen: duplicate specimen id 'S1' (first on line 2)"),
    # two problems: the earlier line wins, whatever the column
    (lambda d: d.assign(radius_mm=["4", "4", "-1"], height_mm=["5", "x", "5"]),
     "line 3, column height_mm: expected a positive number, got 'x'"),
])
def test_specimens_errors(tmp_path, edit, expected):
    p = _csv(tmp_path, edit(_specimens()), "specimens.csv")
    assert _fail(read_specimens, p) == f"{p} {expected}"


def test_parquet_errors_name_the_row(tmp_path):
    spec = _specimens()
    spec.loc[2, "radius_mm"] = -3.9
    p = tmp_path / "specimens.parquet"
    spec.to_parquet(p, index=False)
    assert _fail(read_specimens, p) == f"{p} row 3, column radius_mm: expected a positive " \
        "number, got -3.9"
    spec = _specimens().drop(columns="region")
    spec.to_parquet(p, index=False)
    assert _fail(read_specimens, p).startswith(f"{p} schema, column region: missing required "
                                               "column")


# ------------------------------------------------------------------------------ recordings
def _set(df, row, column, value):
    df = df.astype({column: object}) if df[column].dtype != object else df.copy()
    df.iloc[row, df.columns.get_loc(column)] = value
    return df


# Row r of _recordings() is on CSV line r + 2.  S1 torsion 0.30 occupies rows 41..61.
@pytest.mark.parametrize("edit, expected", [
    (lambda d: d.drop(columns="branch"),
     "line 1, column branch: missing required column; the columns are: specimen, test, "
     "amplitude, cycle, time_s, stretch, nominal_stress_kPa, shear, torque_mNmm, "
     "axial_force_mN"),
    (lambda d: d.drop(columns="stretch"),
     "line 1, column stretch: missing required column for compression_tension rows (first "
     "on line 2); the columns are: specimen, test, amplitude, cycle, branch, time_s, "
     "nominal_stress_kPa, shear, torque_mNmm, axial_force_mN"),
    (lambda d: _set(d, 15, "stretch", "abc"),
     "line 17, column stretch: expected a positive number, got 'abc'"),
    (lambda d: _set(d, 15, "stretch", "-0.2"),
     "line 17, column stretch: expected a positive number, got -0.2"),
    (lambda d: _set(d, 50, "test", "tension"),
     "line 52, column test: unknown test 'tension'; expected compression_tension or torsion"),
    (lambda d: _set(d, 50, "branch", "Loading"),
     "line 52, column branch: unknown branch 'Loading'; expected loading or unloading"),
    (lambda d: _set(d, 45, "torque_mNmm", ""),
     "line 47, column torque_mNmm: missing value (required for torsion rows)"),
    (lambda d: _set(d, 5, "nominal_stress_kPa", None),
     "line 7, column nominal_stress_kPa: missing value (required for compression_tension "
     "rows)"),
    (lambda d: _set(d, 45, "axial_force_mN", "-inf"),
     "line 47, column axial_force_mN: expected a finite number, got -inf"),
    (lambda d: _set(d, 3, "time_s", "nan"),
     "line 5, column time_s: missing value (required)"),
    (lambda d: _set(d, 3, "amplitude", "0"),
     "line 5, column amplitude: expected a positive number, got 0"),
    (lambda d: d.assign(amplitude=np.where(d["test"] == "torsion", d["amplitude"], 15.0)),
     "line 2, column amplitude: a compression_tension amplitude must lie in (0, 1), got 15.0 "
     "(it is a fraction: 0.15 for 15 %)"),
    (lambda d: _set(d, 8, "cycle", "1.5"),
     "line 10, column cycle: expected a whole number >= 1, got 1.5"),
    (lambda d: _set(d, 8, "cycle", "0"),
     "line 10, column cycle: expected a whole number >= 1, got 0"),
    (lambda d: _set(d, 20, "time_s", 1.0),
     "line 22, column time_s: time goes backwards in series (S1, compression_tension, "
     "amplitude 0.15): 1.0 s after 28.5 s on line 21"),
    (lambda d: _set(d, 61, "amplitude", 0.3001),
     "line 63, column specimen: series (S1, torsion, amplitude 0.3001) has only 1 point; a "
     "curve needs at least 2 (check the specimen id and the amplitude)"),
    (lambda d: _set(d, 30, "stretch", 1.16),
     "line 32, column stretch: stretch 1.16 lies outside [0.85, 1.15] = 1 -/+ the amplitude "
     "of its series (S1, compression_tension, amplitude 0.15)"),
    (lambda d: _set(d, 50, "shear", -0.31),
     "line 52, column shear: |shear| = 0.31 exceeds the amplitude of its series (S1, "
     "torsion, amplitude 0.3)"),
    (lambda d: _set(_set(d, 41, "amplitude", 0.3000001), 42, "amplitude", 0.3000001),
     "line 45, column amplitude: amplitude 0.3 here and 0.3000001 on line 43 both give "
     "specimen 'S1' the test torsion_0.30; use one amplitude per curve"),
    (lambda d: _set(d, 70, "specimen", "S9"),
     "line 72, column specimen: specimen 'S9' is not in {spec}"),
    (lambda d: d.assign(specimen=d["specimen"].where(d.index < 62, "basal ganglia")),
     "line 64, column specimen: specimen 'basal ganglia' is not in {spec}; 'basal ganglia' "
     "is a region: region-averaged curves need require_specimens=False"),
])
def test_recordings_errors(tmp_path, edit, expected):
    spec_path = _csv(tmp_path, _specimens(), "specimens.csv")
    p = _csv(tmp_path, edit(_recordings()), "recordings.csv")
    msg = _fail(read_recordings, p, read_specimens(spec_path))
    assert msg == f"{p} " + expected.format(spec=spec_path)


def test_line_numbers_count_blank_lines_and_the_header(tmp_path):
    p = tmp_path / "recordings.csv"
    p.write_text("\n".join([
        "specimen,test,amplitude,cycle,branch,time_s,shear,torque_mNmm",  # line 1
        "R1,torsion,0.15,1,loading,0,0,0",                                 # line 2
        "",                                                                 # line 3
        "R1,torsion,0.15,1,loading,1,0.1,1.5",                              # line 4
        "  ,  ,  ,  ",                                                      # line 5 (skipped)
        "R1,torsion,0.15,1,unloading,2,0.05,0.7",                           # line 6
        "R1,torsion,0.15,1,unloading,3,zero,0",                             # line 7
    ]) + "\n")
    assert _fail(read_recordings, p, require_specimens=False) == \
        f"{p} line 7, column shear: expected a number, got 'zero'"


def test_amplitude_tolerance_is_relative_1e6(tmp_path):
    ok = _set(_recordings(), 30, "stretch", 1.15 * (1 + 1e-12) + 0.15 * 5e-7)
    ok = _set(ok, 50, "shear", -(0.30 + 0.30 * 5e-7))
    rec = read_recordings(_csv(tmp_path, ok, "ok.csv"), require_specimens=False)
    assert rec["stretch"].iloc[30] > 1.15
    bad = _set(_recordings(), 50, "shear", 0.30 + 0.30 * 2e-6)
    p = _csv(tmp_path, bad, "bad.csv")
    assert _fail(read_recordings, p, require_specimens=False).startswith(
        f"{p} line 52, column shear: |shear| = 0.300001 exceeds")


def test_specimen_requirement(tmp_path, caplog):
    spec = read_specimens(_csv(tmp_path, _specimens(), "specimens.csv"))
    region = _recordings().assign(specimen=lambda d: np.where(d.index < 62, "cortex", "S2"))
    p = _csv(tmp_path, region, "regions.csv")
    with caplog.at_level(logging.INFO, logger="recordings.tables"):
        rec = read_recordings(p, spec, require_specimens=False)
    assert rec["specimen"].unique().tolist() == ["cortex", "S2"]
    assert "1 ids not in" in caplog.text and "region names: cortex" in caplog.text
    assert list(series(rec))[:2] == [("cortex", "compression_tension"), ("cortex",
                                                                          "torsion_0.30")]
    with pytest.raises(TypeError, match="needs the specimens table"):
        read_recordings(p)


def test_series_far_below_amplitude_is_warned_not_rejected(tmp_path, caplog):
    rec = _recordings()
    rec.loc[rec["test"] == "torsion", "amplitude"] = 30.0  # a percentage by mistake
    with caplog.at_level(logging.WARNING, logger="recordings.tables"):
        out = read_recordings(_csv(tmp_path, rec, "r.csv"), require_specimens=False)
    assert ("S1", "torsion_30.00") in series(out)
    assert "(S1, torsion, amplitude 30) reaches only 0.3 of its amplitude" in caplog.text


def test_last_digit_perturbation_changes_only_the_measured_numbers(tmp_path, monkeypatch):
    """benchmarks/last_digits.py (is a diagnosis determined by the data?): every measured
    number moves by at most a few units in the last place, most move, and the protocol,
    the flags and the empty cells stay exactly as written."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "last_digits.py"
    monkeypatch.syspath_prepend(str(path.parent))  # its helpers (as when run as a script)
    spec = importlib.util.spec_from_file_location("last_digits", path)
    last_digits = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(last_digits)

    ref = _recordings()
    ref["in_contact"] = (np.arange(len(ref)) % 2).astype(float)  # a 0/1 flag column
    src = _csv(tmp_path, ref, "recordings.csv")
    changed = last_digits.perturb(Path(src), tmp_path / "ulp.csv", seed=3)
    specimens = read_specimens(_csv(tmp_path, _specimens(), "specimens.csv"))
    a = read_recordings(src, specimens)
    b = read_recordings(str(tmp_path / "ulp.csv"), specimens)
    for c in ("specimen", "test", "amplitude", "cycle", "branch", "in_contact"):
        assert a[c].tolist() == b[c].tolist(), c
    measured = ["time_s", "stretch", "shear", "nominal_stress_kPa", "torque_mNmm",
                "axial_force_mN"]
    x, y = a[measured].to_numpy(), b[measured].to_numpy()
    np.testing.assert_array_equal(np.isnan(x), np.isnan(y))
    nonzero = np.isfinite(x) & (x != 0)
    assert changed == int((x[nonzero] != y[nonzero]).sum()) > 0.5 * nonzero.sum()
    # a relative SD of 4e-16: no change beyond 10 SD (plus the rounding to a double)
    assert np.max(np.abs(y[nonzero] / x[nonzero] - 1)) < 10 * 4e-16 + 2.0**-52
    assert (y[x == 0] == 0).all()
