# The two commands a new machine needs (see README):
#   make goaling   set up .venv and run the main job (python -m hairexp experiment=goaling)
#   make test      set up .venv and run the default test suite
PY      ?= python3
VENV    := .venv
VPY     := $(VENV)/bin/python
STAMP   := $(VENV)/.installed

.PHONY: setup goaling test test-slow bench paper-scenes reports clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip
	# torch first, with the exact CPU pin, so nothing else can pull a CUDA build
	$(VPY) -m pip install -q torch==2.13.0
	$(VPY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

# the package's bytecode: an editable install gets none from pip, and where PYTHONDONTWRITEBYTECODE
# is set (CI, containers) Python compiled its modules again at every launch (about 0.35 s);
# compileall skips the files whose bytecode is current
setup: $(STAMP)
	$(VPY) -m compileall -q hairexp experiments > /dev/null

goaling: setup
	$(VPY) -m hairexp experiment=goaling

# the default suite in TEST_WORKERS processes (pytest-xdist; auto: one per CPU; 0: in this process)
TEST_WORKERS ?= auto

test: setup
	$(VPY) -m pytest -n $(TEST_WORKERS)

test-slow: $(STAMP)
	$(VPY) -m pytest -m slow

# the scripts under experiments/ are modules of the experiments package, run from the repo root
bench: $(STAMP)
	$(VPY) -m experiments.bench_free
	$(VPY) -m experiments.bench_tracking
	$(VPY) -m experiments.bench_collisions
	$(VPY) -m experiments.bench_experiment

# CACHE=1: reuse cached results of the slow runs (paper scenes, stress, accuracy) whose config,
# solver source (hairexp/**/*.py, conf/**/*.yaml) and torch/numpy/scipy versions match, from
# reports/cache/ (git-ignored); the reports mark every cached row with its cache date and entry.
CACHE   ?=
CACHE_FLAG := $(if $(filter 1 yes true,$(CACHE)),--cache,)

paper-scenes: $(STAMP)
	$(VPY) -m experiments.paper_scenes $(CACHE_FLAG)

# every report under reports/ (about an hour on 2 cores).  By default every run is fresh (and
# refreshes its entry in reports/cache/); `make reports CACHE=1` reuses the paper scenes', stress
# cases' and accuracy runs' entries whose full key matches (benchmarks, scale, ablations and
# baselines always run fresh).
reports: bench paper-scenes
	$(VPY) -m experiments.bench_scale
	$(VPY) -m experiments.ablations
	$(VPY) -m experiments.ablations --full
	$(VPY) -m experiments.stress $(CACHE_FLAG)
	$(VPY) -m experiments.stress --set solver.integrator=bdf2 --report stress_bdf2 $(CACHE_FLAG)
	$(VPY) -m experiments.baselines
	$(VPY) -m experiments.assignment
	$(VPY) -m experiments.accuracy --scenes goaling celia --frames 30 $(CACHE_FLAG)
	$(VPY) -m experiments.fidelity_static
	$(VPY) -m experiments.fidelity
	$(VPY) -m experiments.integrators
	$(VPY) -m experiments.bench_memory

clean:
	rm -rf $(VENV) outputs multirun
