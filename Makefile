# Set-up and everyday commands. Every target creates what it needs (.venv) on first use.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
TORCH   ?= torch==2.13.0

.PHONY: run test fuzz test-all lint bench learning clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# The CPU build first: a bare `torch` requirement could otherwise resolve to a CUDA build.
	$(BIN)/pip install -q "$(TORCH)"
	$(BIN)/pip install -q -e ".[dev,ray]"
	touch $(STAMP)

## run: the main job on its small built-in default: the quick study (about 29 minutes on 2 cores)
run: $(STAMP)
	$(BIN)/latentdrive reproduce runs/quick --preset quick --workers 2

## test: the default (fast) test suite
test: $(STAMP)
	$(BIN)/python -m pytest -q

## fuzz: the property tests with fresh random examples, 20x as many as the default suite
fuzz: $(STAMP)
	HYPOTHESIS_PROFILE=explore $(BIN)/python -m pytest -q tests/test_loaders_property.py tests/test_fileio.py tests/test_bad_input.py \
		tests/bnn/test_checkpoint.py tests/data/test_manifest_property.py

## test-all: every test, slow ones included
test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m ""

lint: $(STAMP)
	$(BIN)/ruff check latentdrive tests
	$(BIN)/mypy latentdrive tests
	$(BIN)/lint-imports

bench: $(STAMP)
	$(BIN)/latentdrive bench

## learning: the learning results of docs/learning.md (BNN, raw and latent policies, evaluation; an hour or more on 2 cores)
learning: $(STAMP)
	scripts/learning.sh

clean:
	rm -rf $(VENV) runs .pytest_cache .mypy_cache .ruff_cache .hypothesis
