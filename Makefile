# The two commands of the README: `make run` and `make test`.
# Each creates .venv on first use (and again when pyproject.toml changes).

PYTHON ?= python3
HOST   ?= 127.0.0.1
PORT   ?= 8000
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
# Debian/Ubuntu packages, installed when missing (as root, or through sudo):
# - to build .venv (deps-build): the venv module, Python's headers and a C compiler
#   (core/_blobs.pyx, core/_geometry.pyx and core/_tracks.pyx are compiled with Cython), each only if $(PYTHON) lacks it;
# - to serve (deps-run): Pango, HarfBuzz, fontconfig and a font for the PDF reports (WeasyPrint);
# - to test (deps-test): Chromium (browser tests), poppler-utils (reading the PDF reports),
#   postgresql-client (pg_dump/pg_restore for the PostgreSQL backup round trip).
RUN_PACKAGES  := libpango-1.0-0 libpangoft2-1.0-0 libharfbuzz0b libharfbuzz-subset0 libfontconfig1 libglib2.0-0 fonts-dejavu-core
TEST_PACKAGES := chromium poppler-utils postgresql-client

# Installs the packages listed in the shell variable $$need (a no-op when it is empty).
APT_INSTALL = if [ -n "$$need" ]; then \
	  echo "installing Debian packages:$$need"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; \
	  elif command -v sudo >/dev/null 2>&1; then SUDO=sudo; \
	  else echo "install these Debian packages first (as root):$$need" >&2; exit 1; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$need; \
	fi

.PHONY: run test lint deps-build deps-run deps-test system-deps bench clean

$(STAMP): pyproject.toml setup.py core/_blobs.pyx core/_geometry.pyx core/_tracks.pyx | deps-build
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

## run: the web app with one worker and a demo clinician, rig and simulated patient
##      (make run PORT=8080 HOST=0.0.0.0 to listen elsewhere; Ctrl+C stops it)
run: deps-run $(STAMP)
	$(BIN)/bradyscope serve --demo --host $(HOST) --port $(PORT)

## test: lint, type-check and the whole test suite (installs what it needs)
test: deps-run deps-test $(STAMP)
	$(BIN)/ruff check core app tests bench
	$(BIN)/ruff format --check core app tests bench
	$(BIN)/mypy
	@# Bytecode is written even where PYTHONDONTWRITEBYTECODE is set: every server, worker and
	@# command the tests start would otherwise compile app/ and core/ again (0.3-0.8 s each).
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -n 2 --timeout 600 --durations=40

## deps-build: what creating .venv needs, if $(PYTHON) lacks it
deps-build:
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { \
	  echo "bradyscope needs Python 3.11 or newer; $(PYTHON) is $$($(PYTHON) --version 2>&1)." \
	       "Give another one: make run PYTHON=python3.12" >&2; exit 1; }
	@need=""; \
	$(PYTHON) -c 'import ensurepip, venv' 2>/dev/null || need="$$need python3-venv"; \
	$(PYTHON) -c 'import os, sys, sysconfig; sys.exit(not os.path.isfile(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' || need="$$need python3-dev"; \
	command -v cc >/dev/null 2>&1 || need="$$need gcc libc6-dev"; \
	$(APT_INSTALL)

## deps-run: the libraries the PDF reports need (when missing)
deps-run:
	@need=$$(for p in $(RUN_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || printf ' %s' $$p; done); \
	$(APT_INSTALL)

## deps-test: what the tests need besides (when missing)
deps-test:
	@need=$$(for p in $(TEST_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || printf ' %s' $$p; done); \
	$(APT_INSTALL)

system-deps: deps-build deps-run deps-test

lint: $(STAMP)
	$(BIN)/ruff check core app tests bench
	$(BIN)/mypy

bench: $(STAMP)
	for b in bench/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
