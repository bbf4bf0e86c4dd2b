VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
DEMO_OUT ?= demo-output
# lsst-images (the `lsst` extra) needs Python >= 3.12: its tests run in a second venv
LSST_VENV ?= .venv-lsst
LSST_PY := $(LSST_VENV)/bin/python
LSST_PYTEST_ARGS ?=
# Tests run with single-threaded OpenBLAS: on a busy 2-core machine its idle threads spin
# and a test's CPU time grows several-fold (measured: 21 -> 5 CPU s for two BFD tests)
TEST_ENV ?= OPENBLAS_NUM_THREADS=1

.PHONY: demo test test-all test-lsst test-slurm bench lint schemas clean

$(VENV)/.installed-base: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $@ $(VENV)/.installed-base

$(VENV)/.installed-docs: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[docs]"
	touch $@

demo: $(VENV)/.installed-base
	$(VENV)/bin/cellcoadd demo --out $(DEMO_OUT) --overwrite

# the default suite: tests marked slow (Monte Carlo, long runs) are left out by the addopts
# of pyproject.toml, which also print the 15 slowest tests
test: $(VENV)/.installed-test
	$(TEST_ENV) $(PY) -m pytest
	@$(MAKE) --no-print-directory test-lsst

# every test, the slow ones too (before a release); the last -m given wins over the addopts.
# The SLURM tests run last, in test-slurm (it starts a SLURM on this machine first)
test-all: $(VENV)/.installed-test
	$(TEST_ENV) $(PY) -m pytest -m 'not slurm'
	@$(MAKE) --no-print-directory test-lsst LSST_PYTEST_ARGS="-m 'slow or not slow'"
	@$(MAKE) --no-print-directory test-slurm

# tests/system: a survey run through dask-jobqueue's SLURMCluster on a single-host SLURM
# (munged, slurmctld, slurmd on 127.0.0.1) that start_slurm.sh installs (Debian's slurm-wlm
# and munge), configures and starts when it is not running; needs root.
# tests/system/slurm/stop_slurm.sh stops the daemons
test-slurm: $(VENV)/.installed-test
	bash tests/system/slurm/start_slurm.sh
	$(TEST_ENV) $(PY) -m pytest -m slurm tests/system

# tests/test_lsst_images.py in $(LSST_VENV), made with the newest pyenv 3.12 (else a plain
# python3.12 on PATH); without any Python 3.12 it is skipped, unless CI is set (then fails)
test-lsst:
	@py=$$(pyenv versions --bare 2>/dev/null | grep -E '^3\.12(\.[0-9]+)?$$' | tail -1); \
	if [ -n "$$py" ]; then python="env PYENV_VERSION=$$py python3.12"; \
	elif python3.12 -c pass >/dev/null 2>&1; then python=python3.12; \
	elif [ -n "$$CI" ]; then echo "test-lsst: no Python 3.12 found (pyenv or PATH); CI must run the lsst-images tests"; exit 1; \
	else echo "test-lsst: skipped, no Python 3.12 found (pyenv or PATH) for lsst-images"; exit 0; fi; \
	set -e; \
	test -x $(LSST_PY) || $$python -m venv $(LSST_VENV); \
	if [ ! -f $(LSST_VENV)/.installed ] || [ pyproject.toml -nt $(LSST_VENV)/.installed ]; then \
		$(LSST_PY) -m pip install -q -e ".[lsst]" "pytest>=7.4"; touch $(LSST_VENV)/.installed; \
	fi; \
	$(TEST_ENV) $(LSST_PY) -m pytest tests/test_lsst_images.py $(LSST_PYTEST_ARGS)

bench: $(VENV)/.installed-test
	for script in benchmarks/bench_*.py; do $(PY) $$script || exit 1; done

lint: $(VENV)/.installed-test
	$(VENV)/bin/ruff check cellcoadd tests benchmarks
	$(VENV)/bin/ruff format --check cellcoadd tests benchmarks
	$(VENV)/bin/mypy cellcoadd/

schemas: $(VENV)/.installed-base
	$(VENV)/bin/cellcoadd schemas --out schemas/

.PHONY: docs docs-inventories

# HTML of docs/ (the Markdown pages and the API reference) in docs/_build/html; warnings are
# errors. No network needed: intersphinx links only to the projects whose inventory is in
# docs/_inventories/ (see docs/conf.py and `make docs-inventories`)
docs: $(VENV)/.installed-docs
	rm -rf docs/api
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html -d docs/_build/doctrees docs docs/_build/html

# where there is network: the intersphinx inventories of numpy, astropy, GalSim, dask, ...
docs-inventories:
	$(PY) -c "import sys; sys.path.insert(0, 'docs'); import conf; conf.fetch_inventories()"

clean:
	rm -rf $(VENV) $(LSST_VENV) $(DEMO_OUT) .pytest_cache .mypy_cache docs/_build docs/api
