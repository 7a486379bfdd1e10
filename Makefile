# densityloop: `make help` lists the targets.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.DEFAULT_GOAL := help
.PHONY: help install test test-slow test-slurm lint format docs bench reproduce picture sweeps clean \
	benchmark benchmark-quick

help: ## List the targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; {printf "  %-12s %s\n", $$1, $$2}'
	@echo "  sweep-NAME   One study, its figures and its page; NAME in: $(STUDIES) $(EXTRA_STUDIES) distributed_frontier"

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) ## Create .venv and install the project with its dev tools

# the tests on every core, at most 4 processes (pytest-xdist; tests/conftest.py gives each
# worker its share of the cores for the compiled loops); PYTEST_WORKERS= runs them serially
PYTEST_WORKERS ?= --numprocesses=auto --maxprocesses=4 --durations=20

test: $(STAMP) ## Static checks (ruff, mypy), the documentation build and the tests (not the slow ones)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy
	$(MAKE) --no-print-directory docs
	scripts/viewer_deps.sh  # chromium and viewer/node_modules for tests/test_viewer.py; never fails
	$(PY) -m pytest $(PYTEST_WORKERS)

test-slow: $(STAMP) ## Run only the slow tests
	$(PY) -m pytest -m slow -rP

test-slurm: $(STAMP) ## Two-job SLURM sweep on a private one-node cluster (root; installs slurm-wlm, munge)
	PY=$(abspath $(PY)) scripts/test_slurm.sh

lint: $(STAMP) ## Static checks only: ruff (lint, format) and mypy
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

format: $(STAMP) ## Format the code with ruff
	$(PY) -m ruff format .
	$(PY) -m ruff check --fix .

DOCS_DIR := build/docs/html

# a fresh environment (-E) every time: Sphinx re-emits a page's warnings only when it
# re-reads the page, and autodoc's pages change with the code, which it does not track
docs: $(STAMP) ## Build the documentation site into build/docs/html (warnings are errors)
	$(PY) -m sphinx -b html -E -n -W --keep-going -q docs $(DOCS_DIR)
	@echo "docs: $(DOCS_DIR)/index.html"

BENCHMARKS := "benchmarks.suite" "benchmarks.numerics" "benchmarks.distributed --app" "benchmarks.jobs" \
	"benchmarks.laws" "benchmarks.robots"
BENCH_FIGURES := build/bench/figures.jsonl

# every benchmark runs and the page is written even when a target is missed; the exit
# status says whether every benchmark exited 0
bench: $(STAMP) ## Speed benchmarks, each figure against its target; writes docs/performance.md (about 15 min on 2 cores)
	@mkdir -p $(dir $(BENCH_FIGURES)) && rm -f $(BENCH_FIGURES)
	@status=0; \
	for b in $(BENCHMARKS); do \
		echo "== python -m $$b"; \
		DENSITYLOOP_BENCH_FIGURES=$(BENCH_FIGURES) $(PY) -m $$b || status=1; \
	done; \
	$(PY) -m benchmarks.report $(BENCH_FIGURES) --out docs/performance.md || status=1; \
	exit $$status

RUN_DIR := outputs/reproduce

reproduce: $(STAMP) ## Run the paper's experiment (100 s, N = 1024) and write its figures to figures/
	rm -rf $(RUN_DIR) $(RUN_DIR)_meanfield  # a run never overwrites a log: start afresh
	$(PY) -m experiments.closed_loop hydra.run.dir=$(RUN_DIR)
	$(PY) -m analysis.figures $(RUN_DIR) --out figures
	$(PY) -m experiments.closed_loop plant=meanfield estimator=exact log.field_every=100 \
		hydra.run.dir=$(RUN_DIR)_meanfield
	$(PY) -m analysis.figures $(RUN_DIR)_meanfield --out figures/meanfield --no-gif
	@echo "log: $(RUN_DIR)/run.mcap"
	@echo "figures:"; ls -1 figures/* figures/meanfield/*

PICTURE_RUN := outputs/rooms_picture

picture: $(STAMP) ## The README's picture: the paper's law in the rooms at 30 s (docs/rooms.png, about 1 min)
	rm -rf $(PICTURE_RUN)  # a run never overwrites a log: start afresh
	$(PY) -m experiments.closed_loop domain=rooms init=left_room sim.t_final=30 \
		log.field_every=100 log.positions_every=50 log.progress=off hydra.run.dir=$(PICTURE_RUN)
	$(PY) -m analysis.swarm_picture $(PICTURE_RUN) --at 30 --out docs/rooms.png

STUDIES := laws_n laws_iss heat_floor laws_noise robots link conv_grid conv_sigma conv_alpha \
	agents_n
# run alone (make sweep-NAME), beyond the sweeps' 30-minute budget: distributed_r
# (decentralised loop against the communication radius, 28 min on 2 cores),
# conv_grid_agents (grid refinement at the agent level, about 10 min), iss_gain (the
# paper's and the heat law's gain under smooth errors from the paper's start; the smooth
# panel of laws_iss measures the same from p_*), debias_n (the paper's loop against the
# debiased loop up to N = 16384, about 12 min) and domains (every law on the rooms and
# the obstacles, N = 1024 and 4096, three seeds, 60 s: 49 min on 2 cores)
EXTRA_STUDIES := distributed_r conv_grid_agents iss_gain debias_n domains
# distributed_frontier (the decentralised designs against the radius and the rounds, with
# the centralised loop they are measured against; about 45 min on 2 cores) has a rule of
# its own below

sweeps: $(STAMP) ## Run the study presets (about 30 min on 2 cores); figures/sweeps/ and docs/studies/
	@for s in $(STUDIES); do \
		echo "== $$s"; \
		$(PY) -m experiments.closed_loop +experiment=$$s hydra.sweep.dir=multirun/$$s || exit 1; \
		$(PY) -m analysis.sweep multirun/$$s --out figures/sweeps/$$s || exit 1; \
		$(PY) -m analysis.study_pages $$s || exit 1; \
	done
	@echo "figures:"; ls -1 figures/sweeps/*/*.png

$(addprefix sweep-,$(STUDIES) $(EXTRA_STUDIES)): sweep-%: $(STAMP)
	$(PY) -m experiments.closed_loop +experiment=$* hydra.sweep.dir=multirun/$*
	$(PY) -m analysis.sweep multirun/$* --out figures/sweeps/$*
	$(PY) -m analysis.study_pages $*

sweep-distributed_frontier: $(STAMP)
	test -f multirun/distributed_frontier_centralised/run.mcap || \
		$(PY) -m experiments.closed_loop +experiment=distributed_frontier_centralised
	$(PY) -m experiments.closed_loop +experiment=distributed_frontier \
		hydra.sweep.dir=multirun/distributed_frontier
	$(PY) -m experiments.closed_loop +experiment=distributed_frontier \
		hydra.sweep.dir=multirun/distributed_frontier '+design=band,command_band' \
		estimator.radius=null estimator.k_nearest=6 estimator.rounds=10 estimator.band_limit=2.0
	$(PY) -m analysis.sweep multirun/distributed_frontier --out figures/sweeps/distributed_frontier
	$(PY) -m analysis.study_pages distributed_frontier

# the benchmark's runs go through the Hydra launcher these overrides choose: joblib on
# every core by default; e.g. LAUNCHER="hydra/launcher=slurm hydra.launcher.partition=P" on SLURM
LAUNCHER ?=
BENCHMARK_ARGS = $(foreach o,$(LAUNCHER),--launcher $(o))

benchmark-quick: $(STAMP) ## Every law tuned on paper, ring and two_groups, small budget; writes docs/benchmark.md (about 35 min on 2 cores)
	$(PY) -m experiments.benchmark --tier quick --out outputs/benchmark/quick \
		--page docs/benchmark.md --command "make benchmark-quick" $(BENCHMARK_ARGS)

benchmark: $(STAMP) ## Every law tuned on every scenario, verdicts on 8 fresh seeds (hours; LAUNCHER=hydra/launcher=slurm on a cluster)
	$(PY) -m experiments.benchmark --tier full --out outputs/benchmark/full \
		--page docs/benchmark.md --command "make benchmark" $(BENCHMARK_ARGS)

clean: ## Remove outputs, figures and the built documentation (keeps .venv)
	rm -rf outputs multirun figures build/docs build/bench .pytest_cache .ruff_cache
