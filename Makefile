# Everything sets itself up: the first `make run` or `make test` creates .venv and installs
# jaxtraj with its test dependencies into it.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: run test test-slow test-isa check bench clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/jaxtraj solve earth-mars --case 4 --out results/earth-mars-case4

# test files spread over the cores (pytest-xdist; a file stays in one process, where its tests
# share compiled solvers), at most 4 processes (each can hold a few GB of compiled programs).
# Compiled at XLA's backend (LLVM) optimization level 0: compiling is most of this tier's time
# and takes half as long there (benchmarks/RESULTS.md, "make test"); it is also another
# arithmetic than the default level 3, which `test-slow` and `test-isa` keep.
test: $(STAMP)
	XLA_FLAGS="--xla_backend_optimization_level=0 $$XLA_FLAGS" $(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile --durations=30

# the studies marked `slow` (re-solves against finite differences, adaptive simulations), which
# `make test` leaves out; CI runs them too
test-slow: $(STAMP)
	$(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile -m slow

# another CPU's arithmetic on this one (issue 49): the round-off-sensitive tests (both tiers) with XLA's
# vectorization capped at SSE4.2 and at AVX (FMA use and reduction order change as on
# another processor)
ISA_TESTS := tests/test_random_problems.py tests/test_classic.py tests/test_kalman_sqp.py
test-isa: $(STAMP)
	for isa in SSE4_2 AVX; do \
	  XLA_FLAGS=--xla_cpu_max_isa=$$isa $(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile -m "slow or not slow" $(ISA_TESTS) || exit 1; \
	done

# lint, format check, type check (basedpyright, basic mode, over jaxtraj/), and the documentation
# site built with --strict (into a throwaway folder)
check: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/basedpyright --project . --pythonpath $(PY)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet --site-dir $$(mktemp -d)

bench: $(STAMP)
	$(PY) benchmarks/kernel.py

clean:
	rm -rf $(VENV) results .pytest_cache
