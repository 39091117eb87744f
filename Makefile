# Set-up and entry points. Every target builds the virtual environment it needs from the
# pinned requirements (requirements.txt) only when it is missing or older than that file.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
export PYTHONPATH := $(CURDIR)$(if $(PYTHONPATH),:$(PYTHONPATH))
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
# the machine-wide pip config points at local mirrors that may not exist: use PyPI only
export PIP_CONFIG_FILE := /dev/null
PYTEST_ARGS ?=

.PHONY: venv test demo bench gallery paper study clean

venv: $(STAMP)

$(STAMP): requirements.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade 'pip==26.3'
	$(PY) -m pip install --quiet -r requirements.txt
	@touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS) test

demo: $(STAMP)
	$(PY) -m sphere_servo.experiments.demo

bench: $(STAMP)
	$(PY) -m benchmarks.bench

gallery: $(STAMP)
	$(PY) -m sphere_servo.experiments.gallery

paper: $(STAMP)
	nice $(PY) -m sphere_servo.experiments.paper --out runs/paper --ros

study: $(STAMP)
	nice $(PY) -m sphere_servo.experiments.study --n 500 --out docs/study --resume

clean:
	rm -rf $(VENV) build install log
