# radaredge — the two commands of a fresh machine are `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
MODEL   ?= tdfanet
RUNS    ?= 20

.PHONY: setup test demo bench clean

# `.[dev]` is every extra (export, eval, ros, openvino) plus the test tools; a device that only
# runs exported graphs needs the base install (`pip install .`: numpy, onnxruntime, pyyaml, click).
$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# The layers first (import-linter, contracts in pyproject.toml), then the suite.
test: $(STAMP)
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2 --dist loadfile tests

# The main job on built-in defaults: export the model, prove parity, measure speed.
demo: $(STAMP)
	$(BIN)/radaredge export --model $(MODEL)
	$(BIN)/radaredge parity-check --model $(MODEL) --onnx export/$(MODEL).onnx
	$(BIN)/radaredge bench --model $(MODEL) --onnx export/$(MODEL).onnx --runs $(RUNS)

# The speed suite: every card x {torch reference, torch export, onnxruntime fp32, int8} on 2 cores;
# writes benchmarks/README.md, benchmarks/suite.png and benchmarks/results/suite-<date>.json.
bench: $(STAMP)
	$(BIN)/python benchmarks/run.py --runs $(RUNS)

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
