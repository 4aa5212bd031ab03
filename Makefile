# Everything sets itself up: the first `make run` or `make test` creates .venv and installs
# jaxtraj with its test dependencies into it.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: run test bench clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/jaxtraj solve earth-mars --case 4 --out results/earth-mars-case4

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) benchmarks/kernel.py

clean:
	rm -rf $(VENV) results .pytest_cache
