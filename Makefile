# Two commands for a newcomer: `make train` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH := torch==2.13.0
RUN ?= runs/default
EPISODES ?= 50000

.PHONY: install train test lint bench clean

$(BIN)/bitcomm: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q $(TORCH)
	$(BIN)/pip install -q -e ".[dev]"
	touch $(BIN)/bitcomm

install: $(BIN)/bitcomm

train: install
	$(BIN)/bitcomm train --estimator improved --messages bitwise --episodes $(EPISODES) --out $(RUN)
	$(BIN)/bitcomm eval $(RUN) --episodes 2000 --seed 0

test: install
	$(BIN)/python -m pytest

lint: install
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/mypy

bench: install
	$(BIN)/python benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) runs build *.egg-info src/*.egg-info
