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
# wheels with plain cmake and installed into the venv's prefix, where the venv's Python finds
# it with no variables (docs/ros.md, *Our interfaces*). Rebuilt when its files or the pins
# change; the build dir (git-ignored) is kept for incremental rebuilds.
MSGS       := tetra_gradiometer_msgs
MSGS_STAMP := $(VENV)/.msgs-installed
MSGS_FILES := $(MSGS)/CMakeLists.txt $(MSGS)/package.xml $(wildcard $(MSGS)/msg/*.msg $(MSGS)/srv/*.srv)
# per venv (target-specific below): MSGS_VENV, and its build dir MSGS_BUILD; the wheels'
# ament index (rosidl_typesupport_c's lookup) and cmake packages are the venv's
MSGS_ENV    = PATH="$(abspath $(MSGS_VENV))/bin:$$PATH" AMENT_PREFIX_PATH="$(abspath $(MSGS_VENV))"

.PHONY: setup browser check demo test tests test-slow test-noble paper bench bags clean

# The bytecode of this package and of the interface package too (compileall rewrites only what
# changed): where PYTHONDONTWRITEBYTECODE is set, nothing else writes it, and every process
# compiled the modules it imports (~0.4 s of CPU for a node's).
setup: $(STAMP) $(MSGS_STAMP) browser
	@$(PY) -m compileall -q tetra_gradiometer "$$($(PY) -c 'import tetra_gradiometer_msgs as m, pathlib; print(pathlib.Path(m.__file__).parent)')" > /dev/null

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
	# uv installs the pinned tree in ~10 s where pip took ~90 s (the same packages: pip freeze
	# of both venvs is identical but for uv itself). --compile-bytecode: uv writes no .pyc by
	# default, and where PYTHONDONTWRITEBYTECODE is set nothing else does, so every process
	# compiled numpy, scipy and rclpy from source (~0.8 s of CPU per node process).
	$(PY) -m uv pip install --quiet --compile-bytecode --python $(PY) -r requirements.txt -r requirements-dev.txt -c constraints.txt
	# The repo itself goes on the venv's path (an editable install without a build step;
	# colcon builds the ROS package from ros/tetra_gradiometer/).
	$(PY) -c 'import pathlib, site; pathlib.Path(site.getsitepackages()[0], "tetra_gradiometer.pth").write_text(str(pathlib.Path.cwd()))'
	touch $(STAMP)

define BUILD_MSGS
$(MSGS_ENV) cmake -S $(MSGS) -B $(MSGS_BUILD) -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
  -DCMAKE_PREFIX_PATH="$(abspath $(MSGS_VENV))" -DPython3_EXECUTABLE="$(abspath $(MSGS_VENV))/bin/python" > /dev/null
$(MSGS_ENV) cmake --build $(MSGS_BUILD) -j $(shell nproc) > $(MSGS_BUILD)/make.log \
  || { tail -n 30 $(MSGS_BUILD)/make.log; exit 1; }
cmake --install $(MSGS_BUILD) --prefix "$(abspath $(MSGS_VENV))" > /dev/null
touch $@
endef

$(MSGS_STAMP): MSGS_VENV := $(VENV)
$(MSGS_STAMP): MSGS_BUILD := build/$(MSGS)
$(MSGS_STAMP): $(STAMP) $(MSGS_FILES)
	$(BUILD_MSGS)

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

# PYTHONDONTWRITEBYTECODE emptied: pytest keeps the test modules as it rewrote their asserts
# (test/**/__pycache__), so a worker imports what another one rewrote: collecting the suite
# took 7.4 s of CPU in a worker with nothing written, 5.2 s as the first one writing, 2.6 s after.
tests: setup
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -n $(TEST_WORKERS) -m 'not slow'

test-slow: setup
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -n $(TEST_WORKERS) -m slow

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
$(NOBLE_MSGS_STAMP): MSGS_VENV := $(NOBLE_VENV)
$(NOBLE_MSGS_STAMP): MSGS_BUILD := build/$(MSGS)-noble
$(NOBLE_MSGS_STAMP): $(NOBLE_STAMP) $(MSGS_FILES)
	$(BUILD_MSGS)

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
