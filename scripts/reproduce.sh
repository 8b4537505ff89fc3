#!/usr/bin/env bash
# The README's first command. Until `brainmech reproduce` (the whole study) exists, it runs
# the forward model on the default protocols and prints the computed curves' key numbers.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
BM=.venv/bin/brainmech
OUT=${OUT:-results/forward}
mkdir -p "$OUT"
$BM simulate --test compression_tension --amplitude 0.15 --out "$OUT/compression_tension.csv"
$BM simulate --test torsion --amplitude 0.30 --out "$OUT/torsion_0.30.csv"
.venv/bin/python - "$OUT" <<'PY'
import sys
import pandas as pd
out = sys.argv[1]
ct = pd.read_csv(f"{out}/compression_tension.csv")
to = pd.read_csv(f"{out}/torsion_0.30.csv")
c = ct.loc[ct.stretch.idxmin()]
t = ct.loc[ct.stretch.idxmax()]
s = to.loc[to.shear.idxmax()]
print("Glued cylinder R = 4 mm, H = 5 mm, one-term Ogden mu = 1 kPa, alpha = -20, nu0 = 0.49")
print(f"  nominal stress at stretch {c.stretch:.2f}: {c.nominal_stress_kPa:+.4f} kPa")
print(f"  nominal stress at stretch {t.stretch:.2f}: {t.nominal_stress_kPa:+.4f} kPa")
print(f"  torque at shear {s.shear:.2f}: {s.torque_mNmm:.3f} mN mm "
      f"(shear stress {s.shear_stress_kPa:.4f} kPa, axial force {s.axial_force_mN:+.3f} mN)")
print(f"  curves: {out}/compression_tension.csv, {out}/torsion_0.30.csv")
PY
