# Two commands do all setup on a machine that has only Python 3.10+:
#   make demo   - fit the paper's Example 1 with I-PIA and IURS, print the table, save the figure
#   make test   - build the docs with warnings as errors, then run the whole test suite
#                 (the benchmarks' own tests in benchmarks/tests and the notebooks included)
# and for development:
#   make test-fast - the suite without the tests marked slow (pytest -m "not slow")
#   make docs      - the documentation site, into site/
#   make lint      - ruff's linter and formatter check and the type checker (make test
#                    runs them first)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Quiets mkdocs-material's banner about its successor; the build itself is unchanged.
MKDOCS := NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs

.PHONY: demo test test-fast docs lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,jaxopt,docs,lint]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/jurs demo

# Two pytest workers: on 2 cores the suite takes about 30 % less wall time than one
# (compilation is mostly single-threaded). On a GPU, JAX would give each worker 75 % of
# the device's memory up front; the workers allocate as they go instead.
# The docs build first (seconds): a broken link or a docstring reference that no longer
# resolves fails the run before the long suite starts.
test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check --quiet .
	$(VENV)/bin/basedpyright --project . --level error
	$(MKDOCS) build --strict --quiet
	XLA_PYTHON_CLIENT_PREALLOCATE=false $(PY) -m pytest -q -n 2 --durations=25 --nbmake tests benchmarks/tests notebooks

test-fast: $(STAMP)
	XLA_PYTHON_CLIENT_PREALLOCATE=false $(PY) -m pytest -q -n 2 -m "not slow" tests benchmarks/tests

docs: $(STAMP)
	$(MKDOCS) build --strict

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/basedpyright --project .

bench: $(STAMP)
	$(PY) -m benchmarks.step_speed

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info site
