VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
DEMO_OUT ?= demo-output

.PHONY: demo test bench lint schemas clean

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

demo: $(VENV)/.installed-base
	$(VENV)/bin/cellcoadd demo --out $(DEMO_OUT)

test: $(VENV)/.installed-test
	$(PY) -m pytest

bench: $(VENV)/.installed-test
	for script in benchmarks/bench_*.py; do $(PY) $$script || exit 1; done

lint: $(VENV)/.installed-test
	$(VENV)/bin/ruff check cellcoadd tests benchmarks
	$(VENV)/bin/ruff format --check cellcoadd tests benchmarks
	$(VENV)/bin/mypy cellcoadd/

schemas: $(VENV)/.installed-base
	$(VENV)/bin/cellcoadd schemas --out schemas/

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .mypy_cache
