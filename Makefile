# Entry points on a fresh machine: `make demo` (main job), `make test` (every test: what CI runs), `make test-fast`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# The CPU wheel of torch 2.13.0 lies on these machines' disk; elsewhere set TORCH_SPEC (e.g. TORCH_SPEC=torch for CUDA).
TORCH_SPEC ?= torch==2.13.0

.PHONY: install demo test test-fast clean

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/mapsqueeze demo

test: install
	$(PY) -m pytest tests

test-fast: install
	$(PY) -m pytest tests -m "not slow"

clean:
	rm -rf $(VENV) build dist src/*.egg-info
