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

.PHONY: venv test demo bench gallery paper study video replay browser clean

venv: $(STAMP)

$(STAMP): requirements.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade 'pip==26.3'
	$(PY) -m pip install --quiet -r requirements.txt
	@touch $(STAMP)

# Two phases: the tests without ROS (pure computation, no timing) on both cores, then the ROS
# tests one at a time, as before: several at once would load the machine under the timing
# tests (late delivery, the cut link) and make them measure each other. Both phases always
# run; the exit code is the first failing phase's (5, "no test selected" by PYTEST_ARGS in
# one phase, is not a failure unless neither ran a test).
test: $(STAMP) browser
	@$(PY) -m pytest -q -n 2 -m 'not ros' $(PYTEST_ARGS) test; a=$$?; \
	$(PY) -m pytest -q -m ros $(PYTEST_ARGS) test; b=$$?; \
	if [ $$a = 5 ] && [ $$b = 5 ]; then exit 5; fi; \
	[ $$a = 5 ] && a=0; [ $$b = 5 ] && b=0; \
	exit $$(( a != 0 ? a : b ))

# The replay page's test opens it in Debian's chromium: install it when missing (apt-get, as
# root, as in CI). If that cannot be done, say why here and in the log the test then fails
# with; the other tests still run.
CHROMIUM_LOG := $(VENV)/chromium-install.log
browser: $(STAMP)
	@command -v chromium >/dev/null 2>&1 || { \
	  echo "make: installing Debian's chromium for the replay page's browser test"; \
	  if [ "$$(id -u)" = 0 ]; then \
	    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	      apt-get install -y -qq chromium; } > $(CHROMIUM_LOG) 2>&1; \
	  else echo "not root: cannot apt-get install chromium" > $(CHROMIUM_LOG); fi; \
	  command -v chromium >/dev/null 2>&1 || { \
	    echo "make: chromium could not be installed (see $(CHROMIUM_LOG)); the browser" \
	         "test will fail"; tail -3 $(CHROMIUM_LOG); }; }

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

# a video (servo.mp4 + servo.gif) and a 3-D replay page (replay.html) of a recorded run:
#   make video BAG=runs/<timestamp>/bag     make replay BAG=runs/<timestamp>/bag
video: $(STAMP)
	$(if $(BAG),,$(error give the run's bag: make video BAG=runs/<timestamp>/bag))
	$(PY) -m sphere_servo.experiments.video $(BAG) --gif $(VIDEO_ARGS)

replay: $(STAMP)
	$(if $(BAG),,$(error give the run's bag: make replay BAG=runs/<timestamp>/bag))
	$(PY) -m sphere_servo.experiments.replay3d $(BAG) $(REPLAY_ARGS)

clean:
	rm -rf $(VENV) build install log
