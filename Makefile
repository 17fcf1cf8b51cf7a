# sotif-bench: `make run` (the benchmark, default profile) and `make test` (the test suite).
# Both create the virtual environment .venv on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PROFILE ?= default

.PHONY: run quick test bench clean

$(BIN)/.installed: pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q -e '.[test,openvino]'
	touch $@

run: $(BIN)/.installed
	$(BIN)/sotif-bench run --profile $(PROFILE)

quick: $(BIN)/.installed
	$(BIN)/sotif-bench run --profile quick

test: $(BIN)/.installed
	$(BIN)/pytest

bench: $(BIN)/.installed
	$(BIN)/python benchmarks/bench_eval.py

clean:
	rm -rf $(VENV) reports/quick reports/default
