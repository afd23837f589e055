# im_tuner workspace: one-command set-up, tests, demo and benchmarks.
#   make setup   create .venv from pinned requirements and install the three packages
#   make test    the whole test suite (unit + integration)
#   make test-unit  the pure tier only: no DDS graph, no child processes (under a minute)
#   make lint    ruff (lint + format check) over the tree, mypy over the pure modules
#   make demo    the main job: ros2 run im_tuner tuner (its default algorithm; ALGO=necga ...)
#   make bench   the benchmarks, printing their figures
#   make reproduction  the paper's study (full grid) + every algorithm beyond it -> docs/reproduction.md
#   make calibrate-bench  the `bench` realism profile's calibration -> docs/calibration.md
# Every target does the set-up it needs first; a re-run with nothing changed is quick.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PKGS   := src/im_drive_sim src/im_controller src/im_tuner
# Anything that changes what gets installed re-triggers the (fast, no-deps) package install.
PKG_FILES := $(shell find $(PKGS) -type f \( -name '*.py' -o -name '*.yaml' -o -name '*.xml' \
               -o -name '*.cfg' -o -path '*/scripts/*' -o -path '*/resource/*' \) -not -path '*/test/*' \
               -not -path '*/__pycache__/*' 2>/dev/null)

# ROS needs a writable log directory and the ament index of the venv.
export HOME ?= $(CURDIR)
export AMENT_PREFIX_PATH := $(abspath $(VENV))$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))
export PYTHONDONTWRITEBYTECODE := 1

.PHONY: test-parallel setup test test-unit lint format demo demo-drive bench reproduction calibrate-bench foxglove-check lock clean

setup: $(VENV)/.installed

$(PY):
	$(PYTHON) -m venv $(VENV)

$(VENV)/.deps: requirements.txt constraints.txt | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt -c constraints.txt
	touch $@

$(VENV)/.installed: $(VENV)/.deps $(PKG_FILES) tools/ros2 Makefile
	@# numba's cache knows only the file of each function: a fused kernel (bench/offline.py)
	@# would keep a stale copy of a changed kernel it calls. Compile afresh on reinstall.
	@find $(VENV)/lib -path '*/im_*/__pycache__/*.nb[ci]' -delete 2>/dev/null || true
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation \
	    --force-reinstall $(addprefix ./,$(PKGS))
	@# The ros2 command, bound to this venv's interpreter so it works without activation.
	@{ echo '#!$(abspath $(PY))'; tail -n +2 tools/ros2; } > $(VENV)/bin/ros2
	@chmod +x $(VENV)/bin/ros2
	@# Activation exports the ament index root (the ROS wheels do not).
	@grep -q 'AMENT_PREFIX_PATH' $(VENV)/bin/activate || \
	    printf '\n# im_tuner: ament index of this venv\nexport AMENT_PREFIX_PATH="$$VIRTUAL_ENV$${AMENT_PREFIX_PATH:+:$$AMENT_PREFIX_PATH}"\n' >> $(VENV)/bin/activate
	touch $@

test: setup
	$(PY) -m pytest

# The same suite in about two thirds of the time: two workers (pytest-xdist, a test file
# to a worker, the longest files first: conftest.py) for all but the tests that assert
# wall-clock timing, which then run alone (marked serial: another test beside them would
# be their load). Not yet CI's command: each parallel run here still found a test that
# assumed an idle machine (README).
test-parallel: setup
	$(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder -m 'not serial'
	$(PY) -m pytest -m serial

test-unit: setup
	$(PY) -m pytest -m unit

# Lint and types: ruff.toml and mypy.ini say what is checked and why.
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# Apply the formatter and the safe lint fixes.
format: setup
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

# The product: tune the simulated bench with the tuner's default algorithm (named in one
# place: im_tuner.optim.options.DEFAULT_ALGO); ALGO=necga|spsa|... picks another, ARGS=more options.
ALGO ?=
demo: setup
	$(VENV)/bin/ros2 run im_tuner tuner $(if $(ALGO),--algo $(ALGO)) $(ARGS)

# The simulated drive closed over DDS by the hand-tuned cascade (one experiment, a plot).
demo-drive: setup
	$(PY) tools/demo_drive.py

bench: setup
	$(PY) bench/run_all.py

# The `bench` realism profile's calibration (issue 29): the spread of repeated experiments
# and the paper's centre cells (Tables I-II) for `ideal` and `bench` at noise scales s,
# the fit -> docs/calibration.md (im_tuner.study.calibrate; ~5-10 min on 2 cores, niced).
calibrate-bench: setup
	nice -n 10 $(PY) -m im_tuner.study.calibrate --out docs/calibration.md $(ARGS)

# The paper's Tables I-III offline (issue 7): the full grid, then its write-up into docs/.
STUDY_OUT := bags/study_reproduction
# the paper's two (Tables I-III) and every algorithm beyond the paper (the comparison)
STUDY_ALGOS ?= spsa,necga,cga,pecga,rcga,cmaes,tpe,safe
reproduction: setup
	rm -rf $(STUDY_OUT)
	$(VENV)/bin/ros2 run im_tuner study --out $(STUDY_OUT) --algos $(STUDY_ALGOS) $(ARGS)
	mkdir -p docs/reproduction
	cp $(STUDY_OUT)/tables.png $(STUDY_OUT)/convergence.png $(STUDY_OUT)/comparison.png docs/reproduction/
	sed -e 's#](tables.png)#](reproduction/tables.png)#' \
	    -e 's#](convergence.png)#](reproduction/convergence.png)#' \
	    -e 's#](comparison.png)#](reproduction/comparison.png)#' \
	    $(STUDY_OUT)/reproduction.md > docs/reproduction.md

# Decode every message of a bag with Foxglove's own libraries (Node.js + npm; pinned in
# tools/foxglove-check/package-lock.json): make foxglove-check BAG=bags/<run>/bag_0
foxglove-check:
	@test -n "$(BAG)" || { echo 'usage: make foxglove-check BAG=<bag directory>'; exit 2; }
	cd tools/foxglove-check && npm ci --silent --no-audit --no-fund
	node tools/foxglove-check/check.mjs $(BAG)/*.mcap

# Re-resolve the pinned set after editing requirements.txt.
lock: | $(PY)
	$(PY) -m pip install --quiet -r requirements.txt
	{ echo '# Full resolved dependency set (pip freeze), used as constraints by `make setup`.'; \
	  $(PY) -m pip freeze --exclude-editable | grep -viE '^im[-_](drive[-_]sim|controller|tuner)( @|==)'; } > constraints.txt

clean:
	rm -rf $(VENV) build src/*/build src/*/*.egg-info
