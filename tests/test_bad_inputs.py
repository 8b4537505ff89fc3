"""No input that is wrong, degenerate or implausible gets a confident answer (issue 18).

A table of malformed or degenerate inputs across every command.  Each case must end with a
non-zero exit code (2: the command line could not be parsed, 1: the input was refused),
exactly one line on stderr naming the file, row and column or the option (the expected
fragments below), no traceback, no output left behind (the output path does not exist and
the working folder holds only the inputs), within 60 s.

The valid baseline is one specimen of the project's own synthetic brain bank
(data/brain_bank); every recordings case mutates one thing of it.  Commands run in-process
(``brainmech.main.main``), so a case costs what the refusal costs.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from brainmech.main import main

BANK = Path(__file__).resolve().parents[1] / "data" / "brain_bank"
SID = "B1-BG"


def _valid() -> tuple[pd.DataFrame, pd.DataFrame]:
    spec = pd.read_csv(BANK / "specimens.csv")
    rec = pd.read_csv(BANK / "recordings.csv")
    return spec[spec.specimen == SID].reset_index(drop=True), \
        rec[rec.specimen == SID].reset_index(drop=True)


def _rec_rows(test: str, amp: float) -> pd.Series:
    _, rec = _valid()
    return (rec.test == test) & np.isclose(rec.amplitude, amp)


# ---------------------------------------------------------------- input builders
# Each builder writes the inputs into ``d`` and returns {name: path} for the argv template.

def files(rec_edit=None, spec_edit=None, rec_text=None, spec_text=None,
          rec_name="rec.csv", spec_name="spec.csv"):
    def build(d: Path) -> dict:
        spec, rec = _valid()
        if spec_edit is not None:
            spec = spec_edit(spec.copy())
        if rec_edit is not None:
            rec = rec_edit(rec.copy())
        sp, rp = d / spec_name, d / rec_name
        if spec_text is not None:
            sp.write_bytes(spec_text if isinstance(spec_text, bytes) else spec_text.encode())
        elif spec is not None:
            spec.to_csv(sp, index=False)
        if rec_text is not None:
            rp.write_bytes(rec_text if isinstance(rec_text, bytes) else rec_text.encode())
        elif rec is not None:
            rec.to_csv(rp, index=False)  # an edit returning None leaves the file out
        return {"rec": str(rp), "spec": str(sp)}
    return build


def cell(row: int, column: str, value):
    def edit(df):
        df[column] = df[column].astype(object)
        df.loc[row, column] = value
        return df
    return edit


def where(mask_of, column: str, value):
    """Set ``column`` of the rows ``mask_of(df)`` to ``value``."""
    def edit(df):
        df.loc[mask_of(df), column] = value
        return df
    return edit


def ct(df):
    return df.test == "compression_tension"


def t15(df):
    return (df.test == "torsion") & np.isclose(df.amplitude, 0.15)


def valid(d: Path) -> dict:
    return files()(d)


def nothing(d: Path) -> dict:
    return {}


def a_file(d: Path) -> dict:
    (d / "plain").write_text("x")
    return {"file": str(d / "plain")}


def empty_dir(d: Path) -> dict:
    (d / "emptydir").mkdir()
    return {"dir": str(d / "emptydir")}


# The recordings cases shared by identify and diagnose: (id, builder, fragments)
REC_CASES = [
    ("rec-missing", files(rec_edit=lambda d: None), ["rec.csv: file not found"]),
    ("rec-empty", files(rec_text=""), ["rec.csv: file is empty"]),
    ("rec-header-only", files(rec_text="specimen,test,amplitude,cycle,branch,time_s\n"),
     ["no data rows"]),
    ("rec-semicolons", files(rec_text="specimen;test;amplitude\nB1-BG;torsion;0.3\n"),
     ["line 1", "separated by commas"]),
    ("rec-not-utf8", files(rec_text=b"specimen,test\n\xff\xfe,1\n"), ["not UTF-8"]),
    ("rec-xlsx", files(rec_name="rec.xlsx"), ["unsupported file type '.xlsx'"]),
    ("rec-missing-column", files(rec_edit=lambda d: d.drop(columns=["time_s"])),
     ["column time_s", "missing required column"]),
    ("rec-duplicate-column", files(rec_text="specimen,test,test\nB1-BG,torsion,torsion\n"),
     ["column test", "appears twice"]),
    ("rec-stretch-text", files(rec_edit=cell(3, "stretch", "abc")),
     ["line 5, column stretch", "expected a positive number"]),
    ("rec-stretch-nan", files(rec_edit=cell(3, "stretch", "nan")),
     ["line 5, column stretch", "missing value"]),
    ("rec-stretch-inf", files(rec_edit=cell(3, "stretch", "inf")),
     ["line 5, column stretch", "finite"]),
    ("rec-stretch-negative", files(rec_edit=cell(3, "stretch", -0.5)),
     ["line 5, column stretch", "positive"]),
    ("rec-stress-text", files(rec_edit=cell(4, "nominal_stress_kPa", "1,5")),
     ["line 6, column nominal_stress_kPa", "decimal point"]),
    ("rec-stress-inf", files(rec_edit=cell(4, "nominal_stress_kPa", "-inf")),
     ["line 6, column nominal_stress_kPa", "finite"]),
    ("rec-torque-missing", files(rec_edit=lambda d: cell(int(np.flatnonzero(t15(d))[2]),
                                                         "torque_mNmm", "")(d)),
     ["column torque_mNmm", "missing value"]),
    ("rec-time-text", files(rec_edit=cell(2, "time_s", "soon")),
     ["line 4, column time_s", "expected a number"]),
    ("rec-time-backwards", files(rec_edit=cell(5, "time_s", -1.0)),
     ["column time_s", "time goes backwards"]),
    ("rec-cycle-zero", files(rec_edit=cell(1, "cycle", 0)),
     ["line 3, column cycle", "whole number >= 1"]),
    ("rec-cycle-fraction", files(rec_edit=cell(1, "cycle", 1.5)),
     ["line 3, column cycle", "whole number >= 1"]),
    ("rec-branch-unknown", files(rec_edit=cell(2, "branch", "Loading")),
     ["line 4, column branch", "unknown branch 'Loading'"]),
    ("rec-test-unknown", files(rec_edit=cell(0, "test", "tension")),
     ["line 2, column test", "unknown test 'tension'"]),
    ("rec-amplitude-zero", files(rec_edit=where(ct, "amplitude", 0.0)),
     ["column amplitude", "positive"]),
    ("rec-amplitude-percent", files(rec_edit=where(ct, "amplitude", 15.0)),
     ["column amplitude", "(0, 1)"]),
    ("rec-stretch-beyond-amplitude", files(rec_edit=cell(3, "stretch", 0.5)),
     ["line 5, column stretch", "lies outside"]),
    ("rec-unknown-specimen", files(rec_edit=cell(0, "specimen", "B9-XX")),
     ["line 2, column specimen", "'B9-XX' is not in"]),
    ("rec-one-point", files(rec_edit=lambda d: pd.concat([d[~t15(d)], d[t15(d)].iloc[:1]])),
     ["has only 1 point"]),
    ("rec-two-points", files(rec_edit=lambda d: pd.concat([d[~t15(d)], d[t15(d)].iloc[:2]])),
     ["column specimen", "has only 2 points; at least 5"]),
    ("rec-three-points", files(rec_edit=lambda d: pd.concat([d[~t15(d)], d[t15(d)].iloc[:3]])),
     ["column specimen", "has only 3 points; at least 5"]),
    ("rec-no-motion", files(rec_edit=where(ct, "stretch", 1.0)),
     ["column stretch", "never changes its stretch", "nothing was tested"]),
    ("rec-no-twist", files(rec_edit=where(t15, "shear", 0.0)),
     ["column shear", "never changes its shear"]),
    ("rec-zero-stress", files(rec_edit=where(ct, "nominal_stress_kPa", 0.0)),
     ["column nominal_stress_kPa", "is 0 throughout", "no load was recorded"]),
    ("rec-constant-torque", files(rec_edit=where(t15, "torque_mNmm", 1.5)),
     ["column torque_mNmm", "is 1.5 throughout"]),
    ("rec-frozen-clock", files(rec_edit=where(t15, "time_s", 3.0)),
     ["column time_s", "time does not advance"]),
    ("rec-two-points-per-ramp", files(rec_edit=lambda d: d.drop(index=[
        i for i in np.flatnonzero(ct(d)) if i % 5 != 0])),
     ["column stretch", "points per ramp"]),
    ("spec-missing", files(spec_text=None, spec_edit=lambda s: None), ["spec.csv"]),
    ("spec-radius-4000", files(spec_edit=lambda s: s.assign(radius_mm=4000.0)),
     ["line 2, column radius_mm", "4000 mm is not a plausible specimen radius"]),
    ("spec-height-micron", files(spec_edit=lambda s: s.assign(height_mm=0.004)),
     ["line 2, column height_mm", "not a plausible specimen height"]),
    ("spec-radius-zero", files(spec_edit=lambda s: s.assign(radius_mm=0.0)),
     ["line 2, column radius_mm", "positive"]),
    ("spec-radius-text", files(spec_edit=lambda s: s.assign(radius_mm="four")),
     ["line 2, column radius_mm", "expected a positive number"]),
    ("spec-duplicate", files(spec_edit=lambda s: pd.concat([s, s])),
     ["line 3, column specimen", "duplicate specimen id"]),
    ("spec-missing-column", files(spec_edit=lambda s: s.drop(columns=["region"])),
     ["column region", "missing required column"]),
    ("spec-ends-unknown", files(spec_edit=lambda s: s.assign(ends="sticky")),
     ["line 2, column ends", "unknown end condition 'sticky'"]),
]

IDENTIFY = ["identify", "--recordings", "{rec}", "--specimens", "{spec}", "--surrogates",
            "{models}", "--out", "{out}"]
DIAGNOSE = ["diagnose", "--recordings", "{rec}", "--specimens", "{spec}", "--out", "{out}"]

# (id, builder, argv template, exit code, fragments)
CASES: list[tuple] = []
for cid, build, frags in REC_CASES:
    CASES.append((f"identify/{cid}", build, IDENTIFY, 1, frags))
    CASES.append((f"diagnose/{cid}", build, DIAGNOSE, 1, frags))

SIM = ["simulate", "--refinement", "1", "--out", "{out}.csv"]
for opt, values in {
    "--mu": ["abc", "nan", "inf", ""], "--alpha": ["x", "nan"], "--amplitude": ["0", "-1", "nan"],
    "--kappa": ["0", "-5", "inf"], "--nu0": ["nan", "zero"], "--radius-mm": ["0", "nan", "-4"],
    "--height-mm": ["inf", "0"], "--refinement": ["0", "1.5", "two"], "--rate": ["0", "inf"],
    "--cycles": ["0", "-1"], "--hold": ["-1", "nan"], "--softening": ["nan"],
    "--softening-m": ["0"], "--maxwell-beta": ["nan"], "--maxwell-tau": ["a"],
    "--k-r": ["-1", "nan"], "--stretch-offset": ["inf"], "--force-offset": ["nan"],
    "--model": ["2d"], "--test": ["shear"], "--ends": ["velcro"], "--volumetric": ["cubic"],
}.items():
    for v in values:
        CASES.append((f"simulate/{opt}={v}", nothing, SIM + [opt, v], 2, [opt]))
for cid, extra, frags in [
    ("nu0-half", ["--nu0", "0.5"], ["nu0 must lie in [0, 0.5)"]),
    ("nu0-negative", ["--nu0", "-0.2"], ["nu0 must lie in [0, 0.5)"]),
    ("alpha-zero", ["--alpha", "0"], ["alpha must be non-zero"]),
    ("mu-alpha-count", ["--mu", "1,2", "--alpha", "-20"], ["as many mu values as alpha"]),
    ("mu-sum-negative", ["--mu", "-1"], ["shear modulus"]),
    ("amplitude-ct", ["--amplitude", "1.5"], ["amplitude must lie in (0, 1)"]),
    ("torsion-slip", ["--test", "torsion", "--ends", "slip"], ["torsion needs glued ends"]),
    ("springs-no-k", ["--ends", "springs"], ["--k-r"]),
    ("k-no-springs", ["--k-r", "5", "--k-theta", "5"], ["--ends springs"]),
    ("k-one-only", ["--ends", "springs", "--k-r", "5"], ["--k-theta"]),
    ("softening-1", ["--softening", "1.2"], ["softening d = 1/r must lie in [0, 1)"]),
    ("maxwell-mismatch", ["--maxwell-beta", "0.5", "--maxwell-tau", "1,2"], ["as many Maxwell"]),
    ("maxwell-negative", ["--maxwell-beta", "-0.5", "--maxwell-tau", "1"], ["beta >= 0"]),
    ("maxwell-tau-zero", ["--maxwell-beta", "0.5", "--maxwell-tau", "0"], ["tau_s > 0"]),
    ("stretch-offset-big", ["--stretch-offset", "0.3"], ["stretch_offset must lie in"]),
    ("height-rel-big", ["--height-rel", "0.6"], ["height_rel must lie in"]),
    ("springs-3d", ["--model", "3d", "--ends", "springs", "--k-r", "1", "--k-theta", "1"],
     ["implemented for the axisymmetric model"]),
]:
    CASES.append((f"simulate/{cid}", nothing, SIM + extra, 1, frags))
CASES += [
    ("simulate/out-bad-suffix", nothing, ["simulate", "--out", "{out}.txt"], 1,
     ["expected a file name ending in .csv"]),
    ("simulate/out-no-dir", nothing, ["simulate", "--out", "{out}/x/y.csv"], 1,
     ["output directory does not exist"]),
    ("simulate/out-is-dir", empty_dir, ["simulate", "--out", "{dir}"], 1, ["expected a file"]),
    ("simulate/out-under-file", a_file, ["simulate", "--out", "{file}/y.csv"], 1,
     ["y.csv"]),
    ("simulate/out-unwritable", nothing, ["simulate", "--out", "/proc/brainmech-x.csv"], 1,
     ["/proc/brainmech-x.csv", "cannot write"]),
    ("simulate/fields-no-dir", nothing, ["simulate", "--out", "{out}.csv", "--fields",
                                         "{out}/f/u.xdmf"], 1, ["output directory"]),
    ("simulate/fields-suffix", nothing, ["simulate", "--fields", "{out}.h5"], 1,
     ["ending in .xdmf"]),
]

SAMPLE = ["sample", "--n", "2", "--refinement", "1", "--out", "{out}"]
for opt, values in {"--n": ["0", "-3", "x"], "--seed": ["-1", "x"], "--mu-range": [
        "1", "5,1", "nan,5", "a,b"], "--alpha-range": ["-1", "x,y"], "--nu0": ["nan"],
        "--refinement": ["0", "x"], "--radius-mm": ["nan", "0"], "--height-mm": ["-1"],
        "--chunk-size": ["0"], "--design": ["grid"], "--model": ["2d"], "--ends": ["springs"]
        }.items():
    for v in values:
        CASES.append((f"sample/{opt}={v}", nothing, SAMPLE + [opt, v], 2, [opt]))
for cid, extra, frags in [
    ("alpha-range-zero", ["--alpha-range", "-1,1"], ["alpha range must not contain 0"]),
    ("mu-range-zero", ["--mu-range", "0,5"], ["mu range must be positive"]),
    ("nu0-half", ["--nu0", "0.5"], ["nu0 must lie in [0, 0.5)"]),
    ("tests-unknown", ["--tests", "shear"], ["unknown test 'shear'"]),
    ("tests-amplitude-text", ["--tests", "torsion:abc"], ["bad amplitude"]),
    ("tests-amplitude-big", ["--tests", "compression_tension:1.5"], ["bad amplitude"]),
    ("tests-repeated", ["--tests", "torsion,torsion:0.3"], ["repeat a name"]),
    ("tests-empty", ["--tests", ","], ["at least one test"]),
    ("slip-torsion", ["--ends", "slip"], ["torsion needs glued ends"]),
]:
    CASES.append((f"sample/{cid}", nothing, SAMPLE + extra, 1, frags))
CASES += [
    ("sample/out-is-file", a_file, ["sample", "--n", "2", "--out", "{file}"], 1,
     ["is not a directory"]),
    ("sample/out-unwritable", nothing, ["sample", "--n", "2", "--out", "/proc/brainmech-s"], 1,
     ["cannot write"]),
]

TRAIN = ["train", "--samples", "{store}", "--out", "{out}", "--profile", "tiny"]
CASES += [
    ("train/no-store", nothing, ["train", "--samples", "{out}-none", "--out", "{out}"], 1,
     ["not a sample store"]),
    ("train/not-a-store", empty_dir, ["train", "--samples", "{dir}", "--out", "{out}"], 1,
     ["not a sample store"]),
    ("train/trials-0", nothing, TRAIN + ["--trials", "0"], 2, ["--trials"]),
    ("train/executions-x", nothing, TRAIN + ["--executions", "x"], 2, ["--executions"]),
    ("train/seed-neg", nothing, TRAIN + ["--seed", "-2"], 2, ["--seed"]),
    ("train/profile", nothing, TRAIN + ["--profile", "huge"], 2, ["--profile"]),
    ("train/out-unwritable", nothing, ["train", "--samples", "{store}", "--out",
                                       "/proc/brainmech-m"], 1, ["cannot write"]),
    ("train/incomplete-store", nothing, ["train", "--samples", "{half_store}", "--out",
                                         "{out}"], 1, ["not finished"]),
    ("train/corrupt-manifest", nothing, ["train", "--samples", "{bad_store}", "--out",
                                         "{out}"], 1, ["is corrupted"]),
]

CASES += [
    ("identify/fit", valid, IDENTIFY + ["--fit", "shear"], 2, ["--fit"]),
    ("identify/refinement-0", valid, IDENTIFY + ["--refinement", "0"], 2, ["--refinement"]),
    ("identify/no-surrogates", valid, ["identify", "--recordings", "{rec}", "--specimens",
                                       "{spec}", "--surrogates", "{out}-none", "--out",
                                       "{out}"], 1, ["no surrogates"]),
    ("identify/out-unwritable", valid, ["identify", "--recordings", "{rec}", "--specimens",
                                        "{spec}", "--surrogates", "{models}", "--out",
                                        "/proc/brainmech-i"], 1, ["cannot write"]),
    ("diagnose/effects-misspelt", valid, DIAGNOSE + ["--effects", "viscoelastik"], 1,
     ["unknown candidate effect(s) viscoelastik"]),
    ("diagnose/effects-one-misspelt", valid, DIAGNOSE + ["--effects", "mullins,gluing"], 1,
     ["unknown candidate effect(s) gluing"]),
    ("diagnose/effects-empty", valid, DIAGNOSE + ["--effects", ","], 2, ["--effects"]),
    ("diagnose/refinement-0", valid, DIAGNOSE + ["--refinement", "0"], 2, ["--refinement"]),
    ("diagnose/nu0-nan", valid, DIAGNOSE + ["--nu0", "nan"], 2, ["--nu0"]),
    ("diagnose/unknown-specimen", valid, DIAGNOSE + ["--specimen", "B9"], 1,
     ["no recordings of specimen 'B9'"]),
    ("diagnose/no-specimens", valid, ["diagnose", "--recordings", "{rec}", "--out", "{out}"],
     1, ["give --recordings and --specimens"]),
    ("diagnose/budday-with-recordings", valid, ["diagnose", "--budday", "--recordings",
                                                "{rec}", "--out", "{out}"], 1,
     ["reads --budday data, not --recordings"]),
    ("diagnose/budday-missing-file", nothing, ["diagnose", "--budday", "{out}-none.csv",
                                               "--out", "{out}"], 1, ["file not found"]),
    ("diagnose/budday-bad-effect", nothing, ["diagnose", "--budday", "--effects", "fibres",
                                             "--out", "{out}"], 1, ["unknown candidate"]),
    ("diagnose/out-is-file", a_file, ["diagnose", "--recordings", "{file}", "--specimens",
                                      "{file}", "--out", "{file}"], 1, ["is not a directory"]),
    ("diagnose/out-unwritable", valid, ["diagnose", "--recordings", "{rec}", "--specimens",
                                        "{spec}", "--out", "/proc/brainmech-d"], 1,
     ["cannot write"]),
    ("make-brain-bank/brains-0", nothing, ["make-brain-bank", "--brains", "0", "--out",
                                           "{out}"], 2, ["--brains"]),
    ("make-brain-bank/elisa", nothing, ["make-brain-bank", "--brains", "2", "--elisa-brains",
                                        "3", "--out", "{out}"], 1, ["--elisa-brains"]),
    ("make-brain-bank/seed", nothing, ["make-brain-bank", "--seed", "x", "--out", "{out}"], 2,
     ["--seed"]),
    ("make-brain-bank/refinement", nothing, ["make-brain-bank", "--refinement", "0", "--out",
                                             "{out}"], 2, ["--refinement"]),
    ("make-brain-bank/out-unwritable", nothing, ["make-brain-bank", "--out",
                                                 "/proc/brainmech-b"], 1, ["cannot write"]),
    ("reproduce/profile", nothing, ["reproduce", "--profile", "fast", "--out", "{out}"], 2,
     ["--profile"]),
    ("reproduce/out-unwritable", nothing, ["reproduce", "--out", "/proc/brainmech-r"], 1,
     ["cannot write"]),
    ("benchmark-diagnosis/cases-0", nothing, ["benchmark-diagnosis", "--cases", "0", "--out",
                                              "{out}"], 2, ["--cases"]),
    ("benchmark-diagnosis/no-cases", nothing, ["benchmark-diagnosis", "--out", "{out}"], 1,
     ["give --cases"]),
    ("benchmark-diagnosis/effects", nothing, ["benchmark-diagnosis", "--cases", "2",
                                              "--effects", "fibres", "--out", "{out}"], 1,
     ["unknown candidate effect(s) fibres"]),
    ("benchmark-diagnosis/increment", nothing, ["benchmark-diagnosis", "--cases", "2",
                                                "--increment", "0", "--out", "{out}"], 2,
     ["--increment"]),
    ("benchmark-diagnosis/cycles", nothing, ["benchmark-diagnosis", "--cases", "2",
                                             "--cycles", "0", "--out", "{out}"], 2,
     ["--cycles"]),
    ("benchmark-diagnosis/rescore-empty", empty_dir, ["benchmark-diagnosis", "--rescore",
                                                      "--out", "{dir}"], 1,
     ["not a benchmark directory"]),
    ("benchmark-diagnosis/refinement", nothing, ["benchmark-diagnosis", "--cases", "2",
                                                 "--refinement", "0", "--out", "{out}"], 2,
     ["--refinement"]),
    ("unknown-command", nothing, ["frobnicate"], 2, ["invalid choice"]),
]


def test_the_table_is_large_enough():
    """At least 150 distinct inputs across every command."""
    assert len(CASES) >= 150
    assert len({c[0] for c in CASES}) == len(CASES)
    commands = {c[2][0] for c in CASES}
    assert commands >= {"simulate", "sample", "train", "identify", "diagnose",
                        "make-brain-bank", "reproduce", "benchmark-diagnosis"}


@pytest.fixture(scope="module")
def stores(tiny_store, tmp_path_factory):
    """A finished store (the session's tiny store), a half-finished and a corrupted copy."""
    import json
    import shutil

    from brain_fe import store

    d = tmp_path_factory.mktemp("stores")
    half = d / "half"
    shutil.copytree(tiny_store, half)
    rows = store.read_chunks(half)
    for p in store.chunk_files(half):
        p.unlink()
    keep = rows[rows["sample"] < rows["sample"].max() // 2].to_dict("records")
    store.write_chunk(half, keep, run_id="half", rank=0, seq=0)
    bad = d / "bad"
    shutil.copytree(tiny_store, bad)
    man = json.loads((bad / "manifest.json").read_text())
    man["parameters"]["mu_kPa"][0] *= 2
    (bad / "manifest.json").write_text(json.dumps(man))
    return {"store": str(tiny_store), "half_store": str(half), "bad_store": str(bad)}


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_refused_cleanly(case, tmp_path, capsys, tiny_models, stores):
    cid, build, template, code, fragments = case
    work = tmp_path / "work"
    work.mkdir()
    names = build(work)
    inputs = set(os.listdir(work))
    out = str(work / "out")
    argv = [a.format(out=out, models=str(tiny_models[0]), **stores, **names) for a in template]
    t0 = time.perf_counter()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    elapsed = time.perf_counter() - t0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == code, (cid, rc, err)
    assert len(lines) == 1, (cid, err)
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (cid, f, lines[0])
    assert set(os.listdir(work)) == inputs, (cid, set(os.listdir(work)) - inputs)
    assert elapsed < 60.0, (cid, elapsed)
