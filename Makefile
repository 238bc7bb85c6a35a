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

setup: $(STAMP)

goaling: $(STAMP)
	$(VPY) -m hairexp experiment=goaling

test: $(STAMP)
	$(VPY) -m pytest

test-slow: $(STAMP)
	$(VPY) -m pytest -m slow

bench: $(STAMP)
	$(VPY) experiments/bench_free.py
	$(VPY) experiments/bench_tracking.py
	$(VPY) experiments/bench_collisions.py

paper-scenes: $(STAMP)
	$(VPY) experiments/paper_scenes.py

# every report under reports/ from fresh runs (about an hour on 2 cores; nothing is cached yet)
reports: bench paper-scenes
	$(VPY) experiments/bench_scale.py
	$(VPY) experiments/ablations.py
	$(VPY) experiments/stress.py
	$(VPY) experiments/baselines.py
	$(VPY) experiments/accuracy.py --scenes goaling celia --frames 30

clean:
	rm -rf $(VENV) outputs multirun
