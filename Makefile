# shape_detector: two commands on a bare machine (Python 3.11 + pip):
#   make demo   -> venv + install, then a generated walk-through bag -> detections + scene map (out/)
#   make test   -> venv + install, then the whole pytest suite
# Both are idempotent: the install runs again only when its inputs change.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= out
SAMPLE ?= bags/sample
# ROS traffic of anything started from here stays on this host, over shared memory.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export ROS_DOMAIN_ID ?= 77
# (Fast DDS 2.x, in the Jazzy wheels, reads the FASTRTPS name; 3.x, in Kilted, the FASTDDS one)
export FASTDDS_DEFAULT_PROFILES_FILE ?= $(CURDIR)/shape_detector/config/fastdds_shm.xml
export FASTRTPS_DEFAULT_PROFILES_FILE ?= $(FASTDDS_DEFAULT_PROFILES_FILE)

.PHONY: demo test lint install bench sample-bag figures weights evaluate ablation clean

install: $(STAMP)

$(STAMP): setup.py requirements.txt requirements-ros.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -r requirements.txt -r requirements-ros.txt
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

# A walk-through of a generated room (camera poses on /tf, /tf_static and /odom), made once.
WALK ?= $(OUT)/walkthrough
$(WALK)/metadata.yaml: | $(STAMP)
	$(VENV)/bin/shape-detector synth walkthrough --out $(WALK) --frames 30 --seed 5

demo: $(STAMP) $(WALK)/metadata.yaml
	$(VENV)/bin/shape-detector demo $(WALK) --out $(OUT)

test: $(STAMP)
	$(PY) -m pytest -q test

lint: $(STAMP)
	$(VENV)/bin/ruff check shape_detector msg_conversion test scripts
	$(VENV)/bin/mypy shape_detector msg_conversion

bench: $(STAMP)
	$(VENV)/bin/shape-detector bench all

# Regenerate the committed sample bag, README figure, training data and weights.
sample-bag: $(STAMP)
	$(VENV)/bin/shape-detector synth bag --out $(SAMPLE) --frames 12 --seed 4

figures: $(STAMP)
	$(VENV)/bin/shape-detector synth figure --out docs/synth_grid.png --seed 3

# Training data (generated, never committed), the shipped weights, evaluation, comparison.
DATA ?= data
SD   := $(VENV)/bin/shape-detector

$(DATA)/train/index.json: | $(STAMP)
	$(SD) synth dataset --out $(DATA)/train --frames 3000 --seed 1 --workers 2 --rgb-format jpg --frames-per-shard 150
$(DATA)/val/index.json: | $(STAMP)
	$(SD) synth dataset --out $(DATA)/val --frames 200 --seed 2 --workers 2 --rgb-format jpg --frames-per-shard 100
$(DATA)/test/index.json: | $(STAMP)
	$(SD) synth dataset --out $(DATA)/test --frames 250 --seed 3 --workers 2 --rgb-format jpg --frames-per-shard 125

# The shipped weights: one recipe (shape_detector/training/recipes/shipped.json) lists every
# phase (network stages 1 to 4i, then the proposal classifiers); each phase resumes from its
# checkpoint and is skipped once finished, so an interrupted `make weights` continues where it
# stopped. The recipe generates the data sets it names (recipes/base.json) where they are
# missing. --export copies the phases the recipe exports into shape_detector/weights/. See
# docs/training.md (phases, provenance, several processes or GPUs with torchrun).
# The recipe runs again after the 2D proposer's training: the hybrid proposer's classifier
# (stage 5b) learns from that proposer's candidates, so it retrains only if the proposer changed.
# Last, the scene map's track classifier learns from maps the new detector builds.
RECIPE ?= shipped
RUNS   ?= runs/shipped
weights: | $(STAMP)
	$(SD) train --recipe $(RECIPE) --data-root $(DATA) --out $(RUNS) --device cpu --export shape_detector/weights
	$(SD) train-proposer --data $(DATA)/train $(DATA)/extra $(DATA)/extra2 --out shape_detector/weights/proposer2d.onnx --epochs 30
	$(SD) train --recipe $(RECIPE) --data-root $(DATA) --out $(RUNS) --device cpu --export shape_detector/weights
	$(SD) train-track-classifier --out shape_detector/weights/track_classifier.json

evaluate: $(DATA)/test/index.json
	$(SD) evaluate --weights shape_detector/weights/default.pt --data $(DATA)/test --frames 250 --min-visible 0.1 --out docs/eval/gt_boxes
	$(SD) evaluate --weights shape_detector/weights/default.pt --data $(DATA)/test --frames 250 --min-visible 0.1 --out docs/eval/builtin --no-gt-boxes --estimate-up --class-hypotheses 2
	$(SD) evaluate --weights shape_detector/weights/default.pt --data $(DATA)/test --frames 250 --out docs/eval/gt_boxes_all
	$(SD) evaluate --weights shape_detector/weights/default.pt --data $(DATA)/test --frames 250 --out docs/eval/builtin_all --no-gt-boxes --estimate-up --class-hypotheses 2

ablation: $(DATA)/train/index.json $(DATA)/val/index.json
	bash scripts/ablation.sh

clean:
	rm -rf $(OUT) build *.egg-info .pytest_cache
