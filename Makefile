# agos: `make demo` runs the system locally, `make test` runs the test suite.
# Both create .venv from plain python3 on a fresh machine and install what they need.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint typecheck contracts unit e2e deploy-test clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/agos demo

test: lint contracts typecheck
	$(BIN)/python -m pytest -q

# The layer contracts in pyproject.toml: runtime at the bottom; world, agents, evaluator beside each
# other; deploy on top; no import cycles.
contracts: $(STAMP)
	$(BIN)/lint-imports

# mypy sees the top-level folders under their agos.* names through a folder of links.
typecheck: $(STAMP)
	mkdir -p .typecheck/agos
	for d in runtime world agents evaluator deploy; do ln -sfn ../../$$d .typecheck/agos/$$d; done
	cd .typecheck && ../$(BIN)/mypy --config-file ../pyproject.toml -p agos

unit: $(STAMP)
	$(BIN)/python -m pytest -q -m "not e2e"

e2e: $(STAMP)
	$(BIN)/python -m pytest -q -m e2e

# The compose deployment for real (docs/DEPLOY.md): needs root or a running Docker engine; installs
# docker.io, docker-compose and debootstrap when missing. Not part of `make test`.
deploy-test: $(STAMP)
	$(BIN)/python tests/deploy/compose_e2e.py

lint: $(STAMP)
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) runs .wheels .pytest_cache .ruff_cache .mypy_cache .typecheck *.egg-info
