# Two entry points (see README): `make run` (DPSOC-EM experiment + report), `make test`.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
TASK ?= linear2d
OUT ?= runs/compare-$(TASK)

.PHONY: install run test test-slow lint bench verify api-docs clean

$(BIN)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $@

install: $(BIN)/.installed

run: install
	$(BIN)/soc-opt compare $(TASK) --out $(OUT)

# the default suite on TEST_WORKERS processes (pytest-xdist); the Ray tests share one (their xdist_group)
TEST_WORKERS ?= 2
test: install
	$(BIN)/ruff check soc_opt tests examples && $(BIN)/lint-imports && $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadgroup

lint: install
	$(BIN)/ruff check soc_opt tests examples && $(BIN)/lint-imports

test-slow: install
	$(BIN)/python -m pytest -m slow

verify: install
	$(BIN)/soc-opt verify

bench: install
	$(BIN)/soc-opt bench

# the API reference from the docstrings (pdoc, offline) into build/api, every link between its pages checked
api-docs: install
	$(BIN)/python -m soc_opt.api_doc --out build/api

clean:
	rm -rf $(VENV) runs .pytest_cache
