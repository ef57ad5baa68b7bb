# bevo_ros developer entry points. Quick start: `make demo`, then `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
# DDS must never multicast onto the network: keep discovery on this host.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= 42
export PYTHONUNBUFFERED := 1
# pip's offline mirror warns about every package it does not carry; keep real errors visible.
# (braces: `|| true` must cover only grep, or it would also swallow a failing pip under pipefail)
PIP_FILTER := { grep -v -E "Location '.*' is ignored" || true; }

.PHONY: setup test demo bench lock clean

setup: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml tools/build_tf2_msgs.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "[setup] installing pinned requirements into $(VENV) (fast when nothing changed)"
	@set -o pipefail; $(PY) -m pip install -q --disable-pip-version-check -r requirements.txt 2>&1 | $(PIP_FILTER)
	@set -o pipefail; $(PY) -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e . 2>&1 | $(PIP_FILTER)
	@# tf2_msgs has no wheel: build TFMessage from its interface into the venv (stamped, seconds).
	@bash tools/build_tf2_msgs.sh $(VENV)
	@touch $(STAMP)
	@echo "[setup] done"

test: setup
	$(PY) -m pytest

demo: setup
	$(VENV)/bin/bevo demo

bench: setup
	$(PY) tools/bench_core.py

# Re-resolve requirements.in into the fully pinned requirements.txt.
lock:
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --dry-run --ignore-installed --report /tmp/bevo-lock.json -r requirements.in 2>&1 | $(PIP_FILTER)
	$(PY) tools/write_lock.py /tmp/bevo-lock.json requirements.txt

clean:
	rm -rf build install log out .pytest_cache
