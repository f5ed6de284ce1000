# The two commands of the README: `make run` and `make test`.
# Each creates .venv on first use (and again when pyproject.toml changes).

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
# Debian packages the tests need: Chromium (browser tests), poppler-utils
# (pdftotext/pdftoppm read the PDF reports), Pango (WeasyPrint), a font.
SYSTEM_PACKAGES := chromium poppler-utils libpango-1.0-0 libpangoft2-1.0-0 libharfbuzz0b libharfbuzz-subset0 libfontconfig1 libglib2.0-0 fonts-dejavu-core

.PHONY: run test lint system-deps bench clean

$(STAMP): pyproject.toml setup.py core/_blobs.pyx
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

## run: the web app with one worker and a demo clinician, rig and simulated patient
run: $(STAMP)
	$(BIN)/bradyscope serve --demo

## test: lint, type-check and the whole test suite (installs what it needs)
test: $(STAMP) system-deps
	$(BIN)/ruff check core app tests bench
	$(BIN)/ruff format --check core app tests bench
	$(BIN)/mypy
	$(BIN)/pytest -n 2 --timeout 600

## system-deps: install the Debian packages the tests need (when missing)
system-deps:
	@missing=$$(for p in $(SYSTEM_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing $$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

lint: $(STAMP)
	$(BIN)/ruff check core app tests bench
	$(BIN)/mypy

bench: $(STAMP)
	for b in bench/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
