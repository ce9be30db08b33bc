# Two commands a user needs: `make demo` and `make test`. Each sets itself up first (idempotent).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: setup sysdeps demo test repro clean-runs

setup: sysdeps $(STAMP)

# The open3d 0.20 wheel links against libusb-1.0 but does not ship it.
sysdeps:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; }

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,bench]'
	@touch $(STAMP)

demo: setup
	$(BIN)/binpick demo

test: setup
	$(BIN)/python -m pytest -q

repro: setup
	$(BIN)/dvc repro

clean-runs:
	rm -rf runs mlflow.db mlartifacts .prefect
