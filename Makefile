# Two commands do all setup on a machine that has only Python 3.10+:
#   make demo   - fit the paper's Example 1 with I-PIA and IURS, print the table, save the figure
#   make test   - run the whole test suite (notebooks included)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,jaxopt]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/jurs demo

# Two pytest workers: on 2 cores the suite takes about 30 % less wall time than one
# (compilation is mostly single-threaded). On a GPU, JAX would give each worker 75 % of
# the device's memory up front; the workers allocate as they go instead.
test: $(STAMP)
	XLA_PYTHON_CLIENT_PREALLOCATE=false $(PY) -m pytest -q -n 2 --nbmake tests notebooks

bench: $(STAMP)
	$(PY) benchmarks/step_speed.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
