# Quick start: `make demo` (set up and run the main job), `make test` (set up and run the suite).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint format build clean bytecode analyses-campaign validate-physics-dt bit-for-bit

$(STAMP): pyproject.toml constraints.txt
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# the versions the committed results were made with (constraints.txt)
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	# compile the reach check once now (Numba caches it beside the module)
	$(BIN)/python -c 'from payload.envelope.overlap import compile_check; compile_check()'
	touch $(STAMP)

# the workbench's bytecode, brought up to date (where PYTHONDONTWRITEBYTECODE is set, as in
# many containers and on the development machine, Python writes none: every process
# compiled the workbench modules it imports again: a trial's hundred, about 0.15 s)
bytecode: $(STAMP)
	$(BIN)/python -m compileall -q -j 0 payload

demo: $(STAMP) bytecode
	$(BIN)/payload build
	$(BIN)/payload summary
	$(BIN)/payload report envelope
	$(BIN)/payload report reach --samples 100000
	$(BIN)/payload trials run --n 10 --seed 0 --out runs/campaign-$$(date +%Y%m%d-%H%M%S)

# the committed campaign results (analyses/campaign/<name>/): the paper's experiment per CTB
# model with the paper's controller, and the single bag with the converged budget, with
# self-collision modelled, with the safe controller profile (contact-aware self-collision
# and the base safety filter) and with it over a 1 s delayed ground link. The full runs (recordings included) stay in
# runs/analyses-<name>/.
CAMPAIGNS := single:--ctb=single rigid:--ctb=rigid single-converged:--ctb=single:--retarget-budget=converged single-collisions:--ctb=single:--retarget-collisions single-safe:--ctb=single:--controller=safe single-safe-delay1s:--ctb=single:--controller=safe:--link-delay=1.0
analyses-campaign: $(STAMP)
	set -e; for spec in $(CAMPAIGNS); do \
	  name=$${spec%%:*}; args=$$(echo $${spec#*:} | tr ':' ' '); \
	  $(BIN)/payload trials run --n 10 --seed 0 --workers 2 $$args --out runs/analyses-$$name --force; \
	done
	# copied once every campaign has run: each ran on the tree as committed (git_dirty false)
	set -e; for spec in $(CAMPAIGNS); do \
	  name=$${spec%%:*}; \
	  mkdir -p analyses/campaign/$$name; \
	  cp runs/analyses-$$name/summary.md runs/analyses-$$name/summary.json analyses/campaign/$$name/; \
	  for f in ctb_body_frame route; do \
	    cp runs/analyses-$$name/trial-0000/fig_$$f.png analyses/campaign/$$name/trial-0000_$$f.png; \
	  done; \
	  if [ -f runs/analyses-$$name/fig_campaign.png ]; then \
	    cp runs/analyses-$$name/fig_campaign.png analyses/campaign/$$name/; fi; \
	done

# the opt-in 2 ms physics step against the paper's 1 kHz: the `single` campaign at both
# steps, compared seed by seed with the largest change of each metric
# (analyses/physics-dt/compare.md; docs/speed.md)
# (the 1 ms run is the committed `single` campaign's, runs/analyses-single, when present)
validate-physics-dt: $(STAMP)
	test -f runs/analyses-single/summary.json || $(BIN)/payload trials run --n 10 --seed 0 \
	  --workers 2 --ctb single --out runs/analyses-single --force
	$(BIN)/payload trials run --n 10 --seed 0 --workers 2 --ctb single --physics-dt 0.002 --out runs/physics-dt-2ms --force
	mkdir -p analyses/physics-dt
	$(BIN)/payload trials compare runs/analyses-single runs/physics-dt-2ms --out analyses/physics-dt/compare.md --force

# speed work's "the maths is unchanged" check: full trials of seeds 0, 5 and 9 on the
# commit BASE (default main, in a temporary worktree) and on this tree, every recorded
# step compared bit for bit (exit 1 on any difference; docs/speed.md)
BASE ?= main
BFB := runs/bit-for-bit
bit-for-bit: $(STAMP)
	rm -rf $(BFB) && mkdir -p $(BFB)
	git worktree add --detach $(BFB)/base $(BASE)
	set -e; for s in 0 5 9; do d=trial-$$(printf %04d $$s); \
	  (cd $(BFB)/base && PYTHONPATH=$$PWD $(CURDIR)/$(BIN)/payload trial --seed $$s \
	    --out $(CURDIR)/$(BFB)/before/$$d --json > /dev/null); \
	  $(BIN)/payload trial --seed $$s --out $(BFB)/after/$$d --json > /dev/null; \
	done
	git worktree remove --force $(BFB)/base
	$(BIN)/payload trials compare $(BFB)/before $(BFB)/after --require-identical

# the WebXR emulator the browser tests load (iwer), pinned by package-lock.json
node_modules/.package-lock.json: package-lock.json
	npm ci --no-audit --no-fund --loglevel=error

test: $(STAMP) bytecode node_modules/.package-lock.json
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	cache=$$(mktemp -d) && trap 'rm -rf "$$cache"' EXIT && \
	PAYLOAD_TEST_CACHE_DIR=$$cache $(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not serial" && \
	PAYLOAD_TEST_CACHE_DIR=$$cache $(BIN)/python -m pytest -q -n 2 --dist loadgroup -m serial

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
