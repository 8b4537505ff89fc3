#!/usr/bin/env bash
# Docker lane set-up on Debian 13 (trixie): Debian's DOLFINx 0.9.0 stack + a venv at $VENV that
# sees it, with the project installed editable (test extras). One recipe for both ways of running
# the lane: `docker build` (docker/Dockerfile) and debootstrap + chroot (docker/rootfs_test.sh).
# Idempotent: apt is skipped when every package is installed, pip when the stamp matches, so a
# second run takes seconds.
#   --apt-only   install the Debian packages only (the Dockerfile's cached layer).
set -euo pipefail

APP=$(cd "$(dirname "$0")/.." && pwd)
VENV=${VENV:-/opt/brainmech/venv}
DOLFINX_EXPECTED=${BRAINMECH_DOLFINX_VERSION:-0.9.0}
export DEBIAN_FRONTEND=noninteractive

# python3-dolfinx already depends on python3-dev, compilers and libopenmpi-dev (via libdolfinx-dev);
# they are listed anyway because the FFCx JIT (cffi) compiles C against Python.h at run time.
# ca-certificates: pip reaches PyPI over HTTPS (trixie-slim has no CA bundle).
APT_PACKAGES=(python3-dolfinx python3-petsc4py python3-mpi4py python3-gmsh python3-venv
              python3-dev libpython3-dev gcc g++ make openmpi-bin ca-certificates
              libopenblas0-pthread)

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "install: installing Debian packages: ${missing[*]}"
  # ~480 packages: dpkg's chatter goes to a log, shown only if apt fails.
  log=/var/log/brainmech-apt.log
  if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}"; } >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    echo "install: apt-get failed (log: $log)" >&2
    exit 1
  fi
  # Keep the image (and the cached rootfs) small; lists are fetched again only if a package is missing.
  apt-get clean
  rm -rf /var/lib/apt/lists/*
fi
[ "${1:-}" = "--apt-only" ] && exit 0

# Recreate the venv if it is missing or was made by another Python (e.g. after a rootfs upgrade).
sys_ver=$(/usr/bin/python3 -c 'import sys; print(sys.version.split()[0])')
if [ ! -x "$VENV/bin/python" ] || [ "$("$VENV/bin/python" -c 'import sys; print(sys.version.split()[0])' 2>/dev/null)" != "$sys_ver" ]; then
  echo "install: creating $VENV (system site packages visible)"
  rm -rf "$VENV"
  mkdir -p "$(dirname "$VENV")"
  /usr/bin/python3 -m venv --system-site-packages "$VENV"
fi

# Hold numpy, petsc4py, mpi4py, the FEniCS packages... at Debian's versions: DOLFINx is built against them.
constraints=$VENV/constraints.txt
/usr/bin/python3 "$APP/scripts/write_constraints.py" > "$constraints.new"
mv "$constraints.new" "$constraints"
# PIP_CONSTRAINT too, so that pip's isolated build environments respect the pins as well.
export PIP_CONSTRAINT=$constraints PIP_DISABLE_PIP_VERSION_CHECK=1

stamp=$VENV/.installed-$(cat "$APP/pyproject.toml" "$constraints" "${BASH_SOURCE[0]}" | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ]; then
  echo "install: installing the project (editable, test extras)"
  "$VENV/bin/python" -m pip install -q -e "${APP}[test]" -c "$constraints"
  rm -f "$VENV"/.installed-*
  touch "$stamp"
fi

# The lane exists to test DOLFINx 0.9: fail loudly if the distribution gave us something else.
"$VENV/bin/python" - "$DOLFINX_EXPECTED" <<'EOF'
import sys

import dolfinx
import mpi4py
import numpy
import petsc4py

print(f"install: python {sys.version.split()[0]}, dolfinx {dolfinx.__version__}, "
      f"petsc4py {petsc4py.__version__}, mpi4py {mpi4py.__version__}, numpy {numpy.__version__}")
if dolfinx.__version__ != sys.argv[1]:
    sys.exit(f"install: expected dolfinx {sys.argv[1]}, got {dolfinx.__version__}")
EOF
