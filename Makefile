# tumblenav: two commands matter: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test lint venv clean docs

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/tumblenav demo -o out/demo

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy src/tumblenav

# lint, the layering contracts of ../shared/design.md (pyproject [tool.importlinter]), the
# docs build, then the tests (last, so that pytest's summary closes the output)
test: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy src/tumblenav
	$(MAKE) --no-print-directory docs
	$(PY) -m pytest -q

# the user guide and API reference (mkdocs.yml) into out/site; a warning fails it (not with
# --quiet: it hides the warnings from the strict check, and the build passes)
docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict -d out/site

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache .hypothesis
