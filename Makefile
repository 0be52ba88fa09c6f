# Two set-up commands: `make demo` and `make test`; both create .venv on a fresh machine.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install docs demo demo-hmi test test-portable test-linuxcnc demo-linuxcnc demo-compensate demo-linuxcnc-head demo-fleet linuxcnc-up linuxcnc-down lint bench golden peers clean
LCNC_ENV := .peers/linuxcnc.env

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (Python 3.11 is required)"; exit 2; }
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	@# a venv whose creation was interrupted has a python but no pip: give it one back
	@$(BIN)/python -m pip --version >/dev/null 2>&1 || $(BIN)/python -m ensurepip --upgrade >/dev/null
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,docs]'
	@# An editable install leaves our sources uncompiled; with PYTHONDONTWRITEBYTECODE set (as on
	@# some shop PCs and CI images) every command would compile them again (~0.16 s CPU each).
	$(BIN)/python -m compileall -q -j 0 identification contracts programs drivers simulators daemon demos
	@touch $(STAMP)

install: $(STAMP)

# PROFILE=sinumerik: the control's own OPC UA server as Siemens ships it (default: the gateway)
PROFILE ?= gateway
demo: $(STAMP)
	$(BIN)/python -m demos.e2e --profile $(PROFILE)

# simulated CNC + daemon + HMI until Ctrl-C; prints the URL and a one-time login (HMI_PORT=0: any)
HMI_PORT ?= 8470
demo-hmi: $(STAMP)
	$(BIN)/python -m demos.hmi --port $(HMI_PORT)

# pytest-xdist workers: many tests wait on peers and sockets, so one more worker than cores
# keeps both cores busy (TEST_WORKERS=0 runs in one process).
TEST_WORKERS ?= 3
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal

# The suite as another machine runs it: OpenBLAS on another CPU's kernels (Prescott on x86-64:
# SSE3 only, unlike any recent CPU's own), BLAS_THREADS BLAS threads, the modules and tests in a
# shuffled order (SEED, printed in pytest's header; default from the commit) and a CPU hog beside
# it (HOG=0: none). A test pinned to one CPU's last bits, to the order or to the machine's speed
# fails here before it fails in CI on another box. .ci/run runs the suite this way (no hog: the
# LinuxCNC suite runs beside it).
SEED ?= $(shell git rev-parse --short HEAD 2>/dev/null || echo 1)
HOG ?= 1
BLAS_THREADS ?= 2
PORTABLE_CORE := $(if $(filter x86_64,$(shell uname -m)),Prescott,$(if $(filter aarch64,$(shell uname -m)),ARMV8,))
test-portable: $(STAMP)
	@if [ "$(HOG)" = 1 ]; then $(BIN)/python -c 'while 1: pass' & trap "kill $$!" EXIT; fi; \
	OPENBLAS_CORETYPE=$(PORTABLE_CORE) OPENBLAS_NUM_THREADS=$(BLAS_THREADS) RUMBA_TEST_SHUFFLE=$(SEED) \
	  $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal

test-linuxcnc: $(STAMP)
	bash .ci/install-peers.sh linuxcnc
	$(BIN)/python -m pytest -q -p no:xdist -m linuxcnc

# LinuxCNC 2.9 headless with the HAL probe carrying our truth model (config/linuxcnc/).
linuxcnc-up: $(STAMP)
	bash .ci/install-peers.sh linuxcnc
	@mkdir -p .peers
	$(BIN)/python -m simulators.linuxcnc_peer up > $(LCNC_ENV)
	@cat $(LCNC_ENV)

linuxcnc-down: $(STAMP)
	@if [ -f $(LCNC_ENV) ]; then $(BIN)/python -m simulators.linuxcnc_peer down "$$(sed -n 's/^LCNC_DIR=//p' $(LCNC_ENV))" && rm -f $(LCNC_ENV); else echo "no LinuxCNC from make linuxcnc-up"; fi

demo-linuxcnc: $(STAMP)
	bash .ci/install-peers.sh linuxcnc
	$(BIN)/python -m demos.linuxcnc

# verify, compensate (kins pins live + HAL file), verify again: pivot errors before / after
demo-compensate: $(STAMP)
	bash .ci/install-peers.sh linuxcnc
	$(BIN)/python -m demos.compensate

# the same on a swivel head B + table C whose kinematics are rumba's own LinuxCNC kins module
# (config/linuxcnc/xyzbc_head_kins.comp: built with halcompile and installed, as root)
demo-linuxcnc-head: $(STAMP)
	bash .ci/install-peers.sh linuxcnc
	$(BIN)/python -m demos.compensate_head

demo-fleet: $(STAMP)
	bash .ci/install-peers.sh postgresql mosquitto
	$(BIN)/python -m demos.fleet

# The manual: reference pages regenerated from the code (docs/gen), then the site built into
# build/site with every warning an error (links, anchors, includes). Open build/site/index.html.
docs: $(STAMP)
	$(BIN)/python -m docs.gen
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python -m benchmarks

golden: $(STAMP)
	$(BIN)/python -m tests.regen_golden

peers:
	bash .ci/install-peers.sh

clean:
	rm -rf $(VENV) build *.egg-info
