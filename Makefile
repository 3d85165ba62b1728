# The single entry point: `make demo` and `make test` set everything up themselves (a local
# virtualenv in .venv with the package built from source), so they work on a fresh clone.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DEMO := build/demo

.PHONY: setup browser demo test test-fast lint test-rust test-python bench kill-trials clean

$(BIN)/python:
	@echo "setup: creating the virtualenv $(VENV)"
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Installs the package with its test tools (the [test] extra, which includes [web] and [plot])
# in two steps, so that the slow one is not silent: first the dependencies, read from
# pyproject.toml (quietly), then the package itself, whose build (maturin running cargo, release)
# shows each crate it compiles; the build's whole output goes to $(BUILD_LOG).
BUILD_LOG := $(VENV)/build.log

setup: $(BIN)/python
	@echo "setup: installing the Python dependencies and test tools into $(VENV)"
	@$(BIN)/python -c 'import tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; print("\n".join(p["dependencies"] + p["optional-dependencies"]["test"]))' > $(VENV)/requirements-test.txt
	$(BIN)/python -m pip install --quiet --requirement $(VENV)/requirements-test.txt
	@echo "setup: building the Rust core (release) and installing hitl-slam: about 4 minutes on 2 cores"
	@echo "setup: the first time, seconds afterwards. Each crate is listed as its compilation starts;"
	@echo "setup: the last two (faer, then hitl-slam) take about 2 minutes between them without output"
	@start=$$(date +%s); \
	{ $(BIN)/python -m pip install --no-deps --editable . --verbose; echo $$? > $(BUILD_LOG).status; } 2>&1 \
		| tee $(BUILD_LOG) \
		| grep --line-buffered -E '^ *(Compiling|Finished) |Built wheel|^(error|warning)|Successfully installed hitl-slam'; \
	status=$$(cat $(BUILD_LOG).status); \
	if [ "$$status" != 0 ]; then \
		tail -n 40 $(BUILD_LOG); \
		echo "setup: the build failed (pip exit status $$status); its whole output is in $(BUILD_LOG)"; \
		exit 1; \
	fi; \
	echo "setup: hitl-slam built and installed in $$(( $$(date +%s) - start )) s"

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

# The unit tests alone (no public datasets, no browser, no fuzzing, nothing slow; the markers are
# in pyproject.toml and tests/conftest.py): a few minutes, for the edit-test loop. `make test` is
# what CI runs.
test-fast: setup
	$(BIN)/python -m pytest -q -m "not datasets and not browser and not fuzz and not slow"

# Long measurements; not part of `make test`.
bench: setup
	$(BIN)/python benches/compare_gtsam.py --write benches/README.md
	$(BIN)/python benches/outliers.py --seeds 0 1 2 --write benches/README.md
	$(BIN)/python benches/chains.py --write benches/README.md
	/usr/bin/time -v $(BIN)/python benches/scale.py --write benches/README.md
	cargo bench

# kill -9 trials of a session (tests/kill_trials.py): a child runs corrections, undo, redo and
# saves, is killed with SIGKILL at a random moment, and the reopened session must hold every
# acknowledged step, nothing else, and nothing half-written. About 2 s per trial; `make test`
# runs 2 of them (tests/test_kill_trials.py).
KILL_TRIALS ?= 200

kill-trials: setup
	$(BIN)/python tests/kill_trials.py --trials $(KILL_TRIALS)

clean:
	rm -rf $(VENV) build target

.PHONY: fuzz

# Property-based fuzzing of every reader (issue 13): FUZZ_EXAMPLES cases per reader (corrections
# JSONL, .hitl, .covars, g2o, TORO, CARMEN, relations, ROS bags: mutated bytes, hostile values
# through rosbags' writers, a bag directory's metadata.yaml); `make test` runs a few of each.
# Per-reader tallies are rewritten every 500 cases in $(FUZZ_STATS). Hours on 2 cores at the
# default.
FUZZ_EXAMPLES ?= 100000
FUZZ_STATS ?= build/fuzz-stats.json

fuzz: setup
	mkdir -p $(dir $(FUZZ_STATS))
	HITL_FUZZ_PROFILE=fuzz HITL_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) HITL_FUZZ_STATS=$(FUZZ_STATS) \
		$(BIN)/python -m pytest -p no:cacheprovider -q --hypothesis-show-statistics \
		tests/test_fuzz_readers.py tests/test_fuzz_session.py
