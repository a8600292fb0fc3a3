# Omnidata service: developer and CI entry points. `make test` needs nothing but python3.11 and root (or
# running Postgres/Redis): it builds .venv and starts the services it needs.
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv services test test-fast lint bench gpu-bundle demo clean

venv: $(STAMP)

# Re-install only when pyproject.toml changed since the last install. The worker's kernels are compiled once here
# (~40 s on one core) instead of in every worker of the first `generate`
# (services/worker/process/kernel_warm_up.py). The project's bytecode too, as pip compiles an installed
# package's: an editable install has none, and with PYTHONDONTWRITEBYTECODE set (CI machines) every process
# compiled the ~30k lines it imports again (~0.3 CPU-s for generate's and a worker's modules). A source edited
# later is recompiled as before (the .pyc is stale).
$(STAMP): pyproject.toml
	@if [ ! -x $(BIN)/python ]; then $(PY) -m venv $(VENV); fi
	$(BIN)/pip install -q -e '.[dev]'
	$(BIN)/omnidata compile-kernels
	$(BIN)/python -m compileall -q services
	@touch $(STAMP)

services:
	bash scripts/ensure_services.sh

# The suite in several processes, the tests that assert a recovery deadline beside it at normal priority
# (scripts/run_tests.sh). A plain `$(BIN)/pytest` runs it all in one process.
test: venv services
	BIN=$(BIN) bash scripts/run_tests.sh

test-fast: venv services
	BIN=$(BIN) TEST_MARK="not slow" bash scripts/run_tests.sh

lint: venv
	$(BIN)/ruff check services tests bench
	$(BIN)/mypy services

# Every benchmark with a main, full size, into bench/results/ (bench/README.md; hours on a small machine).
# bench/lib is their shared code; startup_ab.py compares two revisions (--against REV) and runs by hand.
BENCH_MAINS = $(shell grep -l '^if __name__ == "__main__":' bench/*/*.py)
BENCH_SCRIPTS = $(filter-out bench/render/startup_ab.py,$(BENCH_MAINS))
bench: venv services
	@set -e; for f in $(BENCH_SCRIPTS); do echo "== $$f"; $(BIN)/python $$f; done

# The project's install in parts for a lent GPU machine (no registry there, 64 MiB a call): .gpu/part_*; the calls
# that carry and run them are in scripts/device_bundle.py's docstring. Needs strace, zstd, xz and CUDA's ptxas.
gpu-bundle: venv
	$(BIN)/python scripts/device_bundle.py

# The main job on the embedded default (SQLite + local folder + local worker processes): two real scans
# shipped in examples/scans (licenses in their SOURCE.md), every default cue, then a contact sheet.
# Running it again resumes and renders only what is missing.
DEMO_OUT ?= demo-out
SCENES ?= examples/scans
demo: venv
	$(BIN)/omnidata generate $(SCENES)/ycb_banana $(SCENES)/stanford_bunny/bun_zipper_res2.ply \
		--out $(DEMO_OUT) --spec examples/objects.yaml
	$(BIN)/omnidata sheet $(DEMO_OUT) --views 6
	@echo "outputs: $(abspath $(DEMO_OUT)) (manifest.jsonl, job.json, <cue>/<component>/<space>/...)"
	@echo "contact sheet: $(abspath $(DEMO_OUT))/contact_sheet.png"

clean:
	rm -rf .pytest_cache .mypy_cache .ruff_cache build dist out demo-out test-artifacts
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
