# Entry points: `make demo`, `make test` and `make docs`. Each creates .venv on first use: `make demo`
# with the package alone (what the demo needs), the others with every extra too (studies, plot, logs,
# physics, docs, dev, baselines, control, solvers), installed at the versions of
# constraints.txt (the versions the suite last passed with); `make lock` refreshes that file.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
CORE   := $(VENV)/.core
STAMP  := $(VENV)/.installed
# test workers (pytest-xdist): one per core; a file's tests on one worker (its fixtures built once)
JOBS   ?= auto
EXTRAS := studies,plot,logs,physics,docs,dev,baselines,control,solvers
# torch first, pinned: this pin resolves to the local CPU wheel (no CUDA download); a bare
# `torch` (or the package's own `torch>=2.2`, were torch not installed yet) would pull CUDA.
TORCH  := torch==2.13.0
# qpth (a differentiable QP layer of the solver study) declares numpy<2, which the rest of the
# stack cannot meet; it runs on numpy 2, so it is installed without its declared dependencies
# (torch and numpy, both already here).
QPTH   := qpth==0.0.18
# Drake (the cube study's second physics reference, dair_pll's simulator) declares Mosek, a
# commercial solver's Python package: installed, CVXPY lists MOSEK first among its solvers and
# prefers it, unlicensed. Drake's simulation needs only numpy and PyYAML (both already here), so it
# is installed without its declared dependencies.
DRAKE  := drake==1.51.1

.PHONY: demo test test-portable docs lint bench lock clean

$(CORE): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt $(TORCH)
	$(PY) -m pip install --quiet -c constraints.txt -e .
	touch $(CORE)

$(STAMP): $(CORE)
	$(PY) -m pip install --quiet -c constraints.txt -e '.[$(EXTRAS)]'
	$(PY) -m pip install --quiet -c constraints.txt --no-deps $(QPTH)
	$(PY) -m pip install --quiet -c constraints.txt --no-deps $(DRAKE)
	touch $(STAMP)

# constraints.txt anew: a throw-away environment with the newest versions pyproject.toml allows,
# frozen. Run `make test` after it; commit the file when the suite passes with it.
lock:
	rm -rf .lock-venv
	$(PYTHON) -m venv .lock-venv
	.lock-venv/bin/python -m pip install --quiet --upgrade pip
	.lock-venv/bin/python -m pip install --quiet $(TORCH)
	.lock-venv/bin/python -m pip install --quiet -e '.[$(EXTRAS)]'
	.lock-venv/bin/python -m pip install --quiet --no-deps $(QPTH)
	.lock-venv/bin/python -m pip install --quiet --no-deps $(DRAKE)
	{ echo "# The versions the test suite passes with; written by 'make lock' (pip freeze)."; \
	  .lock-venv/bin/python -m pip freeze --exclude-editable; } > constraints.txt
	rm -rf .lock-venv

demo: $(CORE)
	$(VENV)/bin/lcs-cvx demo

test: $(STAMP)
	$(PY) -m pytest -q -n $(JOBS) --dist loadfile

# The suite again as on another processor (tools/other-cpus: numba, torch and BLAS on the code
# paths of a generic x86-64 CPU by default; CPUS="generic avx2 avx512" for more), so that a test
# asserting a fact of this machine's round-off fails here and not on a user's machine.
CPUS ?= generic
test-portable: $(STAMP)
	CPUS="$(CPUS)" PY=$(PY) bash tools/other-cpus -n $(JOBS) --dist loadfile

docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

lint: $(STAMP)
	$(VENV)/bin/ruff check lcs_cvx tests studies

bench: $(STAMP)
	$(VENV)/bin/lcs-cvx bench

clean:
	rm -rf $(VENV) .lock-venv *.egg-info .pytest_cache site
