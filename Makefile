# The two README commands. Each works on a fresh machine with only python3 and pip.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast check lint types bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[all,test]'
	$(PY) -m pip install --quiet -e '.[aravis]' >/dev/null 2>&1 || echo "PyGObject could not be built here (it needs libgirepository1.0-dev, libcairo2-dev, pkg-config; .ci/run installs them): the Aravis camera tests will skip"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m procedures.demo

# The suite on one worker more than there are cores: a module runs whole on one worker (its cell is
# started once), the longest modules first (tests/conftest.py); the 15 slowest tests are listed at the
# end. About a third of the suite waits (on twins, retries, timeouts), so a third worker on two cores
# fills those waits (measured on the 2-core VM: 674 s with 2 workers, 580 s with 3, both green). A fourth
# only adds contention: 2026-12-03, on a faster VM than the figures above, one commit, 516 s with 3 workers
# and 562 s with 4 (CPU 14.3 against 17.0 min), both green.
WORKERS ?= $(shell $(PYTHON) -c "import os; print(len(os.sched_getaffinity(0)) + 1)")
PYTEST_PARALLEL := -n $(WORKERS) --dist loadfile --no-loadscope-reorder --durations=15

# Lint and type checks first: a new lint or type error fails `make test` (and so CI).
test: check
	$(PY) -m pytest -q $(PYTEST_PARALLEL)

# The unit tests only: no simulated cell, twin process, server, database or browser.
test-fast: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_PARALLEL) -m "not integration"

check: lint types

lint: $(STAMP)
	$(PY) -m ruff check .

types: $(STAMP)
	$(PY) -m mypy

bench: $(STAMP)
	for b in benchmarks/*.py; do OMP_NUM_THREADS=1 $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache .ruff_cache
