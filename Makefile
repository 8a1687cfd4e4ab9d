# Quick start:  make demo   (set up everything, then run the main job on the demo campaign)
#               make test   (set up everything, then run the test suite)
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench photos

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fivecal demo

PHOTOS := tests/photos/cache/dualCircles.jpg

$(PHOTOS): | $(STAMP)
	$(VENV)/bin/python tests/photos/fetch.py

photos: $(PHOTOS)

test: $(STAMP) $(PHOTOS)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest -n 2

bench: $(STAMP)
	$(VENV)/bin/python bench/bench_kinematics.py
	$(VENV)/bin/python bench/bench_render.py
	$(VENV)/bin/python bench/bench_identification.py
	$(VENV)/bin/python bench/bench_smoothing.py
	$(VENV)/bin/python bench/bench_formulations.py
	$(VENV)/bin/python bench/bench_dask_ingest.py
	$(VENV)/bin/python bench/bench_memory.py
