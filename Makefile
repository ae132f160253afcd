# Entry points: `make demo`, `make test` and `make docs`. Each creates .venv on first use, with the
# package and every extra (studies, physics, docs, dev, baselines) installed.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test docs lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first, pinned: this pin resolves to the local CPU wheel (no CUDA download); a bare
	# `torch` (or the package's own `torch>=2.2`, were torch not installed yet) would pull CUDA.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[studies,physics,docs,dev,baselines]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/lcs-cvx demo

test: $(STAMP)
	$(PY) -m pytest -q

docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

lint: $(STAMP)
	$(VENV)/bin/ruff check lcs_cvx tests studies

bench: $(STAMP)
	$(VENV)/bin/lcs-cvx bench

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache site
