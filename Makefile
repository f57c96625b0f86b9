# Quick start: `make demo` (set up and run the main job), `make test` (set up and run the suite).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint format build clean

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/payload build
	$(BIN)/payload summary
	$(BIN)/payload report envelope
	$(BIN)/payload report reach --samples 100000
	$(BIN)/payload trials run --n 10 --seed 0 --out runs/campaign-$$(date +%Y%m%d-%H%M%S)

# the WebXR emulator the browser tests load (iwer), pinned by package-lock.json
node_modules/.package-lock.json: package-lock.json
	npm ci --no-audit --no-fund --loglevel=error

test: $(STAMP) node_modules/.package-lock.json
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

build: $(STAMP)
	$(BIN)/payload build

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
