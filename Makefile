# The two commands of the README.  Each creates .venv and installs the package with
# the CPU constraints on first use (or when pyproject.toml changes), then reuses it.
#   make demo   - the main job: every stage on the embedded demo design (writes ./demo-out/)
#   make test   - the test suite (`make test-slow` for the long statistical checks)
PYTHON ?= python3
VENV   ?= .venv
# where pip finds the CPU build of torch when it does not already (e.g. no local wheel folder):
#   make demo TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH_INDEX ?=
PIP_INDEX = $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX),)
BIN     = $(VENV)/bin
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1
# test processes (pytest-xdist; one file per worker at a time, one thread each): `make test TEST_WORKERS=1` for one
TEST_WORKERS ?= 2
XDIST = $(if $(filter-out 0 1,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile,)

.PHONY: demo test test-slow install clean docs

$(BIN)/metadesign: pyproject.toml setup.py constraints/cpu.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q $(PIP_INDEX) -c constraints/cpu.txt -e '.[test]'
	touch $@

install: $(BIN)/metadesign

demo: install
	$(BIN)/metadesign demo

test: install
	$(BIN)/python -m pytest $(XDIST)

test-slow: install
	$(BIN)/python -m pytest -m slow $(XDIST)

clean:
	rm -rf demo-out .pytest_cache docs/_build docs/gallery

# the documentation site (Sphinx; examples execute at build time; warnings are errors): docs/_build/html
DOCS_STAMP = $(VENV)/.docs-installed
$(DOCS_STAMP): $(BIN)/metadesign
	$(BIN)/python -m pip install -q $(PIP_INDEX) -c constraints/cpu.txt -e '.[test,docs]'
	touch $@

docs: $(DOCS_STAMP)
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html
