# The two commands of the README are `make reproduce` and `make test`.
# Every target sets up what it needs first (idempotent, seconds when already done).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
export OMPI_ALLOW_RUN_AS_ROOT ?= 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM ?= 1
export OMPI_MCA_rmaps_base_oversubscribe ?= 1
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: setup reproduce test test-serial test-mpi test-docker lint bench clean

setup:
	@bash scripts/setup_host.sh

reproduce: setup
	@bash scripts/reproduce.sh

test: setup
	@bash scripts/run_tests.sh

test-docker:
	@bash docker/rootfs_test.sh

lint: setup
	$(VENV)/bin/ruff check .

# Benchmarks that need no trained surrogates; the others are listed in BENCHMARKS.md.
bench: setup
	OPENBLAS_NUM_THREADS=1 $(PY) benchmarks/bench_forward.py
	OPENBLAS_NUM_THREADS=1 $(PY) benchmarks/bench_sampling.py
	OPENBLAS_NUM_THREADS=1 $(PY) benchmarks/convergence.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
