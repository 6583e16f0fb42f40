# Every target works on a fresh clone of a machine that has only Python, pip and make.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEVSTAMP := $(VENV)/.installed-dev

.PHONY: demo test bench validate lint clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(DEVSTAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@ $(STAMP)

demo: $(STAMP)
	$(BIN)/robid demo

test: $(DEVSTAMP)
	$(BIN)/python -m pytest -q

validate: $(DEVSTAMP)
	ROBID_VALIDATE=1 $(BIN)/python -m pytest -q -m slow --timeout=3600

bench: $(DEVSTAMP)  # the link benches need the drivers' extras (modbus, serial)
	$(BIN)/python benchmarks/run.py

lint: $(DEVSTAMP)
	$(BIN)/ruff check robid_link drivers fakes tests benchmarks

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
