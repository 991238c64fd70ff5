# Two commands set up a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

export MUJOCO_GL ?= egl
export OMP_NUM_THREADS ?= 1

.PHONY: demo demo-reach test bench install clean

install: $(STAMP)

# torch first, pinned to the CPU build, so resolving the package pulls no CUDA build.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m recipes.demo

demo-reach: $(STAMP)
	$(PY) -m recipes.reach_demo

# one worker per core (tests are grouped by file, which keeps a module's fixtures on one worker)
test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile

bench: $(STAMP)
	$(PY) benchmarks/bench_core.py
	$(PY) benchmarks/bench_layer.py
	$(PY) benchmarks/bench_envs.py

clean:
	rm -rf $(VENV) runs .pytest_cache
