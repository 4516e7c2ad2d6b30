# Two commands do everything on a fresh machine: `make process` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
CAMPAIGN ?= pipeline/demo/campaign.toml
OUT     ?= out/demo
JOBS    ?= 2
FRESH   ?= /tmp/magalign-fresh

.PHONY: setup process test test-fresh bench golden lint typecheck clean chromium

# The program's bytecode, written ahead: where PYTHONDONTWRITEBYTECODE is set, every command
# (and the suite starts hundreds) would otherwise compile the modules it imports anew.
# Files already compiled and unchanged are skipped.
COMPILE = $(BIN)/python -m compileall -q pipeline stages

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

process: $(STAMP)
	$(COMPILE)
	$(BIN)/magalign process $(CAMPAIGN) --out $(OUT) --jobs $(JOBS)

# Headless Chromium for tests/test_browser.py: Debian's package, installed when apt-get can
# run as root; never fails the build (the browser test is then skipped, saying why).
chromium:
	@if command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; then \
	  :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	  echo "installing chromium (apt-get) for the browser test"; \
	  apt-get install -y -q chromium >/dev/null 2>&1 \
	  || (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1) \
	  || echo "chromium could not be installed: the browser test will be skipped"; \
	else \
	  echo "no chromium (apt-get missing or not root): the browser test will be skipped"; \
	fi

# The suite on one pytest-xdist worker per core (at most 4: each may hold a real recording's
# diagnosis), a file to a worker, the longest files first (tests/conftest.py); the 25
# longest tests are listed at the end, so every run records where its time went.
test: $(STAMP) chromium
	$(COMPILE)
	$(BIN)/ruff check pipeline stages tests bench
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -x -p no:cacheprovider -n auto --maxprocesses 4 --dist loadfile --durations=25 tests

# The committed HEAD cloned afresh into $(FRESH), each clone in a fresh venv, tested twice:
# with the newest dependencies pyproject.toml allows and with the oldest (the lowest release
# series of every >= bound, tests/oldest_deps.py). See docs/testing.md.
test-fresh:
	rm -rf $(FRESH) && mkdir -p $(FRESH)
	if [ -d ../shared ]; then ln -s "$(abspath ../shared)" $(FRESH)/shared; fi
	set -e; for deps in newest oldest; do \
	  git clone -q . $(FRESH)/$$deps; \
	  cd $(FRESH)/$$deps; \
	  $(PY) -m venv .venv; \
	  .venv/bin/pip install --quiet --upgrade pip; \
	  if [ $$deps = oldest ]; then \
	    .venv/bin/python tests/oldest_deps.py pyproject.toml > constraints.txt; \
	    .venv/bin/pip install --quiet -c constraints.txt -e '.[dev]'; \
	  else \
	    .venv/bin/pip install --quiet --upgrade --upgrade-strategy eager -e '.[dev]'; \
	  fi; \
	  .venv/bin/pip freeze > $(FRESH)/$$deps.freeze.txt; \
	  touch .venv/.installed; \
	  echo "== make test with the $$deps dependencies"; \
	  $(MAKE) test; \
	  cd $(CURDIR); \
	done

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

golden: $(STAMP)
	$(BIN)/python tests/make_golden.py

lint: $(STAMP)
	$(BIN)/ruff check pipeline stages tests bench

# mypy on every module of pipeline/, stages/ and schemas/ (pyproject.toml, [tool.mypy]);
# `make test` runs it after ruff. See docs/testing.md.
typecheck: $(STAMP)
	$(BIN)/mypy

clean:
	rm -rf out build *.egg-info
