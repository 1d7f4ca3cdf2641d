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
