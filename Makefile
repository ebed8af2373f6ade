# Two commands do all set-up on a fresh machine:
#   make demo   -- the main job on the embedded default (Moving Maze)
#   make test   -- the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test install clean

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU wheel first: it satisfies `torch>=2.3` so pip never fetches a CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cotpc reproduce maze --quick --out runs/quick

test: $(STAMP)
	$(PY) -m pytest

clean:
	rm -rf $(VENV) runs
