# Omnidata service: developer and CI entry points. `make test` needs nothing but python3.11 and root (or
# running Postgres/Redis): it builds .venv and starts the services it needs.
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv services test test-fast lint bench demo clean

venv: $(STAMP)

# Re-install only when pyproject.toml changed since the last install.
$(STAMP): pyproject.toml
	@if [ ! -x $(BIN)/python ]; then $(PY) -m venv $(VENV); fi
	$(BIN)/pip install -q -e '.[dev]'
	@touch $(STAMP)

services:
	bash scripts/ensure_services.sh

test: venv services
	$(BIN)/pytest -q

test-fast: venv services
	$(BIN)/pytest -q -m "not slow"

lint: venv
	$(BIN)/ruff check services tests bench
	$(BIN)/mypy services

bench: venv services
	@mkdir -p bench/results
	@set -e; for f in bench/*.py; do echo "== $$f"; $(BIN)/python $$f; done

# Placeholder until the end-to-end demo lands.
demo: venv
	$(BIN)/omnidata --help

clean:
	rm -rf .pytest_cache .mypy_cache .ruff_cache build dist out demo-out test-artifacts
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
