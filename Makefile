# The README's commands. Each creates .venv/ if missing and installs what it needs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo bench goldens validation realism venv clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,dask,bench]'
	touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest

demo: $(STAMP)
	$(BIN)/spmc run configs/caseB.yaml --overwrite

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py

goldens: $(STAMP)
	$(BIN)/python -m stereopose_mc.regression refresh

validation: $(STAMP)
	$(BIN)/python docs/make_validation.py

realism: $(STAMP)
	$(BIN)/python docs/make_realism.py

clean:
	rm -rf $(VENV) build *.egg-info
