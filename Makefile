# yawil: two commands on a fresh machine, `make demo` and `make test`.
# Each creates .venv by itself and skips that step when nothing changed.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv test test-all demo lint bench clean

$(STAMP): pyproject.toml constraints.txt
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade --quiet pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e ".[dev]"
	@touch $(STAMP)

venv: $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" -p no:cacheprovider

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/mypy src/yawil

demo: $(STAMP)
	$(BIN)/yawil demo --out runs/demo

bench: $(STAMP)
	$(BIN)/python benchmarks/models.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
