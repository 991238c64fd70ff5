# Two commands set up a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

export MUJOCO_GL ?= egl
export OMP_NUM_THREADS ?= 1

# tcmalloc, where installed (Debian: libtcmalloc-minimal4), serves the runs of `make demo` and `make bench`: the
# compiled plan loops allocate many small tensors, which it makes 1.2-1.4x faster (docs/install.md).
# `make bench MALLOC=` runs on the system's malloc.
# (expanded when a recipe runs, once the package is installed: torchrl_brsl._malloc finds it)
MALLOC ?= $(shell $(PY) -c "from torchrl_brsl._malloc import installed_allocators as a; print(a().get('tcmalloc', ''))")
RUN = $(if $(MALLOC),LD_PRELOAD=$(MALLOC) )$(PY)

.PHONY: demo demo-reach test docs bench install clean

install: $(STAMP)

# torch first, pinned to the CPU build, so resolving the package pulls no CUDA build.
$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]' -c constraints.txt
	touch $(STAMP)

demo: $(STAMP)
	$(RUN) -m recipes.demo

demo-reach: $(STAMP)
	$(RUN) -m recipes.reach_demo

# one worker per core (tests are grouped by file, which keeps a module's fixtures on one worker); the slowest
# tests are listed at the end, where the suite's time goes
test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile -m "not docs" --durations=15

# the site in docs/_build/html: Sphinx with warnings as errors, every tutorial executed
# (the build is the test tests/docs/test_docs_build.py)
DOCS_STAMP := $(VENV)/.installed-docs

$(DOCS_STAMP): $(STAMP) pyproject.toml constraints.txt
	$(PY) -m pip install --quiet -e '.[test,docs]' -c constraints.txt
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(PY) -m pytest -q -m docs tests/docs/test_docs_build.py
	@echo "open docs/_build/html/index.html"

bench: $(STAMP)
	$(RUN) benchmarks/bench_core.py
	$(RUN) benchmarks/bench_layer.py
	$(RUN) benchmarks/bench_envs.py
	$(PY) benchmarks/bench_malloc.py

clean:
	rm -rf $(VENV) runs .pytest_cache docs/_build docs/auto_tutorials docs/sg_execution_times.rst
