# `make demo` and `make test` create .venv when missing and install surftrack into it.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
STAMP := $(VENV)/.surftrack-installed
# CPU build of torch unless an NVIDIA GPU is present (an unpinned torch pulls a multi-GB CUDA build).
TORCH_CPU ?= torch==2.13.0
# e.g. https://download.pytorch.org/whl/cpu where pip's own index would serve a CUDA build
TORCH_INDEX ?=

.PHONY: install demo test test-slow bench clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	if ! command -v nvidia-smi >/dev/null 2>&1; then $(PY) -m pip install --quiet $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) "$(TORCH_CPU)"; fi
	$(PY) -m pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

demo: install
	$(VENV)/bin/surftrack demo --out out/demo

test: install
	$(PY) -m pytest -q -m "not slow" -n 2 --dist loadgroup

test-slow: install
	$(PY) -m pytest -q -m slow

bench: install
	$(PY) pipelines/bench_render.py

clean:
	rm -rf $(VENV) out .pytest_cache
