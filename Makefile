# The two commands: `make sim` and `make test`. Both create .venv when missing and
# reinstall it when pyproject.toml changes.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SIM_ARGS ?= mbzirc --uavs 2 --lockstep --duration 90 --seed 1
CAMPAIGN_ARGS ?= --runs 20 --seed 1

.PHONY: .venv sim test acceptance bench campaign schemas clean

.venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

sim: .venv
	$(VENV)/bin/falconry sim $(SIM_ARGS)

# the slowest tests are listed at the end: the whole target must stay under 15 minutes
test: .venv
	$(PY) -m pytest -q --durations=15

# the whole missions beyond make test's budget (link cuts at t = 20 and 60 s on 2 and 3 UAVs; about 5 min),
# each with the figures it printed (-rP)
acceptance: .venv
	$(PY) -m pytest -q -rP -m heavy

bench: .venv
	$(PY) benchmarks/transport.py

# 20 seeded runs with a random fault each (about 15 min; `make test` flies a 2-run one)
campaign: .venv
	$(VENV)/bin/falconry campaign $(CAMPAIGN_ARGS)

schemas: .venv
	$(PY) -m schemas export

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
