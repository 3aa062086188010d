# One-command set-up: `make test` and `make demo` create .venv in this folder and install everything.
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
ifeq ($(OS),Windows_NT)
BIN     = $(VENV)/Scripts
endif
STAMP   = $(VENV)/.installed

.PHONY: test test-fast lint docs demo install install-cpu bench clean

$(STAMP): requirements.txt requirements-dev.txt pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements-dev.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	@touch $(STAMP)

install: $(STAMP)

# PyTorch's CPU build first (no CUDA wheels); `make install` then finds torch and torchvision satisfied
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
install-cpu:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --index-url $(TORCH_CPU_INDEX) "torch>=2.14" "torchvision>=0.29"
	$(MAKE) install

test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 MPLBACKEND=Agg $(BIN)/python -m pytest -q -rs --durations=15 $(PYTEST_ARGS)

# ruff (pyproject.toml): lint findings and unformatted files both fail; `ruff format .` and `ruff check --fix .` mend
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# the documentation site (mkdocs.yml) into site/; strict: a broken link or a docstring mkdocstrings cannot read fails
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

# the quick loop: everything but the tests marked slow (docs/development.md, "Test tiers")
test-fast: $(STAMP)
	OPENBLAS_NUM_THREADS=1 MPLBACKEND=Agg $(BIN)/python -m pytest -q -rs --durations=15 -m "not slow" $(PYTEST_ARGS)

# Ctrl-C: the demo prints one line and exits 130. From a terminal make gets the same SIGINT and ends by it (status
# 130): the shell ignores SIGINT (the demo re-enables it) and hides that 130 from make, so make adds no "Error
# 130"/"Interrupt" line. Where make itself ignores SIGINT (started in the background by a script: `make demo &`;
# its SigIgn mask in /proc) it cannot end by the signal: the 130 is passed on and make exits 2, never 0.
demo: $(STAMP)
	@trap '' INT; MPLBACKEND=Agg $(BIN)/python -m matchplant.demo $(DEMO_ARGS) || { s=$$?; \
	  if [ $$s -eq 130 ] && ! grep -qs '^SigIgn:.*[2367abef]$$' /proc/$$PPID/status; then exit 0; fi; exit $$s; }

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -r requirements-bench.txt
	$(BIN)/python -m bench $(BENCH_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache site
