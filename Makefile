# Two commands do all set-up on a fresh machine:
#   make demo   -- the main job on the embedded default (Moving Maze)
#   make test   -- the test suite
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test install clean

# The kitchen extra (gymnasium-robotics + mujoco, CPU wheels) is small, so the main environment and CI have it:
# tests/test_kitchen.py runs instead of skipping.
$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The CPU wheel first: it satisfies `torch>=2.3` so pip never fetches a CUDA build.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,kitchen]'
	touch $(STAMP)

# ManiSkill3 lives in its own environment: mani-skill 3.0.1 needs numpy<2, the core uses what pip picks.
MS_VENV ?= .venv-ms
MS_STAMP := $(MS_VENV)/.installed

$(MS_STAMP): pyproject.toml
	python3 -m venv $(MS_VENV)
	$(MS_VENV)/bin/python -m pip install -q --upgrade pip
	$(MS_VENV)/bin/python -m pip install -q torch==2.13.0
	$(MS_VENV)/bin/python -m pip install -q -e '.[dev,maniskill]'
	touch $(MS_STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cotpc reproduce maze --quick --out runs/quick

test: $(STAMP) $(MS_STAMP)
	$(PY) -m pytest
	$(MS_VENV)/bin/python -m pytest tests/test_maniskill.py

clean:
	rm -rf $(VENV) $(MS_VENV) runs
