# Two commands a new user needs (see README): `make run` and `make test`.
# Each creates its own virtual environment in .venv on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test,io]'
	touch $@

.PHONY: venv run test bench
venv: $(VENV)/.installed

run: $(VENV)/.installed
	$(PY) -m redman_jax study --out results

# pytest exits 5 when it collects no test: treat that as a failure-free run with a clear message.
test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 --dist loadfile; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi; exit $$rc

bench: $(VENV)/.installed
	$(PY) -m pip install -q -e '.[bench]'
	for f in benchmarks/*.py; do $(PY) $$f || exit 1; done
