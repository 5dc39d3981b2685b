# orchard_mapping developer targets. Everything runs from the project venv
# (.venv), which `make setup` creates and keeps up to date (scripts/setup.sh).

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := test

VENV   ?= .venv
PYTHON ?= python3
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.setup-stamp
PYTEST_ARGS ?=

# Every process started from here keeps DDS discovery on loopback.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export PIP_DISABLE_PIP_VERSION_CHECK := 1
export VENV PYTHON

# Inputs of the set-up: any change re-runs scripts/setup.sh (pip and the CMake
# build are incremental, so a re-run only does what changed).
SETUP_INPUTS := requirements.lock setup.py setup.cfg package.xml \
                scripts/setup.sh cmake/fix_wheel_includes.cmake \
                $(shell find orchard_mapping_msgs vendor -type f 2>/dev/null)

.PHONY: setup lint test test-slow test-portable demo bench fixtures clean train-setup

setup: $(STAMP)

$(STAMP): $(SETUP_INPUTS)
	bash scripts/setup.sh
	touch $@

# ruff (pinned in requirements.lock, rules in ruff.toml); any finding fails. `.ci/run` runs it before the tests.
LINT_PATHS := orchard_mapping/ benchmarks/ test/ scripts/
lint: setup
	$(VENV)/bin/ruff check $(LINT_PATHS)

# pytest exit 5 means "no tests collected": report it plainly and fail.
# -p no:dash: the pytest plugin of dash (pulled in by open3d) is not ours.
# The test files run on TEST_WORKERS pytest-xdist workers (2: the project's 2-core machine; 0 runs them in
# this process), a file's tests on one worker; rows shared by several files are made once (test/conftest.py).
# `make test` leaves out the tests marked slow (end-to-end runs of minutes each); `make test-slow` runs them.
# `.ci/run` runs both.
TEST_WORKERS ?= 2
# $(1): the marker expression of the tests to run
define run_pytest
@rc=0; $(PY) -m pytest test -q -ra --durations=15 --timeout=1800 -p no:dash -n $(TEST_WORKERS) --dist loadfile \
  -m $(1) $(PYTEST_ARGS) || rc=$$?; \
if [ $$rc -eq 5 ]; then echo "make $@: pytest collected no tests (exit 5)" >&2; fi; \
exit $$rc
endef

test: setup
	$(call run_pytest,"not slow")

test-slow: setup
	$(call run_pytest,slow)

# The accuracy tests again with OpenCV's optimised paths off, on one thread, and on two other seeds
# (test/conftest.py); prints one table (build/accuracy_table.md) and fails on a check within 20 % of its limit.
# PORTABLE_JOBS=2 runs two of the five runs at a time.
test-portable: setup
	bash scripts/test_portable.sh $(PYTEST_ARGS)

# The fixture recordings in bags/: the commands in bags/README.md, run again.
fixtures: setup
	grep '^orchard-map simulate ' bags/README.md | while read -r cmd; do $(VENV)/bin/$$cmd; done

# The furthest stage that exists: simulate a row, read it back, reconstruct each side with its trunks and
# local grounds, evaluate (prints the per-side trunk table beside the truth).
demo: setup
	$(VENV)/bin/orchard-map simulate --scenario standard --trees 3 --seed 0 --set camera.rate_hz=10 --out demo_out/sim --force
	$(VENV)/bin/orchard-map inspect demo_out/sim
	rm -rf demo_out/result
	@echo "Trunks: found by the shipped detector (models/trunk_maskrcnn.onnx, trunks.source=model)."
	$(VENV)/bin/orchard-map run demo_out/sim/front demo_out/sim/back --out demo_out/result
	$(VENV)/bin/orchard-map evaluate --truth demo_out/sim/ground_truth.json --result demo_out/result

# The training-only extra (torch, torchvision) for `orchard-map train-detector`; never part of `make setup`.
train-setup: setup
	$(VENV)/bin/pip install -r requirements-train.lock

bench: setup
	@shopt -s nullglob; files=(benchmarks/*.py); \
	if [ $${#files[@]} -eq 0 ]; then echo "make bench: no benchmarks/*.py"; exit 0; fi; \
	for f in "$${files[@]}"; do echo "== $$f"; $(PY) "$$f"; done

clean:
	rm -rf $(VENV) build demo_out .pytest_cache *.egg-info
	find . -name __pycache__ -type d -not -path './.git/*' -prune -exec rm -rf {} +
