# On a fresh machine:  make demo,  make test  and  make docs
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m aocontrol demo --output demo-output

# Two pytest-xdist workers, one test file each at a time (a file's module-scoped fixtures are
# built once): the suite is CPU-bound and a serial run uses one of CI's two cores.
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

lint: $(STAMP)
	$(PY) -m ruff check aocontrol tests benchmarks

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

# HTML docs in docs/_build/html: API, tour, cases, notebooks executed in quick mode (the test
# extra installs the docs extra's packages; warnings are errors; -q: only what needs acting on).
docs: $(STAMP)
	@echo "make docs: building docs/_build/html (runs the five notebooks in quick mode)"
	$(PY) -m sphinx -q -W --keep-going -b html docs docs/_build/html
	@echo "make docs: open docs/_build/html/index.html"

clean:
	rm -rf $(VENV) demo-output .pytest_cache
