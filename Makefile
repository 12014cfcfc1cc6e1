# Every target creates .venv itself on a fresh machine that has only python3 and make.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test bench lint format clean

$(VENV)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

$(VENV): $(VENV)/.installed

demo: $(VENV)
	$(BIN)/fpe demo --out out/demo --force

# PYTHONDONTWRITEBYTECODE empty: the suite's fpe processes read the package's compiled bytecode
# rather than compile it each, and a second run reuses pytest's rewritten test modules
test: $(VENV)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -q -n 2 --dist loadfile --no-loadscope-reorder

bench: $(VENV)
	$(BIN)/python experiments/benchmarks/run.py
	$(BIN)/python experiments/benchmarks/node_latency.py
	$(BIN)/python experiments/benchmarks/node_cpu.py
	$(BIN)/python experiments/benchmarks/dds_roundtrip.py
	$(BIN)/python experiments/benchmarks/fit_scale.py
	$(BIN)/python experiments/benchmarks/batch_io.py

format: $(VENV)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
