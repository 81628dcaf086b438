# Two entry points for a fresh machine with Python 3.11:
#   make demo   set up .venv, then run the main job on embedded defaults
#   make test   set up .venv, then run the test suite (what CI runs)
#   make docs   set up .venv, then build the documentation site into build/site (offline)
# PyTorch: TORCH=cpu (default: the CPU wheel, ~190 MB, from TORCH_INDEX beside your usual
# indexes), TORCH=cuda (PyPI's default Linux build with CUDA, several GB), or TORCH=skip (keep
# the torch already in the venv). To switch later: make clean setup TORCH=cuda
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= demo_out
TORCH  ?= cpu
TORCH_VERSION ?= 2.13.0

ifeq ($(TORCH),cpu)
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_WHAT  := CPU wheel, ~190 MB download
else ifeq ($(TORCH),cuda)
TORCH_INDEX ?=
TORCH_WHAT  := CUDA build, several GB download
else ifneq ($(TORCH),skip)
$(error TORCH must be cpu, cuda or skip, got '$(TORCH)')
endif
# An extra index, so that a wheel of the same version on your usual indexes or find-links
# (a local mirror) still counts. torch alone (--no-deps): its dependencies (sympy, networkx...)
# come with seqshape's from your usual indexes, and an unreachable TORCH_INDEX is asked once.
TORCH_PIP := $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX),)

.PHONY: setup demo test test-slow bench lint docs clean

$(VENV)/.installed: pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (set PYTHON=...)"; exit 1; }
	@echo "==> [1/4] creating $(VENV) with $(PYTHON)"
	$(PYTHON) -m venv $(VENV)
	@echo "==> [2/4] upgrading pip"
	$(PY) -m pip install -q --upgrade pip
ifeq ($(TORCH),skip)
	@echo "==> [3/4] TORCH=skip: keeping the torch in $(VENV) (seqshape needs torch>=2.2)"
else
	@echo "==> [3/4] installing torch $(TORCH_VERSION) ($(TORCH_WHAT)$(if $(TORCH_INDEX), from $(TORCH_INDEX)))"
	$(PY) -m pip install --progress-bar on --no-deps torch==$(TORCH_VERSION) $(TORCH_PIP)
endif
	@echo "==> [4/4] installing seqshape, torch's and its dependencies (numpy, scipy, trimesh, opencv, ...) and the dev tools"
	$(PY) -m pip install --progress-bar on -e '.[dev]'
	@echo "==> $(VENV) is ready: $(VENV)/bin/seqshape --help"
	@touch $@

setup: $(VENV)/.installed

demo: setup
	$(VENV)/bin/seqshape demo --out $(OUT)

test: setup
	$(PY) -m pytest -q -m "not slow"

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	for f in benchmarks/bm_*.py; do $(PY) $$f || exit 1; done

docs: setup
	$(VENV)/bin/mkdocs build --strict --site-dir build/site
	@echo "==> open build/site/index.html"

lint: setup
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/lint-imports --no-cache

clean:
	rm -rf $(VENV) $(OUT) build *.egg-info
