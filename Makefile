# Every target works on a fresh clone of a machine that has only Python, pip and make.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEVSTAMP := $(VENV)/.installed-dev

.PHONY: demo test bench validate lint wheel-check clean system-deps

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

# Chromium and PostgreSQL from Debian's packages when missing (browser and store tests)
system-deps:
	.ci/system-deps

# two pytest workers, a test file each at a time (tests/conftest.py); TEST_WORKERS=0: one process
TEST_WORKERS ?= 2
test: $(DEVSTAMP) system-deps
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

validate: $(DEVSTAMP) system-deps
	ROBID_VALIDATE=1 $(BIN)/python -m pytest -q -m slow --timeout=3600

bench: $(DEVSTAMP)  # the link benches need the drivers' extras (modbus, serial)
	$(BIN)/python benchmarks/run.py

# the README's systemd route: a built wheel in a fresh venv, `robid demo` from outside the checkout
WHEEL := build/wheel-check
wheel-check: $(BIN)/python
	rm -rf $(WHEEL) && mkdir -p $(WHEEL)
	$(BIN)/python -m pip wheel -q --no-deps . -w $(WHEEL)/dist
	$(BIN)/python tests/check_wheel.py $(WHEEL)/dist/*.whl
	$(PY) -m venv $(WHEEL)/venv
	$(WHEEL)/venv/bin/python -m pip install -q $(WHEEL)/dist/*.whl
	cd "$$(mktemp -d)" && $(CURDIR)/$(WHEEL)/venv/bin/python -c \
		"import robid_link, sys; sys.exit('/site-packages/' not in robid_link.__file__)" \
		&& $(CURDIR)/$(WHEEL)/venv/bin/robid demo --out demo-out > demo.txt \
		&& tail -n 2 demo.txt && test -f demo-out/summary.txt

# ruff, then mypy on the package (it ships py.typed: users' type checkers read our annotations)
# as installed: drivers/, fakes/, examples/ under robid_link (.ci/mypy-tree; one run, all of it)
lint: $(DEVSTAMP)
	$(BIN)/ruff check robid_link drivers fakes tests benchmarks .ci/mypy-tree
	$(BIN)/python .ci/mypy-tree

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
