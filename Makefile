# The two commands: `make sim` and `make test`. Both create .venv when missing and
# reinstall it when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SIM_ARGS ?= mbzirc --uavs 2 --lockstep --duration 90 --seed 1 --detector oracle

.PHONY: .venv sim test bench schemas clean

.venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

sim: .venv
	$(VENV)/bin/falconry sim $(SIM_ARGS)

test: .venv
	$(PY) -m pytest -q

bench: .venv
	$(PY) benchmarks/transport.py

schemas: .venv
	$(PY) -m schemas export

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
