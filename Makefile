# The single entry point: `make demo` and `make test` set everything up themselves (a local
# virtualenv in .venv with the package built from source), so they work on a fresh clone.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO := build/demo

.PHONY: setup browser demo test lint test-rust test-python bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Builds the Rust extension (release) and installs the package with its test tools.
setup: $(BIN)/python
	$(BIN)/python -m pip install --quiet --editable ".[test]"

# Debian's chromium for the web UI's browser tests (apt-get; skipped when already there).
browser:
	@command -v chromium >/dev/null 2>&1 || bash .ci/install-chromium

demo: setup
	$(BIN)/hitl-slam demo -o $(DEMO)

lint: setup
	cargo fmt --check
	cargo clippy --all-targets -- -D warnings
	cargo clippy --features python --lib -- -D warnings
	$(BIN)/ruff check python tests benches
	$(BIN)/ruff format --check python tests benches
	$(BIN)/mypy
	$(BIN)/python -m mypy.stubtest hitl_slam._core

test-rust:
	cargo test

test-python: setup browser
	$(BIN)/python -m pytest

test: lint test-rust test-python

# Long measurements; not part of `make test`.
bench: setup
	$(BIN)/python benches/compare_gtsam.py --write benches/README.md
	$(BIN)/python benches/outliers.py --seeds 0 1 2 --write benches/README.md
	$(BIN)/python benches/chains.py --write benches/README.md
	/usr/bin/time -v $(BIN)/python benches/scale.py --write benches/README.md
	cargo bench

clean:
	rm -rf $(VENV) build target
