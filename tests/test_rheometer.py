"""`brainmech import`: rheometer exports -> specimens, recordings, noise.json, import.md.

The synthetic files are written by the tests themselves in the instruments' formats (a
tab-separated raw trace, TRIOS-like .xlsx workbooks); the real exports under
shared/data/rheometer are read in place when present.
"""

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from brain_fe.vocabulary import torque_mNmm
from recordings import rheometer_segments as seg
from recordings.rheometer import import_exports, import_file
from recordings.rheometer_segments import RheometerError
from recordings.tables import read_recordings, read_specimens

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rheometer"
AREA = math.pi * 4.0**2  # mm^2, 8 mm plates
H, START, LOW, SPEED = 5.0, 5.5, 2.5, 2.0  # mm, mm, mm, mm/s
F0, SLOPE, SD = 0.01, 0.4, 0.002  # N, N/mm, N
HEADER = "Time (s)\tEncoder (rad)\tTorque (Nm)\tMarker\tNormal force (N)\tGap (um)"


def write_trace(path: Path, seed: int = 1, dt: float = 0.004, refresh: int = 5) -> None:
    """A double compression as a TRIOS text export: 1 s at rest 0.5 mm above the specimen,
    approach, contact at H, two cycles to 50 % with a 0.3 s hold between them, rest; linear
    force after contact plus white noise of SD ``SD``; the gap reading refreshed every
    ``refresh`` samples (sample-and-hold, as the instrument's)."""
    knots, t = [(0.0, START), (1.0, START)], 1.0
    for _ in range(2):
        t += (START - LOW) / SPEED
        knots.append((t, LOW))
        t += (START - LOW) / SPEED
        knots.append((t, START))
        t += 0.3
        knots.append((t, START))
    tt = np.arange(0.0, t, dt)
    gap = np.interp(tt, *zip(*knots, strict=True))
    rng = np.random.default_rng(seed)
    force = F0 + SLOPE * np.clip(H - gap, 0.0, None) + rng.normal(0.0, SD, tt.size)
    reading = gap[(np.arange(tt.size) // refresh) * refresh]
    lines = [HEADER] + [f"{a:.6f}\t0\t-1.4E-05\t0\t{f:.8f}\t{1000 * g:.5f}\t"
                        for a, f, g in zip(tt, force, reading, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_trace_contact_noise_cycles_units(tmp_path):
    f = tmp_path / "mat" / "2s" / "double-compression-1.txt"
    f.parent.mkdir(parents=True)
    write_trace(f)
    spec, rows, noise, info = import_file(f, "mat/double-compression-1")
    # contact gap within its reported uncertainty, which is meaningful (< 0.05 mm)
    assert abs(spec["height_mm"] - H) <= spec["contact_uncertainty_mm"]
    assert 0 < spec["contact_uncertainty_mm"] < 0.05
    assert spec["preload_mN"] == pytest.approx(1000 * F0, abs=1.0)
    # noise: the raw SD at rest and its white-noise conversion to a resampled point (bins of
    # m samples) within 20 %; the direct measurement of the bin-mean scatter written to
    # noise.json (~8 % SD from 4 ramps of 20 points) within 35 %
    sd_kpa = 1000 * SD / AREA
    n = noise["stress"]
    assert n["rest"] == pytest.approx(sd_kpa, rel=0.2)
    assert n["white"] == pytest.approx(sd_kpa / math.sqrt(n["m"]), rel=0.2)
    assert n["sd"] == pytest.approx(sd_kpa / math.sqrt(n["m"]), rel=0.35)
    # segmentation: two cycles, loading then unloading, 20 points per ramp, hold dropped
    runs = rows.groupby((rows[["cycle", "branch"]] != rows[["cycle", "branch"]].shift())
                        .any(axis=1).cumsum())
    assert [(int(g.cycle.iloc[0]), g.branch.iloc[0], len(g)) for _, g in runs] == [
        (1, "loading", 20), (1, "unloading", 20), (2, "loading", 20), (2, "unloading", 20)]
    # amplitude: 1 - min stretch of the bin averages (last bin ~ half a bin above 0.5),
    # rounded up to 0.01
    lo = rows.stretch.min()
    assert 0.49 < lo < 0.52
    assert rows.amplitude.unique().tolist() == [math.ceil(100 * (1 - lo)) / 100]
    assert "in contact at rest" not in info
    # units: um -> mm, N -> mN, stress = F / (pi R^2), compression negative
    assert rows.stretch.to_numpy() == pytest.approx(rows.gap_mm.to_numpy() / spec["height_mm"],
                                                    rel=1e-12)
    assert rows.nominal_stress_kPa.to_numpy() == pytest.approx(
        rows.axial_force_mN.to_numpy() / AREA, rel=1e-12)
    inside = rows[rows.stretch < 0.95]
    expect = -1000 * (F0 + SLOPE * (H - inside.gap_mm))
    assert np.abs(inside.axial_force_mN - expect).max() < 5 * 1000 * SD / math.sqrt(n["m"])
    assert (inside.nominal_stress_kPa < 0).all()
    assert rows.time_s.iloc[0] >= 0 and rows.time_s.is_monotonic_increasing


def _write_xlsx(path: Path, sheets: dict) -> None:
    from openpyxl import Workbook

    wb = Workbook()
    wb.remove(wb.active)
    for name, rows in sheets.items():
        ws = wb.create_sheet(name)
        for r in rows:
            ws.append(list(r))
    wb.save(path)


DETAILS = [("Filename", "x"), ("Geometry name", "8.0mm parallel plate")]


def _axial_sheet(gap_um, force_n, bad: tuple[int, str] | None = None):
    rows = [("Axial - 1",), ("Step time", "Temperature", "Normal stress", "Axial force", "Gap"),
            ("s", "°C", "Pa", "N", "µm")]
    for i, (g, fn) in enumerate(zip(gap_um, force_n, strict=True)):
        rows.append((0.1 * (i + 1), 25, 2 * fn / (math.pi * 0.004**2), fn, g))
    if bad is not None:  # replace the Gap of one data row (0-based) by text
        i, text = bad
        rows[3 + i] = (*rows[3 + i][:4], text)
    return rows


def test_xlsx_axial_step_units(tmp_path):
    gap = np.linspace(5000.0, 4000.0, 100)
    force = 0.001 * (5000.0 - gap)
    f = tmp_path / "comp.xlsx"
    _write_xlsx(f, {"Details": DETAILS, "Axial - 1": _axial_sheet(gap, force)})
    spec, rows, noise, _ = import_file(f, "m/comp", points=20)
    assert spec["height_mm"] == pytest.approx(5.0)
    assert rows.amplitude.unique().tolist() == [0.2]
    assert len(rows) == 20 and set(rows.branch) == {"loading"} and set(rows.cycle) == {1}
    # F = 5 (1 - lambda) N = 5000 (1 - lambda) mN, stress = -F / (16 pi) kPa
    assert rows.nominal_stress_kPa.to_numpy() == pytest.approx(
        -5000 * (1 - rows.stretch.to_numpy()) / (16 * math.pi), rel=1e-9, abs=1e-12)


def test_xlsx_torsion_after_preload(tmp_path):
    gap = np.linspace(5000.0, 4500.0, 30)
    force = 0.0005 * (5000.0 - gap)
    hold = [("Peak hold - 2",), ("Stress", "Shear rate", "Viscosity", "Step time",
                                 "Temperature", "Normal stress"),
            ("Pa", "1/s", "Pa.s", "s", "°C", "Pa")]
    t = np.linspace(0.1, 50.0, 200)
    for ti in t:
        hold.append((20000 * 0.002 * ti, 0.002, 1e5, ti, 25, 2 * 0.25 / (math.pi * 0.004**2)))
    f = tmp_path / "shear.xlsx"
    _write_xlsx(f, {"Details": DETAILS, "Axial - 1": _axial_sheet(gap, force),
                    "Peak hold - 2": hold})
    spec, rows, noise, _ = import_file(f, "m/shear", points=20)
    assert spec["height_mm"] == pytest.approx(4.5) and spec["contact_gap_mm"] == pytest.approx(5)
    assert spec["preload_mN"] == pytest.approx(250.0)
    assert rows.test.unique().tolist() == ["torsion"] and rows.amplitude.iloc[0] == 0.1
    assert rows.shear.to_numpy() == pytest.approx(0.002 * rows.time_s.to_numpy(), rel=1e-9)
    assert rows.torque_mNmm.to_numpy() == pytest.approx(
        torque_mNmm(rows.shear_stress_kPa.to_numpy(), 4.0), rel=1e-12)
    # 40 t Pa = 0.04 t kPa
    assert rows.shear_stress_kPa.to_numpy() == pytest.approx(0.04 * rows.time_s.to_numpy(),
                                                             rel=1e-9)
    assert rows.normal_force_mN.to_numpy() == pytest.approx(250.0, rel=1e-9)
    assert list(noise) == ["torque"]


def test_import_writes_valid_tables(tmp_path):
    d = tmp_path / "data" / "mat"
    (d / "2s").mkdir(parents=True)
    write_trace(d / "2s" / "dc-1.txt", seed=2)
    write_trace(d / "2s" / "dc-2.txt", seed=3)
    out = tmp_path / "out"
    s = import_exports([tmp_path / "data"], out)
    assert s["specimens"] == 2 and s["groups"] == {"mat/2s": 2}
    spec = read_specimens(out / "specimens.csv")
    rec = read_recordings(out / "recordings.csv", spec)
    assert spec.specimen.tolist() == ["mat/dc-1", "mat/dc-2"]
    assert set(spec.region) == {"mat"} and set(spec.brain) == {"2s"}
    assert set(spec.ends) == {"unglued"}  # sandblasted plates: the plate cannot pull
    assert len(rec) == 160 and "gap_mm" in rec
    noise = json.loads((out / "noise.json").read_text())
    assert set(noise) == {"mat/dc-1", "mat/dc-2"} and set(noise["mat/dc-1"]) == {"stress"}
    report = (out / "import.md").read_text()
    assert report.count("\n- ") == 2 and "contact gap" in report


def test_text_exports_in_utf16_or_with_decimal_commas_import_alike(tmp_path):
    """The same raw trace saved as Windows "Unicode" text (UTF-16 with and without its
    byte-order mark) or with decimal commas (a European number setting) imports to the
    same specimen, rows and noise as the UTF-8 file with decimal points (before: a field
    count error, and 'not a number' at the first comma)."""
    f = tmp_path / "mat" / "2s" / "dc-1.txt"
    f.parent.mkdir(parents=True)
    write_trace(f)
    text = f.read_text()
    variants = {"utf16.txt": text.encode("utf-16"), "utf16le.txt": text.encode("utf-16-le"),
                "comma.txt": text.replace(".", ",").encode()}
    ref = import_file(f, "mat/dc-1")
    for name, data in variants.items():
        g = f.with_name(name)
        g.write_bytes(data)
        spec, rows, noise, _ = import_file(g, "mat/dc-1")
        assert spec == ref[0], name
        assert rows.equals(ref[1]), name
        assert noise == ref[2], name


def test_bad_text_line_is_named(tmp_path):
    f = tmp_path / "m" / "g" / "x.txt"
    f.parent.mkdir(parents=True)
    f.write_text(HEADER + "\n0\t0\t0\t0\t0.01\t5000\t\n0.004\t0\t0\t0\t0.01\tabc\t\n")
    with pytest.raises(RheometerError, match=r"x\.txt, line 3: column 'Gap' not a number "
                                             r"\('abc'\)"):
        import_exports([f], tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_cli_malformed_workbook_one_line_no_output(tmp_path):
    gap = np.linspace(5000.0, 4000.0, 30)
    f = tmp_path / "m" / "g" / "bad.xlsx"
    f.parent.mkdir(parents=True)
    _write_xlsx(f, {"Details": DETAILS,
                    "Axial - 1": _axial_sheet(gap, 0.001 * (5000 - gap), bad=(3, "n/a?"))})
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "brainmech", "import", str(tmp_path / "m"),
                        "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert p.returncode != 0
    err = p.stderr.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in p.stderr
    assert err[0].startswith("brainmech import: error: ")
    assert "bad.xlsx, sheet 'Axial - 1', row 7: column 'Gap' not a number ('n/a?')" in err[0]
    assert not out.exists()
    assert [q.name for q in tmp_path.iterdir()] == ["m"]  # no stage left either


def test_workbook_text_cell_is_quoted_not_called_empty(tmp_path):
    """A text cell that pandas would read as missing ('n/a', 'NA') is named as written."""
    gap = np.linspace(5000.0, 4000.0, 30)
    f = tmp_path / "na.xlsx"
    _write_xlsx(f, {"Details": DETAILS, "Axial - 1": _axial_sheet(gap, 0.001 * (5000 - gap),
                                                                  bad=(3, "n/a"))})
    with pytest.raises(RheometerError, match=r"row 7: column 'Gap' not a number \('n/a'\)"):
        import_file(f, "m/na")


def test_contact_uncertainty_grows_with_noise():
    t = np.arange(0, 3, 0.004)
    gap = np.interp(t, [0, 1, 3], [6.0, 6.0, 2.0])
    rng = np.random.default_rng(0)
    widths = []
    for sd in (1.0, 4.0):
        force = 10 + 400 * np.clip(5.0 - gap, 0, None) + rng.normal(0, sd, t.size)
        c = seg.find_contact(t, gap, force)
        assert abs(c.gap_mm - 5.0) <= c.uncertainty_mm
        widths.append(c.uncertainty_mm)
    assert widths[1] > widths[0]


# ------------------------------------------------------------------------------ real data
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared/data/rheometer absent")


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    out = tmp_path_factory.mktemp("rheo") / "out"
    import_exports([DATA], out)
    spec = read_specimens(out / "specimens.csv")
    return spec, read_recordings(out / "recordings.csv", spec), out


@needs_data
def test_real_every_file_imports(real):
    spec, rec, out = real
    files = [f for f in DATA.rglob("*") if f.suffix.lower() in (".txt", ".xls", ".xlsx")]
    assert len(spec) == len(files) and set(rec.specimen) == set(spec.specimen)
    assert spec.height_mm.between(0.5, 20).all()
    assert (out / "import.md").read_text().count("\n- ") == len(files)
    noise = json.loads((out / "noise.json").read_text())
    assert set(noise) == set(spec.specimen)


@needs_data
def test_real_double_compressions_two_cycles(real):
    spec, rec, _ = real
    dc = spec[spec.source.str.contains("double-compressions")]
    assert len(dc) == 15
    for sid in dc.specimen:
        r = rec[rec.specimen == sid]
        assert sorted(set(r.cycle)) == [1, 2]
        assert set(r.branch) == {"loading", "unloading"}
        assert 0.45 <= r.amplitude.iloc[0] <= 0.55
    assert (dc.contact_uncertainty_mm < 0.2).all()
    # every specimen lifts off in cycle 1 and is met again in cycle 2 at a smaller free
    # height (it did not recover between the cycles): 0.71-0.82 H while developing
    for ev in dc.contact_events:
        lift = float(re.search(r"lift-off in cycle 1 at stretch ([\d.]+)", ev).group(1))
        back = float(re.search(r"re-contact in cycle 2 at stretch ([\d.]+)", ev).group(1))
        assert 0.5 < lift < 0.85 and 0.65 < back < 0.9, ev


def test_lift_off_and_re_contact():
    """A moist specimen pulls on the plate before it lets go (still contact), a drive spike
    at the turn does not end the lift-off, and reloading meets it again later."""
    from recordings.rheometer_segments import out_of_contact

    unload = [-50.0, -10.0, 3.0, 5.0, 2.0, 0.1, -0.2, 0.0, 0.9, 0.1]  # spike at the turn
    load = [0.8, 0.1, -0.1, 0.2, -0.3, -2.0, -8.0, -30.0]
    force = np.array(unload + load)
    branch = np.array(["unloading"] * 10 + ["loading"] * 8, dtype=object)
    ramps = np.array([0] * 10 + [1] * 8)
    off = out_of_contact(force, branch, ramps, tol=0.5)
    assert off.tolist() == [False] * 5 + [True] * 5 + [True] * 5 + [False] * 3
