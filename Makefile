# The README's two set-up commands: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
PIP     = $(PY) -m pip
TORCH  ?= torch==2.13.0

.PHONY: demo test lint docs bench clean

$(VENV)/.base:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	# torch first and pinned: an unpinned torch would pull several GB of CUDA wheels.
	$(PIP) install --quiet $(TORCH)
	touch $@

$(VENV)/.installed: $(VENV)/.base pyproject.toml
	$(PIP) install --quiet -e ".[viz]"
	touch $@

$(VENV)/.installed-dev: $(VENV)/.base pyproject.toml
	$(PIP) install --quiet -e ".[dev]"
	touch $@

demo: $(VENV)/.installed
	$(PY) -m egorefine.cli demo --out results/demo

test: $(VENV)/.installed-dev
	$(PY) -m pytest -q

# The documentation site (docs/), warning-free as tests/test_docs.py checks; open docs/_build/html/index.html.
docs: $(VENV)/.installed-dev
	$(PY) -m sphinx -W --keep-going -b html docs docs/_build/html

lint: $(VENV)/.installed-dev
	$(PY) -m ruff check egorefine tests benchmarks

bench: $(VENV)/.installed-dev
	$(PY) benchmarks/stereo.py
	$(PY) benchmarks/real.py
	$(PY) benchmarks/learning.py
	$(PY) benchmarks/ego_motion.py
	$(PY) benchmarks/refine.py
	$(PY) benchmarks/euroc_static.py
	$(PY) benchmarks/autograd.py
	$(PY) benchmarks/speed.py
	$(PY) benchmarks/run_cli.py
	$(PY) benchmarks/plots.py

clean:
	rm -rf $(VENV) results .pytest_cache docs/_build
