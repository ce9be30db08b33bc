# Two commands a user needs: `make demo` and `make test`. Each sets itself up first (idempotent).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Exact versions of every dependency (pip constraints): a fresh machine installs what the results
# were measured with. `make lock` rewrites it from the current environment after a deliberate upgrade.
LOCK := .ci/requirements.lock
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup sysdeps demo test test-slow lint docs docs-build lock repro clean-runs

setup: sysdeps $(STAMP)

# The open3d 0.20 wheel links against libusb-1.0 but does not ship it. The operator page's test
# drives Debian's Chromium (a browser a pip package downloads is not installable here); without
# apt the test says why it skips.
sysdeps:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; }
	@command -v chromedriver >/dev/null || ! command -v apt-get >/dev/null || { \
	  echo "installing chromium and chromium-driver (the operator page's browser test)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq chromium chromium-driver >/dev/null; }

$(STAMP): pyproject.toml $(LOCK)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -c $(LOCK) -e '.[dev,bench,docs]'
	@touch $(STAMP)

demo: setup
	$(BIN)/binpick demo

# The suite without the end-to-end runs (marker `slow`: Prefect flows driving DVC stage processes,
# served schedules; about 14 minutes on 2 CPU cores), which test-slow runs and CI runs after it.
test: lint docs-build
	$(BIN)/python -m pytest -q -m "not slow"

test-slow: setup
	$(BIN)/python -m pytest -q -m slow

# ruff (pyflakes, pycodestyle, import order, bugbear, no print; lines of 120, formatted by `ruff format`) on
# everything; mypy (untyped defs checked) on the library, the application and the stages.
lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# The documentation site: served on http://127.0.0.1:8000 (rebuilt on every edit), or built into
# site/ in strict mode (a broken link, a page missing from the navigation or a reference page
# that cannot be generated fails the build).
docs: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs serve -a 127.0.0.1:8000

docs-build: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

lock: setup
	@{ echo "# Exact versions the project's results were measured with (pip constraints; \`make lock\` rewrites it)."; \
	  $(BIN)/python -m pip freeze --exclude-editable | grep -v '^binpick' | sed 's/^torch==\(.*\)+cpu$$/torch==\1/'; } > $(LOCK)

repro: setup
	$(BIN)/binpick repro

# The run records: the local MLflow store and its artifacts, and Prefect's state (data/README.md).
# Models, results and kept service requests stay.
clean-runs:
	rm -rf data/mlflow data/prefect
