#!/usr/bin/env bash
# Host set-up on Debian 12 (bookworm): Debian's DOLFINx 0.5.2 stack + a venv that sees it.
# Idempotent: every step is skipped when already done, so a second run takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(python3-dolfinx python3-petsc4py python3-mpi4py python3-gmsh python3-venv
              python3-dev openmpi-bin libopenmpi-dev gcc g++ make debootstrap
              libopenblas0-pthread)  # OpenBLAS replaces the reference BLAS (10x+ for numpy)

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv (system site packages visible)"
  /usr/bin/python3 -m venv --system-site-packages .venv
fi

# Hold numpy (and the other Debian-provided scientific stack) at the system versions.
/usr/bin/python3 scripts/write_constraints.py > .venv/constraints.txt

stamp=.venv/.installed-$(cat pyproject.toml .venv/constraints.txt | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ]; then
  echo "setup: installing the project (editable, test extras)"
  .venv/bin/python -m pip install -q --upgrade "pip>=23" -c .venv/constraints.txt
  PIP_CONSTRAINT=.venv/constraints.txt .venv/bin/python -m pip install -q -e ".[test]" -c .venv/constraints.txt
  rm -f .venv/.installed-*
  touch "$stamp"
fi

# The project's bytecode, as a wheel's install would write it (an editable install does not):
# where PYTHONDONTWRITEBYTECODE is set, every command would otherwise compile its ~80 modules
# afresh (0.08 s of each start); a stale file is recompiled in memory, never used.
# The packages are read from pyproject.toml, so that a new one needs adding there alone.
.venv/bin/python - <<'PY'
import compileall
import tomllib

with open("pyproject.toml", "rb") as f:
    packages = tomllib.load(f)["tool"]["setuptools"]["packages"]
ok = [compileall.compile_dir(top, quiet=2, workers=0)
      for top in sorted({p.split(".")[0] for p in packages})]
raise SystemExit(0 if all(ok) else 1)
PY
