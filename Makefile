# mcdenoise make targets. `make test` is what CI runs (.ci/run).
MCDENOISE_HOME ?= $(HOME)/.cache/mcdenoise
PY := $(MCDENOISE_HOME)/venv/bin/python
export MCDENOISE_HOME
export ORT_DYLIB_PATH ?= $(MCDENOISE_HOME)/lib/libonnxruntime.so.1.31.1
export MCDENOISE_BIN := $(CURDIR)/target/release/mcdenoise

.PHONY: setup build test test-rust test-python demo

setup:
	bash scripts/setup

build: setup
	cargo build --release --locked

## Runs every test: Rust unit and integration tests, then the Python tests (training,
## export, data generation, parity with the Rust engine).
test: build
	cargo test --release --locked
	cd training && $(PY) -m pytest -q tests

## Denoises a committed fixture frame with the committed test models and prints the
## per-stage timings and metrics.
demo: build
	$(MCDENOISE_BIN) run tests/fixtures/frames/cornell-spp8.exr -o out/demo.exr \
	  --reference tests/fixtures/frames/cornell-ref.exr --models models

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
