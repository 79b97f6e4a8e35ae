# agos: `make demo` runs the system locally, `make test` runs the test suite.
# Both create .venv from plain python3 on a fresh machine and install what they need.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# Python may cache its compiled modules here even where the environment says not to: the tests start
# hundreds of Python processes, and each compiling numpy, pydantic and agos afresh cost about a third
# of an end-to-end test's CPU (tests/test_e2e_faults.py: 233 -> 157 CPU s).
unexport PYTHONDONTWRITEBYTECODE
# Installs come from uv.lock (every package pinned, with hashes). uv itself is a pinned wheel from
# PyPI in its own folder inside .venv, where `uv sync` leaves it alone.
UV_VERSION := 0.13.9
UV     := $(VENV)/uv-$(UV_VERSION)/bin/uv
UV_ENV := UV_PROJECT_ENVIRONMENT=$(VENV) UV_PYTHON_DOWNLOADS=never
LOCK_EXPORT := $(UV) export --frozen --no-emit-project --quiet

.PHONY: demo check test static all-tests lint lock lock-check typecheck contracts unit unit-quick loopback e2e deploy-test slurm-test clean

$(UV):
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade --target $(VENV)/uv-$(UV_VERSION) "uv==$(UV_VERSION)"

# Exactly the lock's versions (packages not in it are removed), agos itself editable, the dev extra.
$(STAMP): pyproject.toml uv.lock | $(UV)
	$(UV_ENV) $(UV) sync --frozen --extra dev --python $(BIN)/python
	touch $(STAMP)

# After a change to the dependencies in pyproject.toml (needs the network): the lock and its two
# pip-readable exports, all three committed.
lock: | $(UV)
	$(UV) lock
	$(LOCK_EXPORT) --output-file requirements.lock.txt
	$(LOCK_EXPORT) --extra dev --output-file requirements-dev.lock.txt

# uv.lock agrees with pyproject.toml (no network: a current lock is checked without resolving).
lock-check: | $(UV)
	@$(UV) lock --check --offline --quiet || { echo "uv.lock does not match pyproject.toml: run make lock, commit uv.lock and requirements*.lock.txt" >&2; exit 1; }

demo: $(STAMP)
	$(BIN)/agos demo

# The test tiers (README, Development). A test's marks say what it may do, and tests/process_guard.py
# fails one that does more: unmarked (unit) starts no process and opens no socket; loopback opens
# sockets in its own process; e2e starts processes.
# check: ruff, the layer contracts, mypy and the unit tests but the slow ones (marked slow: they play,
# sample or render episodes: seconds of CPU each), the four at once; make test runs the slow ones too.
check: $(STAMP)
	$(MAKE) --no-print-directory -j4 --output-sync=target lint contracts typecheck unit-quick

# test: what check runs, and every loopback and e2e test too, in one pytest session on two workers
# (each file on one worker, so a module's running system is started once; every test takes free
# ports), beside ruff, the contracts and mypy. One session lets the CPU-bound unit tests fill the time
# the e2e tests spend waiting on processes and timers. It lists its 25 slowest tests: where CI's time goes.
test: $(STAMP)
	$(MAKE) --no-print-directory -j2 --output-sync=target static all-tests

static: lint contracts typecheck

all-tests: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=25

# The layer contracts in pyproject.toml: runtime at the bottom; world, agents, evaluator beside each
# other; the library (agos/ itself) on them; deploy on top; no import cycles. Run in .typecheck/, where
# the package is one folder as installed (import-linter cannot follow setuptools' package-dir mapping).
contracts: $(STAMP) typecheck-links
	cd .typecheck && ../$(BIN)/lint-imports --no-cache ../pyproject.toml

# mypy sees the top-level folders under their agos.* names through a folder of links (and examples/ as
# a user's code would import it); then the scripts that draw docs/images, which no test runs (a second
# call: mypy takes packages or files, not both; it reuses the first call's cache).
typecheck: $(STAMP) typecheck-links
	cd .typecheck && ../$(BIN)/mypy --config-file ../pyproject.toml -p agos -p examples
	cd .typecheck && ../$(BIN)/mypy --config-file ../pyproject.toml ../docs/*.py

# .typecheck/agos: the package as installed, made of links: agos/*.py (the package's own modules) and
# one link per subpackage folder; a link whose file is gone is removed.
.PHONY: typecheck-links
typecheck-links:
	mkdir -p .typecheck/agos
	for d in runtime world agents evaluator deploy; do ln -sfn ../../$$d .typecheck/agos/$$d; done
	for f in agos/*.py; do ln -sfn ../../$$f .typecheck/$$f; done
	find .typecheck/agos -maxdepth 1 -xtype l -delete
	ln -sfn ../examples .typecheck/examples

# The unit tests on every core; a module's tests stay on one worker, so its fixtures are built once.
unit: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadscope -m "not e2e and not loopback"

unit-quick: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadscope -m "not e2e and not loopback and not slow"

loopback: $(STAMP)
	$(BIN)/python -m pytest -q -m "loopback and not e2e"

e2e: $(STAMP)
	$(BIN)/python -m pytest -q -m e2e

# The quick form of every ratio benchmark and the look-alike table's check, then one table of figures
# against their goals (6-7 minutes on 2 cores; bench/README.md). Fails when a bench crashes or the
# look-alike check (bench_cues.py --check, a fixed seed) fails, never on a missed timing goal.
.PHONY: bench
bench: $(STAMP)
	$(BIN)/python bench/run_all.py

# The compose deployment for real (docs/DEPLOY.md): needs root or a running Docker engine; installs
# docker.io, docker-compose and debootstrap when missing. Not part of `make test`.
deploy-test: $(STAMP)
	$(BIN)/python tests/deploy/compose_e2e.py

# deploy/slurm/agos-eval.sbatch for real on a 3-node Slurm cluster started on this machine: needs root
# and Debian's slurmctld, slurmd, slurm-client and munge (.ci/run installs them). Not part of `make test`.
slurm-test: $(STAMP)
	$(BIN)/python tests/deploy/slurm_e2e.py

lint: $(STAMP) lock-check
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) runs .wheels .pytest_cache .ruff_cache .mypy_cache .typecheck *.egg-info
