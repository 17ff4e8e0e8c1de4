# Two commands set everything up on a fresh machine with only Python 3.11:
#   make demo   - lc-experiment --preset quick: the zoo's policies on held-out episodes next to the
#                 paper's tables and their sealed test figures from the ledger, a quick recipe trained from
#                 scratch, a recorded episode to view; then lc-bench: the shipped Hybrid-PPO and roads-ppo
#                 (trained on every road of the suite) on each road of the suite (validation episodes)
#   make test   - run the test suite
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
TORCH  := torch==2.13.0
DEMO_OUT ?= runs/demo

.PHONY: demo test lint bench protos clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# The pinned CPU wheel first: an unpinned torch would pull several GB of CUDA packages.
	$(BIN)/python -m pip install --quiet $(TORCH)
	$(BIN)/python -m pip install --quiet -e ".[dev,ray,sumo]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lc-experiment --preset quick --jobs 2 --out $(DEMO_OUT)
	@sed -n '/^## Table III/,/^## Every row/p' $(DEMO_OUT)/REPORT.md | grep -v '^## Every row'
	@echo "make demo: the report is $(DEMO_OUT)/REPORT.md (figures next to it); rerun to resume or refresh it"
	@echo "make demo: recorded episodes of the best shipped policy: $(DEMO_OUT)/showcase/ (lc-view $(DEMO_OUT)/showcase/*.rrd)"
	$(BIN)/lc-bench zoo:hybrid-ppo zoo:roads-ppo --episodes 30 --workers 2 --out $(DEMO_OUT)/bench -q > $(DEMO_OUT)/bench.log
	@sed -n '/^| scenario | driver/,/^$$/p;/^| driver | mean/,/^$$/p' $(DEMO_OUT)/bench/BENCH.md
	@echo "make demo: the suite table on 30 validation episodes per road is $(DEMO_OUT)/bench/BENCH.md; sealed test figures: lc-bench zoo:hybrid-ppo zoo:roads-ppo --final"

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q

lint: $(STAMP)
	$(BIN)/ruff check lcsim lcdata lcmodels lccli tools tests experiments

bench: $(STAMP)
	$(BIN)/python tools/bench_sim.py

protos: $(STAMP)
	$(BIN)/python tools/gen_protos.py

clean:
	rm -rf $(VENV) .pytest_cache
