# esr: the two set-up commands are `make demo` and `make test` (each installs first if needed).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# CUDA=1: also the `cuda` extra (jax's CUDA wheels) for NVIDIA GPUs (docs/performance.md).
CUDA   ?= 0
EXTRAS := test$(if $(filter 1,$(CUDA)),$(comma)cuda)
comma  := ,
STAMP  := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))
DEMO_SET := --budget quick --set train.epochs=40

.PHONY: install browser slurm demo test test-fast bench bench-phases bench-human sweep paper-figures report-store report report-check clean-venv
BUDGET   ?= paper
EXECUTOR ?= local

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[$(EXTRAS)]'
	# The 2019 Overcooked human trials ship inside overcooked-ai 1.1.0; only its data files are
	# used (their sha256 is checked on use), so its own requirements are skipped.
	$(BIN)/python -m pip install -q --no-deps overcooked-ai==1.1.0
	@touch $(STAMP)

# A small ESR run on the N = 2 gridworld (about 2 minutes on 2 CPU cores: the quick budget's 20
# warm-up epochs with a uniform robot, then 20 of ESR's policy), then its evaluation: prints
# the training artifact, the evaluation artifact, its GIF and its learning curve.
demo: install
	$(BIN)/esr train experiments/grid_2.yaml $(DEMO_SET)
	$(BIN)/esr eval experiments/grid_2.yaml $(DEMO_SET)

# The browser tests of `esr play` drive the system's headless Chromium and its driver
# (tests/play/test_play.py); on Debian or Ubuntu they are installed here when missing.
browser:
	@if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q chromium chromium-driver; \
	fi

# The SLURM tests (tests/recipes/test_slurm.py) start munged, slurmctld and slurmd on localhost; on Debian
# or Ubuntu they are installed here when missing. Never fatal: without them those tests skip.
slurm:
	@export PATH="$$PATH:/usr/sbin:/sbin"; \
	if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v sbatch >/dev/null \
	    || ! command -v munged >/dev/null; then \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  { $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends \
	      slurm-wlm munge; } >/dev/null 2>&1 \
	    || echo "make slurm: apt-get could not install slurm-wlm and munge; tests/recipes/test_slurm.py will skip"; \
	fi

# Compiling dominates the suite and XLA compiles on one thread: one worker per core (xdist).
# A module's tests go to one worker, so the trained runs its module fixtures share are made once.
test: install browser slurm
	$(BIN)/python -m pytest -n auto --dist loadscope

# The unit tests alone (tests marked slow left out): under 3 minutes on 2 cores.
test-fast: install
	$(BIN)/python -m pytest -n auto --dist loadscope -m "not slow"

# Train what the paper suite lacks (experiments/suites/paper.yaml), draw all eight figures and
# write the report into the store; prints the report's path. Re-running re-trains nothing.
# At BUDGET=smoke compiling dominates, so XLA skips its optimisation passes (docs/paper.md).
paper-figures: install
	$(if $(filter smoke,$(BUDGET)),XLA_FLAGS="$(XLA_FLAGS) --xla_backend_optimization_level=0") \
	$(BIN)/esr paper --budget $(BUDGET) --executor $(EXECUTOR)

bench: install
	$(BIN)/python benchmarks/bench.py

# Where one epoch's time goes: the gridworld paper configuration's epoch less each phase
# (docs/performance.md, "Where the time goes now").
bench-phases: install
	$(BIN)/python benchmarks/bench.py --phases --configs "gridworld grid_2 (paper)" --seeds 1 --epochs 3

# The PPO human's seconds per update on the three layouts (docs/overcooked.md, "Cost").
bench-human: install
	$(BIN)/python benchmarks/bench_human.py

# Every run of a suite that the store lacks (docs/cluster.md), e.g.
#   make sweep SUITE=experiments/suites/gridworld.yaml BUDGET=quick EXECUTOR=slurm
SUITE    ?= experiments/suites/gridworld.yaml
sweep: install
	$(BIN)/esr sweep $(SUITE) --budget $(BUDGET) --executor $(EXECUTOR)

# docs/reproduction.md and the generated tables in docs/ (`esr tables`) from the archived runs,
# exact checks, diagnoses, evaluations and human calibrations in evidence/ (imported into REPORT_STORE first; an import that is already
# there is skipped). report-check fails when any of them is not what the archives give.
REPORT_STORE ?= artifacts
DOCS_WITH_TABLES := $(filter-out docs/reproduction.md,$(wildcard docs/*.md))
report-store: install
	$(BIN)/esr --store $(REPORT_STORE) import $(wildcard evidence/runs/*.tar.gz)
	$(BIN)/esr --store $(REPORT_STORE) import --without-checkpoint $(wildcard evidence/records/*.tar.gz)
	$(if $(wildcard evidence/exact/*.tar.gz),$(BIN)/esr --store $(REPORT_STORE) import $(wildcard evidence/exact/*.tar.gz))
	$(if $(wildcard evidence/diagnoses/*.tar.gz),$(BIN)/esr --store $(REPORT_STORE) import $(wildcard evidence/diagnoses/*.tar.gz))
	$(if $(wildcard evidence/evals/*.tar.gz),$(BIN)/esr --store $(REPORT_STORE) import $(wildcard evidence/evals/*.tar.gz))
	$(if $(wildcard evidence/calibrations/*.tar.gz),$(BIN)/esr --store $(REPORT_STORE) import $(wildcard evidence/calibrations/*.tar.gz))

report: report-store
	$(BIN)/esr --store $(REPORT_STORE) paper --report --no-exact --out docs/reproduction.md
	$(BIN)/esr --store $(REPORT_STORE) tables $(DOCS_WITH_TABLES)

report-check: report-store
	$(BIN)/esr --store $(REPORT_STORE) paper --report --no-exact --check --out docs/reproduction.md
	$(BIN)/esr --store $(REPORT_STORE) tables --check $(DOCS_WITH_TABLES)

clean-venv:
	rm -rf $(VENV)
