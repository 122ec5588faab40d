# yawil: two commands on a fresh machine, `make demo` and `make test`.
# Each creates .venv by itself and skips that step when nothing changed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv test test-all demo lint bench clean browser

$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade --quiet pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[dev]"
	@touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider

test-all: $(STAMP) browser
	$(BIN)/python -m pytest -q -p no:cacheprovider

# the demo report's browser check (tests/pipelines/test_demo_browser.py): Debian's Chromium
browser:
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
		{ apt-get install -y --no-install-recommends chromium 2>/dev/null || sudo apt-get install -y --no-install-recommends chromium; }

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/mypy src/yawil

demo: $(STAMP)
	$(BIN)/yawil demo --out runs/demo

bench: $(STAMP)
	$(BIN)/python benchmarks/models.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
