# dmd_jax — every target creates the venv from pyproject.toml first if needed.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
PYTEST_WORKERS ?= 2

.PHONY: install test test-slow lint format

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) -q --durations=15

test-slow: $(STAMP)
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) -q -m slow --durations=15

lint: $(STAMP)
	$(BIN)/ruff check dmd_jax tests experiments benchmarks
	$(BIN)/ruff format --check dmd_jax tests experiments benchmarks

format: $(STAMP)
	$(BIN)/ruff format dmd_jax tests experiments benchmarks
	$(BIN)/ruff check --fix dmd_jax tests experiments benchmarks
