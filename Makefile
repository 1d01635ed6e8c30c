# Two entry points for a fresh machine: `make demo` and `make test`.
# Both run `setup` first; setup is idempotent (re-runs only when the pins change, and builds
# the interface package tetra_gradiometer_msgs/ only when its files change).
# `make test` runs the gates (`make check`: ruff, mypy, module/function sizes) and then the tests.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out
UV_VERSION := 0.9.30

# The interface package tetra_gradiometer_msgs/ (ament_cmake, rosidl) built from the ros-jazzy-*
# wheels with plain cmake and installed into the venv's prefix (scripts/build_msgs.sh, which
# caches what it installed). Rebuilt when its files or the pins change; the build dir
# (git-ignored) is kept for incremental rebuilds.
MSGS       := tetra_gradiometer_msgs
MSGS_STAMP := $(VENV)/.msgs-installed
MSGS_FILES := $(MSGS)/CMakeLists.txt $(MSGS)/package.xml $(wildcard $(MSGS)/msg/*.msg $(MSGS)/srv/*.srv)

.PHONY: setup browser check demo test tests test-slow test-noble paper bench bags clean

# Every recipe's Python writes the bytecode of what it imports, on first import, so setup
# compiles nothing: compiling the whole venv (~11 000 modules, the suite imports a fraction)
# took ~20 s of a fresh clone's setup (37 s of CPU). Where PYTHONDONTWRITEBYTECODE is set (this
# machine sets it) nothing is written and every process compiles numpy, scipy, rclpy and ours
# from source: 1.6 s of CPU for the compensator node's modules, 0.8 s from bytecode.
unexport PYTHONDONTWRITEBYTECODE

setup: $(STAMP) $(MSGS_STAMP) browser

# The survey report's browser test (test/reports/test_survey_report.py) loads report.html in
# headless Chromium from Debian's packages: installed here when missing and we are root with
# apt-get (idempotent: nothing is done when it is there); elsewhere that test names what to install.
browser:
	@command -v chromium >/dev/null 2>&1 || ! command -v apt-get >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] \
	  || (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium) >/dev/null 2>&1 \
	  || echo 'warning: apt-get install chromium failed: the survey report browser test will fail'

$(STAMP): requirements.txt requirements-dev.txt constraints.txt
	# A venv without pip, and uv put in it by the interpreter's own pip (pip >= 22.3:
	# --python): ~3 s, where ensurepip's pip first took ~8 s; where that pip cannot, the venv's
	# ensurepip and pip do it.
	test -x $(PY) || $(PYTHON) -m venv --without-pip $(VENV)
	$(PY) -m uv --version 2> /dev/null | grep -q "^uv $(UV_VERSION)" \
	  || $(PYTHON) -m pip --python $(PY) install --quiet --disable-pip-version-check uv==$(UV_VERSION) \
	  || { $(PY) -m ensurepip --default-pip > /dev/null && $(PY) -m pip install --quiet --disable-pip-version-check uv==$(UV_VERSION); }
	# uv installs the pinned tree in ~5 s where pip took ~90 s (the same packages: pip freeze
	# of both venvs is identical but for uv itself).
	$(PY) -m uv pip install --quiet --python $(PY) -r requirements.txt -r requirements-dev.txt -c constraints.txt
	# The repo itself goes on the venv's path (an editable install without a build step;
	# colcon builds the ROS package from ros/tetra_gradiometer/).
	$(PY) -c 'import pathlib, site; pathlib.Path(site.getsitepackages()[0], "tetra_gradiometer.pth").write_text(str(pathlib.Path.cwd()))'
	touch $(STAMP)

$(MSGS_STAMP): $(STAMP) $(MSGS_FILES) scripts/build_msgs.sh
	scripts/build_msgs.sh $(VENV) build/$(MSGS)
	touch $@

demo: setup
	$(PY) -m tetra_gradiometer demo --out $(OUT)/demo --force

# mypy's cache lives beside uv's, outside the clone (its entries are checked against the files'
# hashes): a fresh clone on a machine that ran the gates before checks what changed, ~0.5 s
# instead of ~16 s of CPU beside the tests.
MYPY_CACHE ?= $${XDG_CACHE_HOME:-$$HOME/.cache}/tetra_gradiometer/mypy
check: setup
	$(VENV)/bin/ruff check tetra_gradiometer
	$(VENV)/bin/mypy --cache-dir "$(MYPY_CACHE)"
	$(PY) scripts/check_sizes.py tetra_gradiometer

# The tests on one pytest-xdist worker per core plus one (TEST_WORKERS=0: one process, e.g.
# for pdb); a whole test module goes to one worker (pytest.ini, docs/testing.md). The extra
# worker runs while others wait on wall-clock time (ROS replays, node start-up, discovery),
# which keeps the cores busy; a second one cost more CPU (each worker collects the whole suite,
# ~8 s) than it saved in waits.
TEST_WORKERS ?= $(shell echo $$(($$(nproc) + 1)))
# `make test` leaves out the tests marked slow (pytest.ini): `make test-slow` runs those, and CI
# (.ci/run) runs both.
test: setup
	$(MAKE) --no-print-directory -j2 check tests

# With bytecode written (above), pytest also keeps the test modules as it rewrote their asserts
# (test/**/__pycache__), so a worker imports what another one rewrote: collecting the suite
# took 7.4 s of CPU in a worker with nothing written, 5.2 s as the first one writing, 2.6 s after.
tests: setup
	$(PY) -m pytest -n $(TEST_WORKERS) -m 'not slow'

test-slow: setup
	$(PY) -m pytest -n $(TEST_WORKERS) -m slow

# The suite against Ubuntu Noble's numpy 1.26.4 and scipy 1.11.4 (what a ROS 2 Jazzy install
# has): a second venv with the main pins but the deviations of constraints-noble.txt
# (scripts/noble_pins.py substitutes them). Not in CI (`make test`); needs no ROS install.
NOBLE_VENV  := .venv-noble
NOBLE_PY    := $(NOBLE_VENV)/bin/python
NOBLE_STAMP := $(NOBLE_VENV)/.installed
NOBLE_MSGS_STAMP := $(NOBLE_VENV)/.msgs-installed

$(NOBLE_STAMP): requirements.txt requirements-dev.txt constraints.txt constraints-noble.txt scripts/noble_pins.py
	test -x $(NOBLE_PY) || $(PYTHON) -m venv $(NOBLE_VENV)
	$(NOBLE_PY) scripts/noble_pins.py $(NOBLE_VENV)/pins
	$(NOBLE_PY) -m pip install --quiet --disable-pip-version-check -r $(NOBLE_VENV)/pins/requirements.txt -c $(NOBLE_VENV)/pins/constraints.txt
	$(NOBLE_PY) -c 'import pathlib, site; pathlib.Path(site.getsitepackages()[0], "tetra_gradiometer.pth").write_text(str(pathlib.Path.cwd()))'
	touch $(NOBLE_STAMP)

# the interface package, built against this venv's numpy in a build dir of its own
$(NOBLE_MSGS_STAMP): $(NOBLE_STAMP) $(MSGS_FILES) scripts/build_msgs.sh
	scripts/build_msgs.sh $(NOBLE_VENV) build/$(MSGS)-noble
	touch $@

test-noble: $(NOBLE_STAMP) $(NOBLE_MSGS_STAMP)
	$(NOBLE_PY) -c 'import numpy, scipy; print("numpy", numpy.__version__, "scipy", scipy.__version__)'
	$(NOBLE_PY) -m pytest -n $(TEST_WORKERS)

paper: setup
	$(PY) -m tetra_gradiometer paper --out $(OUT)/paper --force

# The benchmarks, each writing its results to bench/results/NAME.json, then the README's
# tables from those files (bench/tables.py; --measured-here records this machine for them).
# bench_chain prints its figures only, and bench_targets --speed times one bag: their tables
# keep the data of the runs recorded in chain.json and targets.json.
BENCH_JSON := paper solvers accuracy scale checks discrepancy openworld health window signals
bench: setup
	$(PY) -m tetra_gradiometer paper --out $(OUT)/paper --force
	cp $(OUT)/paper/results.json bench/results/paper.json
	$(PY) bench/bench_solvers.py --json bench/results/solvers.json
	$(PY) bench/bench_accuracy.py --json bench/results/accuracy.json
	$(PY) bench/bench_scale.py --json bench/results/scale.json
	$(PY) bench/bench_checks.py --json bench/results/checks.json
	$(PY) bench/bench_chain.py
	$(PY) bench/bench_discrepancy.py --seeds 5 --json bench/results/discrepancy.json
	$(PY) bench/bench_openworld.py --json bench/results/openworld.json
	$(PY) bench/bench_health.py --json bench/results/health.json
	$(PY) bench/bench_targets.py --speed
	$(PY) bench/bench_window.py --json bench/results/window.json
	$(PY) bench/bench_signals.py --json bench/results/signals.json
	$(PY) bench/bench_tracker.py --seeds 1,2,3,4,5,6,7,8 --json bench/results/tracker.json
	$(PY) bench/tables.py --measured-here $(addsuffix .json,$(BENCH_JSON))

clean:
	rm -rf $(VENV) $(NOBLE_VENV) $(OUT) build/$(MSGS) build/$(MSGS)-noble .pytest_cache *.egg-info mutants

# Mutation smoke check (not in CI): mutmut (requirements-dev.txt) mutates core/metrics.py,
# geometry.py, fields.py, core/effects/, core/identification/terms.py, core/streams.py,
# core/live_streams.py and pipelines/window_check.py and runs their direct tests (config:
# setup.cfg [mutmut]); scripts/mutation_score.py prints killed / survived / untested per file.
# Survivors are listed at the end; `.venv/bin/mutmut show NAME` prints one.
# MUTANTS='tetra_gradiometer.core.effects*' runs only the mutants whose names match (the whole
# set takes over 30 min on two loaded cores).
MUTANTS ?=
.PHONY: mutation
mutation: setup
	rm -rf mutants
	$(VENV)/bin/mutmut run --max-children 2 $(MUTANTS)
	$(VENV)/bin/mutmut results
