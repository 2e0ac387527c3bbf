# Every target sets itself up: a virtualenv in .venv with every distribution of the workspace
# (editable) and the dev tools, at the versions of uv.lock. Needs only python3 (3.11+) and make.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
UV_VERSION := 0.13.8
MANIFESTS := Makefile pyproject.toml uv.lock core/pyproject.toml client/pyproject.toml \
	$(wildcard services/*/pyproject.toml) $(wildcard integrations/*/pyproject.toml)

.PHONY: demo test test-fast lint typecheck docs format proto lock clean

# --compile-bytecode: uv leaves the .pyc files to the first import, and with
# PYTHONDONTWRITEBYTECODE set (as on our machines) every process would compile
# scipy, fastapi and filterpy again: 5-6 s instead of 2 s to start a service.
# compileall does the same for the workspace's own (editable) sources.
$(STAMP): $(MANIFESTS)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	test -x $(BIN)/uv || $(BIN)/python -m pip install --quiet "uv==$(UV_VERSION)"
	VIRTUAL_ENV=$(abspath $(VENV)) $(BIN)/uv sync --locked --all-packages --active --quiet --compile-bytecode
	$(BIN)/python -m compileall -q -x '/tests/' core client services integrations
	touch $(STAMP)

## The main job: a demo scan of a simulated slide.
demo: $(STAMP)
	$(BIN)/focustrack demo --tissue-slide --out out/demo --json out/demo/demo.json

# One pytest worker per core; a test file's tests stay on one worker (they share fixtures).
PYTEST := $(BIN)/pytest -n auto --dist loadfile

## Lint, format check, types, import boundaries, the docs and the whole test suite (what CI runs).
test: lint typecheck docs
	$(PYTEST)

## The same without the slow end-to-end tests (for a quick look while developing).
test-fast: lint typecheck docs
	$(PYTEST) -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

typecheck: $(STAMP)
	$(BIN)/mypy

## The documentation site from docs/ (mkdocs, material theme) into site/; --strict fails
## on any warning, such as a link to a page or anchor that does not exist.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

## Regenerate the Python code of the wire schemas in proto/ (checked in; a test compares).
proto: $(STAMP)
	$(BIN)/python proto/generate.py

## Re-resolve uv.lock after a change of dependencies, and each service's requirements.txt.
lock: $(STAMP)
	$(BIN)/uv lock
	$(BIN)/python scripts/export_requirements.py

clean:
	rm -rf $(VENV) out site .pytest_cache .ruff_cache .mypy_cache
