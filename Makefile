# aimbench: one-word entry points. Each target sets up what it needs first (tools/setup.sh:
# Debian packages as root, .venv, the project with the extras the target needs), then runs.
# `make demo` installs the main job's libraries only; `make test` adds the test extra, `make bench`
# the benchmark one (README, "Extras").
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.aimbench-installed
TEST_STAMP  := $(VENV)/.aimbench-test-installed
BENCH_STAMP := $(VENV)/.aimbench-bench-installed
RUN    ?= runs/demo
# Test workers (pytest-xdist): the suite's files are independent, and CI machines have two cores.
# --dist loadfile: a file's tests on one worker, so its module fixtures (a sweep, a study, the
# firmware in simavr) are made once, as in a serial run. --no-loadscope-reorder: the files in
# the order tests/conftest.py gives them, the long ones first (xdist's own puts the files with
# the most tests first, and a long file of three tests started last ran alone for minutes).
JOBS   ?= 2
XDIST  := -n $(JOBS) --dist loadfile --no-loadscope-reorder

.PHONY: setup demo test test-fast lint bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml tools/setup.sh
	bash tools/setup.sh
	touch $@

$(TEST_STAMP): pyproject.toml tools/setup.sh
	bash tools/setup.sh test
	touch $(STAMP) $@

$(BENCH_STAMP): pyproject.toml tools/setup.sh
	bash tools/setup.sh test,bench
	touch $(STAMP) $(TEST_STAMP) $@

## The main job on the simulated bench (README, first command).
demo: setup
	$(BIN)/aimbench demo --out $(RUN)

## The whole test suite (README, second command; CI runs this), on $(JOBS) workers.
test: $(TEST_STAMP)
	$(BIN)/python -m pytest $(XDIST)

test-fast: $(TEST_STAMP)
	$(BIN)/python -m pytest $(XDIST) -m "not slow"

lint: $(TEST_STAMP)
	$(BIN)/ruff check .

## Every benchmark, one after the other (each prints its own table).
bench: $(BENCH_STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache bench_fw/build
