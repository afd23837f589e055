# im_tuner workspace: one-command set-up, tests, demo and benchmarks.
#   make setup   create .venv from pinned requirements and install the three packages
#   make test    the whole test suite (unit + integration)
#   make test-unit  the pure tier only: no DDS graph, no child processes (about a minute)
#   make lint    ruff (lint + format check) over the tree, mypy over the pure modules
#   make demo    the main job: ros2 run im_tuner tuner (its default algorithm; ALGO=necga ...)
#   make bench   the benchmarks, printing their figures
#   make reproduction  the paper's study (full grid) + every algorithm beyond it, on `ideal` and
#                      `bench`, and the study over drives -> docs/reproduction*.md
#   make calibrate-bench  the `bench` realism profile's calibration -> docs/calibration.md
# Every target does the set-up it needs first; a re-run with nothing changed is quick.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PKGS   := src/im_drive_sim src/im_controller src/im_tuner
# Anything that changes what gets installed re-triggers the (fast, no-deps) package install.
PKG_FILES := $(shell find $(PKGS) -type f \( -name '*.py' -o -name '*.yaml' -o -name '*.xml' \
               -o -name '*.cfg' -o -name '*.json' -o -path '*/scripts/*' -o -path '*/resource/*' \) -not -path '*/test/*' \
               -not -path '*/__pycache__/*' 2>/dev/null)

# ROS needs a writable log directory and the ament index of the venv.
export HOME ?= $(CURDIR)
export AMENT_PREFIX_PATH := $(abspath $(VENV))$(if $(AMENT_PREFIX_PATH),:$(AMENT_PREFIX_PATH))
# Bytecode is written (a host may forbid it in its environment): pytest keeps each test
# module's assertion rewrite in __pycache__, and every xdist worker collects the whole
# suite (the pure tier's collection: 6.8 s rewritten, 1.9 s cached).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: test-serial setup test test-unit test-levels lint format demo demo-drive bench reproduction reproduction-docs calibrate-bench foxglove-check foxglove-layouts foxglove-screenshots docs lock clean

setup: $(VENV)/.installed

$(PY):
	$(PYTHON) -m venv $(VENV)

$(VENV)/.deps: requirements.txt constraints.txt | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt -c constraints.txt
	touch $@

$(VENV)/.installed: $(VENV)/.deps $(PKG_FILES) tools/ros2 Makefile
	@# numba's cache knows only the file of each function: a fused kernel (im_tuner/offline.py)
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

# The whole suite in two passes (CI's command): every test but those that assert wall-clock
# timing on two workers (pytest-xdist, a test file to a worker so a module's fixture is made
# once, the longest files first: conftest.py), then those (marked serial: another test
# beside them would be their load) alone. Both passes always run; either failing fails.
# The first steps safe computes are shared by both passes (IM_TUNER_PRIOR_CACHE, conftest.py).
# `make test-serial` is the same suite in one process.
test: setup
	@export IM_TUNER_PRIOR_CACHE=$$(mktemp -d /tmp/im_tuner_test_priors.XXXXXX); \
	    $(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder -m 'not serial'; a=$$?; \
	    $(PY) -m pytest -m serial -p no:cacheprovider; b=$$?; \
	    rm -rf "$$IM_TUNER_PRIOR_CACHE"; \
	    echo "make test: parallel pass exit $$a, serial pass exit $$b"; \
	    [ $$a -eq 0 ] && [ $$b -eq 0 ]

test-serial: setup
	$(PY) -m pytest

# The pure tier (marked unit: no DDS graph, no child process) on two workers, as `make test`,
# with a first-step cache of its own.
UNIT_TIER := -n 2 --dist loadfile --no-loadscope-reorder -m unit -p no:cacheprovider
test-unit: setup
	@export IM_TUNER_PRIOR_CACHE=$$(mktemp -d /tmp/im_tuner_test_priors.XXXXXX); \
	    $(PY) -m pytest $(UNIT_TIER); a=$$?; rm -rf "$$IM_TUNER_PRIOR_CACHE"; exit $$a

# The pure tier (every digest: optimisers, drive model, study) again on a machine without
# AVX-512, emulated: numpy's dispatch held at X86_V3 and OpenBLAS's Zen core type, as on an
# AMD Zen 2/3. With the numeric baseline (im_drive_sim.numeric) it must pass as natively;
# CI runs it after `make test` (docs/tuner.md, "The same bits on every machine"), on two
# workers as `make test`, with a first-step cache of its own (each point computed at this level).
test-levels: setup
	@export IM_TUNER_PRIOR_CACHE=$$(mktemp -d /tmp/im_tuner_test_priors.XXXXXX); \
	    NPY_DISABLE_CPU_FEATURES=X86_V4,AVX512_ICL,AVX512_SPR OPENBLAS_CORETYPE=Zen \
	    $(PY) -m pytest $(UNIT_TIER); \
	    a=$$?; rm -rf "$$IM_TUNER_PRIOR_CACHE"; exit $$a

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
	$(PY) benchmarks/run_all.py

# The `bench` realism profile's calibration: the spread of repeated experiments
# and the paper's centre cells (Tables I-II) for `ideal` and `bench` at noise scales s,
# the fit -> docs/calibration.md (research/calibrate_bench.py; ~5-10 min on 2 cores, niced).
calibrate-bench: setup
	nice -n 10 $(PY) research/calibrate_bench.py --out docs/calibration.md $(ARGS)

# The paper's Tables I-III offline and beyond, then their write-up
# into docs/: reproduction.md (the paper's drive on the `ideal` profile: Tables I-III and
# every algorithm; then Tables I-III on the `bench` profile beside `ideal` and the paper's)
# and reproduction-family.md (a study per drive on `bench`, the summary over the drives).
# Hours at the defaults; a smoke run: make reproduction ARGS='--runs 3 --budget 10'.
STUDY_OUT  := bags/study_reproduction
BENCH_OUT  := bags/study_reproduction_bench
FAMILY_OUT := bags/study_reproduction_family
# the paper's two (Tables I-III) and every algorithm beyond it (the comparison)
STUDY_ALGOS ?= spsa,necga,cga,pecga,rcga,cmaes,tpe,safe
# the drives of the family study (packaged names or drive files), its runs and budget
FAMILY_DRIVES ?= im750w-j1,im750w-j3,im750w-j10,im3700w-j1,im3700w-j3,im3700w-j10,im7500w-j1,im7500w-j3,im7500w-j10
FAMILY_RUNS   ?= 25
FAMILY_BUDGET ?= 200
STUDY := $(VENV)/bin/ros2 run im_tuner study
reproduction: setup
	@echo 'reproduction: three studies, hours at the defaults (each prints its runs, rate and ETA as it goes)'
	rm -rf $(STUDY_OUT) $(BENCH_OUT) $(FAMILY_OUT)
	$(STUDY) --out $(STUDY_OUT) --algos $(STUDY_ALGOS) $(ARGS)
	$(STUDY) --out $(BENCH_OUT) --algos spsa,necga --realism bench --runs 50 --beside $(STUDY_OUT) $(ARGS)
	$(STUDY) --out $(FAMILY_OUT) --drives $(FAMILY_DRIVES) --realism bench \
	    --runs $(FAMILY_RUNS) --budget $(FAMILY_BUDGET) $(ARGS)
	$(MAKE) reproduction-docs

# The write-up alone, from the three studies' directories (no experiment run); every input
# is checked first: one missing leaves docs/ untouched (one line, exit 2).
reproduction-docs:
	bash tools/reproduction_docs.sh $(STUDY_OUT) $(BENCH_OUT) $(FAMILY_OUT)

# Decode every message of a bag with Foxglove's own libraries (Node.js + npm; pinned in
# tools/foxglove-check/package-lock.json): make foxglove-check BAG=bags/<run>/bag_0
foxglove-check:
	@test -n "$(BAG)" || { echo 'usage: make foxglove-check BAG=<bag directory>'; exit 2; }
	cd tools/foxglove-check && npm ci --silent --no-audit --no-fund
	node tools/foxglove-check/check.mjs $(BAG)/*.mcap

# The Foxglove layouts shipped in share/im_tuner/foxglove/, regenerated from the contracts into
# their committed place (docs/foxglove.md); a test checks the committed files are these bytes.
foxglove-layouts: setup
	$(PY) -m im_tuner.foxglove --out src/im_tuner/foxglove
	@$(MAKE) --no-print-directory setup

# docs/foxglove/*.png: each shipped layout in Foxglove Studio's own app (headless Chromium,
# tools/foxglove-view) on a real run's bag, and one live (tools/foxglove-view/screenshots.py).
# Needs /usr/bin/chromium and npm; about 3 min on 2 cores.
foxglove-screenshots: setup
	cd tools/foxglove-view && npm ci --silent --no-audit --no-fund
	nice $(PY) tools/foxglove-view/screenshots.py docs/foxglove

# The docs' generated parts: docs/tuner.md's options table, from im_tuner/tuner_args.py's
# declarations (a test checks it is current).
docs: setup
	$(PY) -m im_tuner.tuner_args docs/tuner.md

# Re-resolve the pinned set after editing requirements.txt.
lock: | $(PY)
	$(PY) -m pip install --quiet -r requirements.txt
	{ echo '# Full resolved dependency set (pip freeze), used as constraints by `make setup`.'; \
	  $(PY) -m pip freeze --exclude-editable | grep -viE '^im[-_](drive[-_]sim|controller|tuner)( @|==)'; } > constraints.txt

clean:
	rm -rf $(VENV) build src/*/build src/*/*.egg-info
