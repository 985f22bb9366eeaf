# radaredge — the two commands of a fresh machine are `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
MODEL   ?= tdfanet
RUNS    ?= 20
# MAFF-Net on trained weights: a run directory of `radaredge train` per card, and the labelled set
# it was trained on (benchmarks/maffnet_trained.py times its test split); skipped when absent.
MAFFNET_RUNS ?= runs
DETECTION_SET ?= bench-detection

.PHONY: setup test demo bench clean

# `.[dev]` is every extra (export, eval, ros, openvino) plus the test tools; a device that only
# runs exported graphs needs the base install (`pip install .`: numpy, onnxruntime, pyyaml, click).
$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# The layers (import-linter, contracts in pyproject.toml) and the lint (ruff) first, then the suite. A worker that
# crashes ends the run at once: under --dist loadfile the rest of its file is never rescheduled
# and the run would wait for it until CI times out.
test: $(STAMP)
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --max-worker-restart=0 tests

# The main job on built-in defaults: export the model, prove parity, measure speed. A card with
# trained weights in the zoo (zoo/<card>/) is exported with them, and a detector then scores a small
# synthetic set, drawing its detections in BEV (export/<card>.onnx.eval/bev-*.png).
ZOO_WEIGHTS = $(wildcard zoo/$(MODEL)/weights.pth)
WEIGHTS_ARGS = $(if $(ZOO_WEIGHTS),--config zoo/$(MODEL)/card.yaml --checkpoint $(ZOO_WEIGHTS))
demo: $(STAMP)
	$(BIN)/radaredge export --model $(MODEL) $(WEIGHTS_ARGS)
	$(BIN)/radaredge parity-check --model $(MODEL) --onnx export/$(MODEL).onnx $(WEIGHTS_ARGS)
	$(BIN)/radaredge bench --model $(MODEL) --onnx export/$(MODEL).onnx --runs $(RUNS) $(WEIGHTS_ARGS)
	@if [ -n "$(ZOO_WEIGHTS)" ] && grep -q '^model: maffnet' zoo/$(MODEL)/card.yaml; then \
	  rm -rf export/demo-detection && \
	  $(BIN)/radaredge make-benchmark --task detection --out export/demo-detection --drives 4 --frames 5 --seed 11 && \
	  $(BIN)/radaredge eval --model $(MODEL) --onnx export/$(MODEL).onnx --data export/demo-detection --split test \
	    $(WEIGHTS_ARGS) --report-dir export/$(MODEL).onnx.eval; fi

# The speed suite: every card x {torch reference, torch export, onnxruntime fp32, int8} on 2 cores;
# writes benchmarks/README.md, benchmarks/suite.png and benchmarks/results/suite-<date>.json.
# Then the MAFF-Net cards that have trained weights under $(MAFFNET_RUNS)/<card>/best.pth: fp32,
# int8 and the worst case with the stage split (benchmarks/results/maffnet-trained-<card>-<date>.json).
bench: $(STAMP)
	$(BIN)/python benchmarks/run.py --runs $(RUNS)
	@for card in maffnet-vod maffnet-vod-edge; do \
	  if [ -f $(MAFFNET_RUNS)/$$card/best.pth ] && [ -d $(DETECTION_SET) ]; then \
	    $(BIN)/python benchmarks/maffnet_trained.py --model $$card --checkpoint $(MAFFNET_RUNS)/$$card/best.pth \
	      --data $(DETECTION_SET) || exit 1; \
	  else echo "$$card: no $(MAFFNET_RUNS)/$$card/best.pth or no $(DETECTION_SET)/: trained-weight rows skipped" \
	    "(radaredge make-benchmark --task detection --out $(DETECTION_SET); radaredge train" \
	    "--model $$card --data $(DETECTION_SET) --output $(MAFFNET_RUNS)/$$card)"; fi; \
	done
	$(BIN)/python benchmarks/render.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
