#!/usr/bin/env bash
# The project's test command (host lane and, with VENV=..., the rootfs lane):
# ruff, the whole suite in serial, then the tests marked `mpi` under `mpirun -n 2`.
# pytest's exit code 5 ("no tests collected") is a failure here.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
export OMPI_MCA_rmaps_base_oversubscribe=1 OMPI_MCA_btl=${OMPI_MCA_btl:-self,vader}
export PRTE_MCA_rmaps_default_mapping_policy=:oversubscribe

run_pytest() {
  local rc=0
  "$@" || rc=$?
  if [ "$rc" -eq 5 ]; then echo "run_tests: pytest collected no tests: failing" >&2; return 1; fi
  return "$rc"
}

echo "== ruff"
"$VENV/bin/ruff" check .
echo "== pytest (serial)"
run_pytest "$VENV/bin/python" -m pytest -q ${PYTEST_ARGS:-}
echo "== pytest -m mpi under mpirun -n 2"
run_pytest mpirun -n 2 "$VENV/bin/python" -m pytest -q -m mpi -p no:cacheprovider ${PYTEST_ARGS:-}
