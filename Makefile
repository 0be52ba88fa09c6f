# Two set-up commands: `make demo` and `make test`; both create .venv on a fresh machine.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-linuxcnc lint bench golden peers clean

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (Python 3.11 is required)"; exit 2; }
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m daemon.demo_e2e

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-linuxcnc: $(STAMP)
	$(BIN)/python -m pytest -q -m linuxcnc

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
