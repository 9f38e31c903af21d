# The README's commands. Each creates .venv/ if missing and installs what it needs,
# at the versions pinned in constraints.txt (the golden percentile tables depend on them).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo bench goldens validation realism filters-doc sensitivity-doc images-doc images-campaign venv clean screenshots

# OpenBLAS picks its kernels by CPU, and their round-off can move a trial on the edge of a rule: the golden tables'
# inconsistent counts of cases C, D and F move by one between its Haswell and SkylakeX kernels. The tests, the
# goldens and the generated docs run on the Haswell kernels (those the goldens were made with) wherever the CPU has
# them (AVX2 and FMA), unless OPENBLAS_CORETYPE is set; `spmc` and `make demo` / `make bench` keep OpenBLAS's choice.
PINNED_BLAS := $(if $(OPENBLAS_CORETYPE),,$(shell grep -qw avx2 /proc/cpuinfo 2>/dev/null && grep -qw fma /proc/cpuinfo 2>/dev/null && echo OPENBLAS_CORETYPE=Haswell))

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,dask,bench]'
	$(BIN)/python -m compileall -q stereopose_mc  # bytecode an editable install leaves out (PYTHONDONTWRITEBYTECODE: never written)
	$(BIN)/python -m stereopose_mc.mc.warm  # Numba's cache of the kernels: the first run loads, not compiles
	touch $(STAMP)

venv: $(STAMP)

# The suite runs on every core available (pytest-xdist, one worker per core, a test module's tests on one worker so
# its module fixtures run once); PYTEST_JOBS= runs it in one process (a single test, a debugger).
PYTEST_JOBS ?= -n auto --dist loadscope

test: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python -m pytest $(PYTEST_JOBS) $(PYTEST_ARGS)

demo: $(STAMP)
	$(BIN)/spmc run configs/caseB.yaml --overwrite

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py

goldens: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python -m stereopose_mc.outputs.goldens refresh

# Screenshots of the demo report in headless Chromium (Debian: apt-get install chromium), into
# runs/screenshots/: report-top.png (the first screen) and report-full.png (a long page). Look at them.
CHROMIUM ?= chromium
CHROMIUM_FLAGS := --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
	--disable-background-networking --disable-component-update --disable-sync --hide-scrollbars
screenshots: $(STAMP)
	@command -v $(CHROMIUM) >/dev/null || { echo "needs Chromium: apt-get install chromium (or CHROMIUM=...)"; exit 2; }
	test -f runs/caseB/trials.parquet || $(BIN)/spmc run configs/caseB.yaml --overwrite --quiet --no-report
	$(BIN)/spmc report runs/caseB
	mkdir -p runs/screenshots
	$(CHROMIUM) $(CHROMIUM_FLAGS) --user-data-dir=$$(mktemp -d) --window-size=1400,1000 \
		--screenshot=$(CURDIR)/runs/screenshots/report-top.png file://$(CURDIR)/runs/caseB/report.html
	$(CHROMIUM) $(CHROMIUM_FLAGS) --user-data-dir=$$(mktemp -d) --window-size=1400,7000 \
		--screenshot=$(CURDIR)/runs/screenshots/report-full.png file://$(CURDIR)/runs/caseB/report.html
	@echo "-> runs/screenshots/report-top.png, runs/screenshots/report-full.png"

validation: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_validation.py

realism: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_realism.py

# docs/images.md's detector comparison and example frames (about two minutes)
images-doc: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_images.py

# docs/images.md's campaign table: configs/caseB-images.yaml (100 trials) beside its point-model twin (~15 min)
images-campaign: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_images_campaign.py

# docs/filters.md's comparison tables: case-B campaigns (about 30 s), spliced between the doc's markers
filters-doc: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_filters.py

# docs/sensitivity.md's mission example: configs/mission-debris.yaml, 500 trials, and its report (about 20 s)
sensitivity-doc: $(STAMP)
	$(PINNED_BLAS) $(BIN)/python docs/make_sensitivity.py

clean:
	rm -rf $(VENV) build *.egg-info
