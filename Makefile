# Two commands do everything on a fresh machine: `make run` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.netpose-installed
CONFIG ?= config/demo.toml
# Extra options for `make run`, e.g. ARGS="--set web.enabled=true" for the web page.
ARGS ?=

BOOKWORM_VENV ?= .venv-bookworm
BOOKWORM_STAMP := $(BOOKWORM_VENV)/.netpose-installed

.PHONY: run test test-bookworm lint typecheck imports pytest bench install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[opencv,plot,test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/netpose run --config $(CONFIG) $(ARGS)

test: lint typecheck imports pytest

lint: $(STAMP)
	$(BIN)/ruff check .

typecheck: $(STAMP)
	$(BIN)/mypy

# The dependency rules between core, drivers and the application (pyproject.toml).
imports: $(STAMP)
	$(BIN)/lint-imports

pytest: $(STAMP)
	$(BIN)/pytest -q

# The suite again on Debian bookworm's versions (numpy 1.24, scipy 1.10, OpenCV 4.6): what a
# Raspberry Pi runs. .ci/run calls it after `make test`.
$(BOOKWORM_STAMP): pyproject.toml .ci/bookworm-constraints.txt
	$(PYTHON) -m venv $(BOOKWORM_VENV)
	$(BOOKWORM_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(BOOKWORM_VENV)/bin/python -m pip install --quiet -c .ci/bookworm-constraints.txt \
		-e '.[opencv,plot,test]'
	touch $(BOOKWORM_STAMP)

test-bookworm: $(BOOKWORM_STAMP)
	$(BOOKWORM_VENV)/bin/pytest -q

bench: $(STAMP)
	$(BIN)/netpose bench speed
	$(BIN)/netpose bench accuracy

# On the ROV (as root): user, venv in /opt/netpose, unit, /etc/netpose. See docs/daemon.md.
install:
	systemd/install.sh

clean:
	rm -rf $(VENV) $(BOOKWORM_VENV) build *.egg-info .mypy_cache .pytest_cache .ruff_cache
