# mcdenoise make targets. `make test` is what CI runs (.ci/run).
MCDENOISE_HOME ?= $(HOME)/.cache/mcdenoise
PY := $(MCDENOISE_HOME)/venv/bin/python
export MCDENOISE_HOME
export ORT_DYLIB_PATH ?= $(MCDENOISE_HOME)/lib/libonnxruntime.so.1.31.1
export MCDENOISE_BIN := $(CURDIR)/target/release/mcdenoise

.PHONY: setup build test serve train eval

setup:
	bash scripts/setup

build: setup
	bash scripts/build-release

## Runs every test: Rust unit and integration tests, then the Python tests (training,
## export, data generation, parity with the Rust engine), then tests/ops (Dockerfile,
## Kubernetes manifests, dashboard, Python client and farm hook against a real daemon).
test: build
	cargo test --release --locked
	cd training && $(PY) -m pytest -q tests
	$(PY) -m pytest -q tests/ops

## Runs the daemon with the shipped models on its defaults (HTTP :8080, gRPC :50051,
## data in ./mcdenoise-data); see docs/api.md for the options.
serve: build
	$(MCDENOISE_BIN) serve --models models

## Training data (docs/training-data.md). `make dataset N=100 SIZE=256` renders N procedural
## scenes into data/: noisy frames at each of SPP (comma-separated) and a REF_SPP reference
## per scene, a manifest and a train/validation split by scene. Interrupted runs resume.
N ?= 10
SIZE ?= 256
SPP ?= 4,8,16,32,64,128
REF_SPP ?= 4096
VAL_FRACTION ?= 0.1
DATA ?= data

.PHONY: dataset fixtures

dataset: setup
	cd training && $(PY) -m mcdenoise_train.datagen.dataset --out $(abspath $(DATA)) --scenes $(N) \
	  --size $(SIZE) --spp $(SPP) --ref-spp $(REF_SPP) --val-fraction $(VAL_FRACTION)

## Regenerates the committed test frames in tests/fixtures/frames (see its README).
fixtures: setup
	cd training && $(PY) -m mcdenoise_train.datagen.fixtures --out $(CURDIR)/tests/fixtures/frames

## Training (training/mcdenoise_train/train.py). The defaults are the network size that
## trains on a 2-core CPU in about half an hour; for the paper's size on a GPU use
## TRAIN_ARGS="--width 64 --blocks 8 --predictor-width 128 --predictor-depth 4 --head-kernel 3 --patch 128 --steps 50000".
VARIANT ?= full
RUN ?= runs/$(VARIANT)
TRAIN_ARGS ?= --width 24 --blocks 4 --predictor-width 48 --predictor-depth 4 --head-kernel 1 \
  --patch 64 --batch 4 --steps 2000 --val-every 250 --lr 3e-4 --log-l1 1

train: build
	cd training && $(PY) -m mcdenoise_train.train --data $(abspath $(DATA)) --out $(abspath $(RUN)) \
	  --variant $(VARIANT) $(TRAIN_ARGS) --resume --export $(CURDIR)/models

## Quality on the validation scenes: noisy input, both shipped variants and OIDN.
eval: build
	cd training && $(PY) -m mcdenoise_train.evaluate --data $(abspath $(DATA)) --split val \
	  --method full=$(CURDIR)/models:full --method nocov=$(CURDIR)/models:nocov --oidn --out $(CURDIR)/eval
