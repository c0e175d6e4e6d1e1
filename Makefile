# Two commands a new user needs (see README): `make run` and `make test`.
# Each creates its own virtual environment in .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

# pip >= 21.3 installs an editable package from pyproject.toml alone (PEP 660): upgraded only where
# the venv's own pip is older (Python 3.10.0 ships 21.2.3; 3.11's is new enough, no download).
# --no-compile: Python byte-compiles the modules a process imports when it first imports them,
# instead of pip compiling every file of jax, scipy, pandas, ... up front. Fresh venv and home, no
# pip cache, alternating: install 33.1 / 46.5 -> 21.3 / 29.3 s, the first import 2.6 -> 5.0-5.3 s.
# The study installs what it runs (the package and `io` for runs.parquet); the test suite adds its
# independent references (`test`: Pinocchio, scipy, OSQP, example-robot-data), which the study never
# imports. Fresh venv and home, the same commands, alternating: `.[io]` 22.1 / 25.2 s, `.[test,io]`
# 32.2 / 46.6 s.
$(VENV)/.created:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q 'pip>=21.3'
	touch $@

$(VENV)/.installed-run: pyproject.toml $(VENV)/.created
	$(PY) -m pip install -q --no-compile -e '.[io]'
	touch $@

$(VENV)/.installed-test: pyproject.toml $(VENV)/.created
	$(PY) -m pip install -q --no-compile -e '.[test,io]'
	touch $@ $(VENV)/.installed-run

# Python writes the bytecode of what a command imports (into .venv and src, both ignored by git) even
# where the environment sets PYTHONDONTWRITEBYTECODE, as some CI and sandbox images do (this project's
# machines among them). A command starts several Python processes that import the same modules (the
# study: its own, two workers, two XLA-flag probes and two report processes; the test suite: its
# workers and the subprocesses of the CLI, example and benchmark tests), and without bytecode on disk
# each compiles jax, diffrax, ... from source again: `import redman_jax` and the sweep's modules 3.2 s
# without, 1.7 s with. A 7-DOF inspection sweep of 2 seeds with its report (`redman-jax sweep --arms 7
# --cases inspection --controllers joint_space --seeds 1-2`, no bytecode at the start either way,
# alternating, 3 rounds): 52.6 / 51.0 / 50.4 s not writing it, 47.7 / 46.0 / 44.2 s writing it.
# `make test` in the tree, bytecode removed before each (one pair): pytest 631.7 s not writing it,
# 577.2 s writing it. `make run WRITE_BYTECODE=` (empty) leaves the environment's setting as it is.
WRITE_BYTECODE := PYTHONDONTWRITEBYTECODE=

.PHONY: venv run test test-all bench
venv: $(VENV)/.installed-test

run: $(VENV)/.installed-run
	$(WRITE_BYTECODE) $(PY) -m redman_jax study --out results

# pytest exits 5 when it collects no test: treat that as a failure-free run with a clear message.
# `make test` (what CI runs) leaves out the tests marked slow: whole tuning runs with reverse-mode
# compilations through the simulator, the examples and each benchmark at a tiny size, minutes each on
# 2 cores. `make test-all` runs them too.
PYTEST_MARK ?= not slow
test: $(VENV)/.installed-test
	$(WRITE_BYTECODE) $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "$(PYTEST_MARK)"; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi; exit $$rc

test-all: $(VENV)/.installed-test
	$(MAKE) test PYTEST_MARK=""

bench: $(VENV)/.installed-run
	$(PY) -m pip install -q -e '.[bench]'
	for f in benchmarks/*.py; do $(WRITE_BYTECODE) $(PY) $$f || exit 1; done
