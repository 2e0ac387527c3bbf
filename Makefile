# Every target sets itself up: a virtualenv in .venv with the project and its dev tools.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint format proto clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

## The main job: a demo scan of a simulated slide.
demo: $(STAMP)
	$(BIN)/focustrack demo --out out/demo --json out/demo/demo.json

## Lint, format check and the whole test suite.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

## Regenerate the Python code of the wire schemas in proto/ (checked in; a test compares).
proto: $(STAMP)
	$(BIN)/python -m focustrack.wire.generate

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
