# physgrad: `make run` sets up and runs the default experiment, `make test` sets up and runs the tests.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run lint test test-long test-cluster test-fast test-faults coverage bench check-stability reproduce-figures clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,launchers,trackers,sims]"
	touch $(STAMP)

# the README's first command: a small tuned comparison (the toy scene, Adam / Gauss-Newton / HIG, each
# tuned with 8 trials in each of 4 tuning studies over the toy's ranges (conf/tuning/toy_*.yaml), 10 paired
# seeds each; about four minutes on 2 cores); ARGS replaces the study's overrides
RUN_STUDY := task=toy optim=adam,gauss_newton,hig trainer.iterations=300 compare.trials=8
run: setup
	$(BIN)/physgrad compare $(if $(ARGS),$(ARGS),$(RUN_STUDY))

# the tests stand in four layers, each a folder that runs alone (.venv/bin/python -m pytest tests/unit):
# unit (pure functions), numerics (closed forms, finite differences, loop against scan), integration
# (run_experiment at tiny sizes), e2e (the console script); make test runs all four in parallel
# processes (pytest-xdist, one per core up to 4; PYTEST_WORKERS=0 runs them in one process) and prints
# its wall and CPU time (user + sys of every process it started)
LAYERS := tests/unit tests/numerics tests/integration tests/e2e
PYTEST_WORKERS ?= auto
XDIST := $(if $(filter 0,$(PYTEST_WORKERS)),-p no:xdist,-n $(PYTEST_WORKERS) --maxprocesses=4)
SHELL := /bin/bash
TIMED = TIMEFORMAT="$@: %R s wall, %U s user + %S s sys CPU"; time
# ruff first (100 columns; pyproject.toml): a lint or layout finding fails the tests in seconds
LINTED := physgrad hydra_plugins tests experiments examples
lint: setup
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)

# make test and make test-fast compile the tests' programs without LLVM's optimisation passes (XLA's backend
# level 0, in every process they start): the same operations in the same order, compiled in about 30% less
# time, which is most of a test at tiny sizes (docs/testing.md). The long checks train
# for longer, where the unoptimised code costs more than it saves (a third slower steps): they keep XLA's
# default, as users' runs and make bench do
FAST_COMPILE := XLA_FLAGS="$(XLA_FLAGS) --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
test: lint
	$(TIMED) $(FAST_COMPILE) $(BIN)/python -m pytest -q $(XDIST) --durations=12 -m "not long and not cluster" $(LAYERS)

# the long checks (numerics through whole solvers, end-to-end studies, the full scene x optim matrix, the small
# stability suite); CI runs them after make test, in parallel processes as make test (about 17 minutes with 2
# on a 2-core machine; docs/testing.md). The scene x optim matrix trains two iterations a pair: compiling is all of it, so it
# compiles as make test does; the rest trains for longer, at XLA's default
MATRIX := tests/integration/test_configs.py::test_pair_runs_two_iterations_or_is_refused
test-long: setup
	$(TIMED) $(FAST_COMPILE) $(BIN)/python -m pytest -q $(XDIST) -m long $(MATRIX)
	$(TIMED) $(BIN)/python -m pytest -q $(XDIST) -m long $(LAYERS) --deselect $(MATRIX)

# studies on a real two-node SLURM cluster on this machine with faults injected (scancel, a time limit,
# SIGKILL of the launching command, a node lost): as root on Debian, installs SLURM, munge, slurmdbd and MariaDB from Debian's packages
# where missing, starts the daemons by hand and stops them at the end (tests/cluster/slurm.sh; docs/cluster.md)
SLURM_STATE ?= /tmp/physgrad-slurm
test-cluster: setup
	PHYSGRAD_SLURM_STATE=$(SLURM_STATE) bash tests/cluster/slurm.sh start
	SLURM_CONF=$(SLURM_STATE)/slurm.conf $(BIN)/python -m pytest -q -m cluster tests/cluster; \
		status=$$?; PHYSGRAD_SLURM_STATE=$(SLURM_STATE) bash tests/cluster/slurm.sh stop; exit $$status

# the fault-injection suite repeated many times (every randomised fault x REPEATS; 4 minutes at REPEATS=2 on 2
# cores, the randomised cases growing linearly with it) and the crafted foreign files
REPEATS ?= 20
test-faults: setup
	PHYSGRAD_FAULT_REPEATS=$(REPEATS) $(BIN)/python -m pytest -q tests/*/test_faults.py tests/*/test_foreign.py \
		tests/e2e/test_compare.py::test_a_study_stopped_at_random_instants_resumes_to_the_same_trials

# the layers that start no run: seconds to a minute
test-fast: setup
	$(TIMED) $(FAST_COMPILE) $(BIN)/python -m pytest -q $(XDIST) -m "not long and not cluster" tests/unit tests/numerics

# the line coverage of physgrad/ over make test and make test-long (one run under coverage.py, subprocesses
# included; about twice as long as the two)
coverage: setup
	rm -f .coverage .coverage.*
	$(TIMED) $(BIN)/coverage run -m pytest -q $(XDIST) -m "not cluster" $(LAYERS)
	$(BIN)/coverage combine -q
	$(BIN)/coverage report

# step time, compile time and peak memory per scene x variant, with floors; writes outputs/bench/benchmarks.md
bench: setup
	$(BIN)/python -m physgrad.bench $(ARGS)

# stiff and extreme cases (physgrad check; ARGS=--small for the CI form); writes outputs/check/check.md
check-stability: setup
	$(BIN)/physgrad check $(ARGS)

# every figure sweep of conf/experiment/, then outputs/figures/summary.md; PROFILE=paper for the papers' budgets;
# PROFILE=claims: the papers' claims as physgrad compare studies (outputs/figures/claims.md), in parts
# (ARGS=--plan lists them and the expected time, ARGS="--part K" runs one); PROFILE=claims-long runs the claims
# that turned with the budget four times as long; PROFILE=claims-gpu the claims that need a GPU's budgets;
# PROFILE=claims-paper the papers' own settings, untuned, at the papers' budgets
PROFILE ?= quick
reproduce-figures: setup
	$(BIN)/python experiments/reproduce.py --profile $(PROFILE) $(if $(OVERWRITE),--overwrite,) $(ARGS)

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
