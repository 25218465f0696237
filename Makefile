# aimbench: one-word entry points. Each target sets up what it needs first (tools/setup.sh:
# Debian packages as root, .venv, the project with its test extras), then runs.
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.aimbench-installed
# the tests' own Debian packages too (tools/setup.sh --test: chromium, chromium-driver)
TSTAMP := $(VENV)/.aimbench-test-installed
RUN    ?= runs/demo

.PHONY: setup demo test test-fast lint bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml tools/setup.sh
	bash tools/setup.sh
	touch $@

## The main job on the simulated bench (README, first command).
demo: setup
	$(BIN)/aimbench demo --out $(RUN)

$(TSTAMP): pyproject.toml tools/setup.sh
	bash tools/setup.sh --test
	touch $(STAMP) $@

## The whole test suite (README, second command; CI runs this).
test: $(TSTAMP)
	$(BIN)/python -m pytest

test-fast: $(TSTAMP)
	$(BIN)/python -m pytest -m "not slow"

lint: setup
	$(BIN)/ruff check .

## Every benchmark, one after the other (each prints its own table).
bench: setup
	$(BIN)/python -m pip install -q -e '.[test,bench]'
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache bench_fw/build
