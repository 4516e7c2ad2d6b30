# Two commands do everything on a fresh machine: `make process` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
CAMPAIGN ?= pipeline/demo/campaign.toml
OUT     ?= out/demo
JOBS    ?= 2

.PHONY: setup process test bench golden lint clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

process: $(STAMP)
	$(BIN)/magalign process $(CAMPAIGN) --out $(OUT) --jobs $(JOBS)

test: $(STAMP)
	$(BIN)/ruff check pipeline stages tests bench
	$(BIN)/python -m pytest -q -x -p no:cacheprovider tests

bench: $(STAMP)
	@for b in bench/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

golden: $(STAMP)
	$(BIN)/python tests/make_golden.py

lint: $(STAMP)
	$(BIN)/ruff check pipeline stages tests bench

clean:
	rm -rf out build *.egg-info
