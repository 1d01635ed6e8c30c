# Two entry points for a fresh machine: `make demo` and `make test`.
# Both run `setup` first; setup is idempotent (re-runs only when the pins change).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: setup demo test paper bench bags clean

setup: $(STAMP)

$(STAMP): requirements.txt constraints.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt -c constraints.txt
	# The repo itself goes on the venv's path (an editable install without a build step;
	# colcon builds the real package from setup.py).
	$(PY) -c 'import pathlib, site; pathlib.Path(site.getsitepackages()[0], "tetra_gradiometer.pth").write_text(str(pathlib.Path.cwd()))'
	touch $(STAMP)

demo: setup
	$(PY) -m tetra_gradiometer demo --out $(OUT)/demo --force

test: setup
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
	rm -rf $(VENV) $(OUT) .pytest_cache *.egg-info
