# The two commands of the README:
#   make demo   simulates the embedded default sequence once, runs the main frontends x backends
#               on it and prints the errors (creates .venv on first use; no data needed)
#   make test   runs the test suite (creates .venv on first use)
# Also: make kitti   runs kiss-icp on the real KITTI extract in $(DATA)
VENV ?= .venv
PYTHON ?= python3
DATA ?= ../shared/data
DEMO_SEQ ?= $(DATA)/kitti-odometry-00-first16
export VENV PYTHON

STAMP := $(VENV)/.flowslam-installed

.PHONY: demo kitti test setup clean-venv

$(STAMP): pyproject.toml tools/setup_env.sh
	bash tools/setup_env.sh
	touch $@

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/flowslam demo

kitti: $(STAMP)
	$(VENV)/bin/flowslam run --frontend kiss-icp --backend odometry $(DEMO_SEQ)

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

clean-venv:
	rm -rf $(VENV)
