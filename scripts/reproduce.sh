#!/usr/bin/env bash
# The README's first command: the whole study on the embedded synthetic brain bank
# (sample -> train -> identify -> correlate -> report), quick profile by default.
# PROFILE=default|paper and OUT=DIR override; a re-run reuses finished stages.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OPENBLAS_NUM_THREADS=1
.venv/bin/brainmech reproduce --profile "${PROFILE:-quick}" --out "${OUT:-results/reproduce}"
