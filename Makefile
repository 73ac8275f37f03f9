# One command surface. `make help` lists the targets.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.DEFAULT_GOAL := help
.PHONY: help install lint format test test-browser test-faults demo bench clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-12s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) ## create .venv and install the project with its dev tools

lint: $(STAMP) ## ruff check, ruff format --check, the import contracts (pyproject.toml)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

format: $(STAMP) ## ruff format + autofix
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

test: $(STAMP) ## run every test (unit, property-based, integration; browser tests need chromium)
	@[ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ] || echo "make test: /usr/bin/chromium or chromedriver missing: the browser tests are SKIPPED (apt-get install -y chromium chromium-driver)"
	$(BIN)/python -m pytest -q -rs -m "not faults"

test-browser: $(STAMP) ## the headless-Chromium tests alone
	$(BIN)/python -m pytest -q -rs -s -m browser

test-faults: $(STAMP) ## the long fault-injection runs
	$(BIN)/python -m pytest -q -m faults

demo: $(STAMP) ## run the main job on embedded defaults (writes out/demo/)
	$(BIN)/hdmap demo --out out/demo

bench: $(STAMP) ## run the benchmarks (see BENCHMARKS.md)
	$(BIN)/python benchmarks/run_all.py

clean: ## remove generated state (keeps .venv)
	rm -rf var out .pytest_cache .hypothesis
