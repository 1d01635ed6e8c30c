# Two entry points for a fresh machine: `make demo` and `make test`.
# Both run `setup` first; setup is idempotent (re-runs only when the pins change).
# `make test` runs the gates (`make check`: ruff, mypy, module/function sizes) and then the tests.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: setup check demo test paper bench bags clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt constraints.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt -r requirements-dev.txt -c constraints.txt
	# The repo itself goes on the venv's path (an editable install without a build step;
	# colcon builds the real package from setup.py).
	$(PY) -c 'import pathlib, site; pathlib.Path(site.getsitepackages()[0], "tetra_gradiometer.pth").write_text(str(pathlib.Path.cwd()))'
	touch $(STAMP)

demo: setup
	$(PY) -m tetra_gradiometer demo --out $(OUT)/demo --force

check: setup
	$(VENV)/bin/ruff check tetra_gradiometer
	$(VENV)/bin/mypy
	$(PY) scripts/check_sizes.py tetra_gradiometer

test: setup check
	$(PY) -m pytest

paper: setup
	$(PY) -m tetra_gradiometer paper --out $(OUT)/paper --force

bench: setup
	$(PY) bench/bench_solvers.py
	$(PY) bench/bench_accuracy.py
	$(PY) bench/bench_scale.py
	$(PY) bench/bench_chain.py
	$(PY) bench/bench_discrepancy.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache *.egg-info mutants

# Mutation smoke check (not in CI, a few minutes): mutmut (requirements-dev.txt) mutates
# core/metrics.py, geometry.py and fields.py and runs their tests (config: setup.cfg [mutmut]).
# Survivors are listed at the end; `.venv/bin/mutmut show NAME` prints one.
.PHONY: mutation
mutation: setup
	rm -rf mutants
	$(VENV)/bin/mutmut run --max-children 2
	$(VENV)/bin/mutmut results
