# Two commands for a newcomer: `make train` and `make test`. Both create .venv on first use, with the
# optional extras (mpe: MPE2 tasks for the channel wrapper; ray: the Ray backend) so the tests cover them.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH := torch==2.13.0
RUN ?= runs/default
EPISODES ?= 200000
# torch threads; empty: bitcomm picks the cores the load average leaves free (a thread on a busy core
# costs more than it gives: with one other busy core, 2 threads trained 2.9x slower than 1)
THREADS ?=

.PHONY: install train test lint bench clean

$(BIN)/bitcomm: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q $(TORCH)
	$(BIN)/pip install -q -e ".[dev,mpe,ray]"
	touch $(BIN)/bitcomm

install: $(BIN)/bitcomm

# Re-runnable: a RUN with a checkpoint is resumed (a finished one just evaluated again); a RUN that exists
# without one is left alone and a fresh RUN-<date>-<time> is used. Which one is printed first.
train: install
	@run="$(RUN)"; resume=""; \
	if [ -f "$$run/checkpoints/latest.json" ]; then resume="--resume"; echo "make train: resuming $$run"; \
	elif [ -e "$$run" ]; then run="$(RUN)-$$(date +%Y%m%d-%H%M%S)"; \
		echo "make train: $(RUN) exists without a checkpoint; training a fresh run in $$run"; \
	else echo "make train: training a fresh run in $$run"; fi; \
	$(BIN)/bitcomm train --estimator improved --messages bitwise --episodes $(EPISODES) --out "$$run" $$resume \
		$(if $(THREADS),--threads $(THREADS)) && \
	$(BIN)/bitcomm eval "$$run" --episodes 2000 --seed 0

# the suite's files split over TEST_JOBS processes (pytest-xdist), whole files to one process so a module's
# shared study is trained once; tests/conftest.py gives each process one torch thread
TEST_JOBS ?= 2
test: install
	$(BIN)/python -m pytest -n $(TEST_JOBS) --dist loadfile

lint: install
	$(BIN)/ruff check src tests benchmarks setup.py
	$(BIN)/ruff format --check src tests benchmarks setup.py
	$(BIN)/mypy

bench: install
	$(BIN)/python benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) runs build *.egg-info src/*.egg-info
