# The README's commands. Each creates .venv/ if missing and installs what it needs,
# at the versions pinned in constraints.txt (the golden percentile tables depend on them).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo bench goldens validation venv clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,dask,bench]'
	touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest

demo: $(STAMP)
	$(BIN)/spmc run configs/caseB.yaml --overwrite

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py

goldens: $(STAMP)
	$(BIN)/python -m stereopose_mc.outputs.goldens refresh

validation: $(STAMP)
	$(BIN)/python docs/make_validation.py

clean:
	rm -rf $(VENV) build *.egg-info
