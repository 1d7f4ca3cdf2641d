# mcdenoise make targets. `make test` is what CI runs (.ci/run).
MCDENOISE_HOME ?= $(HOME)/.cache/mcdenoise
PY := $(MCDENOISE_HOME)/venv/bin/python
export MCDENOISE_HOME
export ORT_DYLIB_PATH ?= $(MCDENOISE_HOME)/lib/libonnxruntime.so.1.31.1
export MCDENOISE_BIN := $(CURDIR)/target/release/mcdenoise

.PHONY: setup setup-serve setup-train setup-test build test serve train eval bench int8-models ablation reliability fuzz

## Set-up (scripts/setup), in three sets under $(MCDENOISE_HOME); each target below names
## the one it needs. setup-serve: the ONNX Runtime library only (29 MB, seconds).
## setup-train: that, the training environment (venv: torch, Mitsuba; about 5 GB) and
## libllvm19. setup-test (= setup): that, the deploy checks' tools (tests/ops) and the
## dashboard's browser test (Debian's chromium, playwright-core from npm).
setup: setup-test

setup-serve:
	bash scripts/setup serve

setup-train:
	bash scripts/setup train

setup-test:
	bash scripts/setup test

## The release binary (needs only Rust: the ONNX Runtime library is loaded at run time).
build:
	bash scripts/build-release

## Runs every test: Rust unit and integration tests, then the Python tests (training,
## export, data generation, parity with the Rust engine), then tests/ops (Dockerfile,
## Kubernetes manifests, dashboard, Python client and farm hook against a real daemon).
## The speed benchmark runs once on tiny frames so that it keeps working (figures: make bench).
test: setup-test build
	cargo test --release --locked
	bash scripts/test-shared
	$(call int8_quantize,2,64)
	cargo bench --locked --bench speed -- --quick --runs 1 --int8-models $(INT8_MODELS) --out target/bench/quick.json
	cd training && $(PY) -m pytest -q tests
	$(PY) -m pytest -q tests/ops

## Runs the daemon with the shipped models on its defaults (HTTP :8080, gRPC :50051,
## data in ./mcdenoise-data); see docs/api.md for the options. Sets up only the ONNX
## Runtime library (setup-serve): no Python environment.
serve: setup-serve build
	$(MCDENOISE_BIN) serve --models models

## Training data (docs/training-data.md). `make dataset N=100 SIZE=256` renders N procedural
## scenes into data/: noisy frames at each of SPP (comma-separated) and a REF_SPP reference
## per scene, a manifest and a train/validation split by scene, plus TEST_N test scenes
## (disjoint seeds) into data-test/. Interrupted runs resume. WORKERS processes render in
## parallel (several feed one GPU: MI_VARIANT=cuda_ad_rgb). RENDERER=both also renders every
## scene with Blender Cycles (needs scripts/setup-bpy), RENDERER=cycles only with Cycles.
N ?= 10
TEST_N ?= 0
SIZE ?= 256
SPP ?= 1,2,4,8,16,32,64,128
REF_SPP ?= 4096
VAL_FRACTION ?= 0.1
DATA ?= data
WORKERS ?= 1
MI_VARIANT ?= llvm_ad_rgb
RENDERER ?= mitsuba
DATAGEN_ARGS ?=

.PHONY: dataset datagen-timing fixtures

dataset: setup-train
	cd training && $(PY) -m mcdenoise_train.datagen.dataset --out $(abspath $(DATA)) --scenes $(N) \
	  --test-scenes $(TEST_N) --size $(SIZE) --spp $(SPP) --ref-spp $(REF_SPP) --val-fraction $(VAL_FRACTION) \
	  --workers $(WORKERS) --variant $(MI_VARIANT) --renderer $(RENDERER) $(DATAGEN_ARGS)

## Times the generator: 6 scenes at SIZE into a scratch directory; summary.json (printed)
## gives frames/h and, per scene, the seconds of each launch (tracing, compilation, execution).
datagen-timing: setup-train
	rm -rf target/datagen-timing
	cd training && $(PY) -m mcdenoise_train.datagen.dataset --out $(CURDIR)/target/datagen-timing --scenes 6 \
	  --size $(SIZE) --spp $(SPP) --ref-spp $(REF_SPP) --workers $(WORKERS) --variant $(MI_VARIANT) --no-progress

## Regenerates the committed test frames in tests/fixtures/frames (see its README).
fixtures: setup-train
	cd training && $(PY) -m mcdenoise_train.datagen.fixtures --out $(CURDIR)/tests/fixtures/frames

## Training (training/mcdenoise_train/train.py). The defaults are the network size that
## trains on a 2-core CPU in about half an hour; for the paper's size on a GPU use
## TRAIN_ARGS="--width 64 --blocks 8 --predictor-width 128 --predictor-depth 4 --head-kernel 3 --patch 128 --steps 50000 --lr 5e-5"
## (train_ms saturated that size's kernels at 1e-4: docs/training.md, "The paper's network at its width").
VARIANT ?= full
RUN ?= runs/$(VARIANT)
TRAIN_ARGS ?= --width 24 --blocks 4 --predictor-width 48 --predictor-depth 4 --head-kernel 1 \
  --patch 64 --batch 4 --steps 2000 --val-every 250 --lr 1e-4 --log-l1 1

train: setup-train build
	cd training && $(PY) -m mcdenoise_train.train --data $(abspath $(DATA)) --out $(abspath $(RUN)) \
	  --variant $(VARIANT) $(TRAIN_ARGS) --resume --export $(CURDIR)/models

## Quality (docs/results.md): the noisy input, the default variant (`full` on frames with
## covariance, `nocov` on frames without), `nocov`, `beauty` (each frame as a beauty-only file
## gives it: no split, no variances), `lin2020` and `lin2020-narrow` (frames with covariance only)
## and OIDN (high, balanced, fast), per scene and sample count, with plots and side-by-side
## crops, and the firefly check (20 injected outliers per frame, with and without the
## handling; docs/fireflies.md), on each set that is present: the validation scenes that chose
## the checkpoints (VAL_DATA, split val: scripts/cpu-pipeline's 384² ones), the held-out
## 384² scenes beside them (HELDOUT_DATA), Cycles' held-out 384² scenes (HELDOUT_C_DATA)
## and the unseen test scenes of both renderers (TEST_DATA); then quality against time
## (benches/quality_time.py: seconds per 720p frame on this machine, after make bench).
VAL_DATA ?= runs/cpu/val384
HELDOUT_DATA ?= runs/cpu/heldout384
HELDOUT_C_DATA ?= runs/cpu/heldout384c
TEST_DATA ?= data-test
# The data generator's test sets (--test-scenes) carry split `test`; older sets `val`.
TEST_SPLIT ?= test
TEST_OUT ?= test-both
EVAL_SETS = $(VAL_DATA):val:val $(HELDOUT_DATA):test:heldout-384 $(HELDOUT_C_DATA):test:heldout-384-cycles $(TEST_DATA):$(TEST_SPLIT):$(TEST_OUT)
EVAL_METHODS = --method default=$(CURDIR)/models --method nocov=$(CURDIR)/models:nocov --method beauty=$(CURDIR)/models:beauty --method lin2020=$(CURDIR)/models:lin2020 --method lin2020-narrow=$(CURDIR)/models:lin2020-narrow --oidn --oidn-quality high,balanced,fast --crops 4 --outliers 20
eval: setup-train build
	for set in $(EVAL_SETS); do \
	  dir=$${set%%:*} rest=$${set#*:}; split=$${rest%%:*} out=$${rest#*:}; \
	  if [ -f $$dir/manifest.jsonl ]; then data=$$(realpath $$dir); \
	    (cd training && $(PY) -m mcdenoise_train.evaluate --data $$data --split $$split $(EVAL_METHODS) \
	      --out $(CURDIR)/docs/results/$$out) || exit 1; \
	  else echo "no $$dir/manifest.jsonl: $$out left out"; fi; \
	done
	if [ -f target/bench/frame-1280x720.exr ]; then $(PY) benches/quality_time.py \
	  --results docs/results/$(TEST_OUT)/results.jsonl --out docs/results/quality-time.json; \
	  else echo "no target/bench/frame-1280x720.exr (make bench writes it): quality against time left out"; fi
	$(PY) benches/report.py

## Speed (docs/results.md): GEMM ceilings (FP32 and int8), ONNX Runtime alone, the engine's
## stages, the daemon with 1, 2 and 8 clients, peak memory at 720p/1080p/4K, int8 against
## FP32, OIDN on the same frame, and `mcdenoise run` against OIDN high timed in turns.
bench: setup-train build
	$(call int8_quantize,$(INT8_FRAMES),$(INT8_CROP))
	cargo bench --locked --bench speed -- --models models --int8-models $(INT8_MODELS) --out docs/results/speed.json
	$(PY) benches/oidn_speed.py target/bench/frame-1280x720.exr --out docs/results/oidn.json
	$(PY) benches/paired_speed.py target/bench/frame-1280x720.exr --models models --out docs/results/paired.json
	$(PY) benches/report.py

## An int8 copy of the default model for the benchmark (mcdenoise_train.quantize, every
## operator quantised, heads in float): calibrated on DATA's training frames, or on the
## repository's fixtures where there are none (speed does not depend on the ranges; the
## quality of int8 is measured on calibrated models, docs/training.md).
INT8_MODELS ?= target/bench/int8
INT8_FRAMES ?= 32
INT8_CROP ?= 128
INT8_FIXTURES = $(addprefix $(CURDIR)/tests/fixtures/frames/,caustic-spp8.exr cornell-spp8.exr shadow-spp8.exr)
int8_quantize = cd training && $(PY) -m mcdenoise_train.quantize --model $(CURDIR)/models/full/model.onnx --ops all \
	  --data $(abspath $(DATA)) --frames-from $(INT8_FIXTURES) --frames $(1) --crop $(2) \
	  --out $(abspath $(INT8_MODELS))/full/model.onnx
int8-models: setup-train
	$(call int8_quantize,$(INT8_FRAMES),$(INT8_CROP))

## Shared mode's throughput with 1, 2 and 3 replicas against the embedded mode, on this
## machine (benches/scale_out.py): the shipped models on the quick speed benchmark's 320x180
## frame. Pause background renders and training first.
SCALE_OUT_JOBS ?= 24
bench-scale-out: setup-test build
	cargo bench --locked --bench speed -- --quick --runs 1 --out target/bench/quick.json
	$(PY) benches/scale_out.py --frame target/bench/frame-320x180.exr --jobs $(SCALE_OUT_JOBS) \
	  --models models --out docs/results/scale-out.json

## The paper's ablations (models/MODEL_CARD.md): same data, seed and steps for each variant.
ABLATION_STEPS ?= 600
ablation: setup-train build
	cd training && $(PY) -m mcdenoise_train.ablation --data $(abspath $(DATA)) --test-data $(abspath $(TEST_DATA)) \
	  --out $(CURDIR)/runs/ablation --steps $(ABLATION_STEPS) --threads 1

## Reliability (docs/reliability.md): the SIGKILL soak (KILLS restarts), the burst of 10x the
## queue and the SIGTERM drain against the binary; figures in docs/results/reliability/.
KILLS ?= 40
reliability: setup-serve build
	MCDENOISE_SOAK_KILLS=$(KILLS) MCDENOISE_RELIABILITY_OUT=$(CURDIR)/docs/results/reliability \
	  cargo test --release --locked --test integration -- soak:: --nocapture --test-threads 1
	MCDENOISE_RELIABILITY_OUT=$(CURDIR)/docs/results/reliability \
	  cargo test --release --locked --test integration -- bad_inputs:: --nocapture

## Fuzzing (docs/reliability.md) with cargo fuzz on nightly Rust (`cargo install cargo-fuzz`):
## each target for FUZZ_SECONDS, growing fuzz/corpus (unpacked from fuzz/corpus.zip, the form
## the repository keeps it in: scripts/fuzz-corpus); crashes land in fuzz/regressions/<target>/,
## which `make test` replays with the corpus (tests/fuzz_regressions.rs). Minimise the corpus
## and pack it back before committing it: `make fuzz-cmin`.
FUZZ_SECONDS ?= 600
FUZZ_TARGETS ?= exr_frame http_submit grpc_chunks
FUZZ_FLAGS = -max_len=65536 -rss_limit_mb=2048 -malloc_limit_mb=512 -timeout=20 -print_final_stats=1
fuzz: setup-serve
	[ -d fuzz/corpus ] || python3 scripts/fuzz-corpus unpack
	cd fuzz && for t in $(FUZZ_TARGETS); do mkdir -p corpus/$$t regressions/$$t && \
	  cargo +nightly fuzz run -s none $$t corpus/$$t -- $(FUZZ_FLAGS) -max_total_time=$(FUZZ_SECONDS) \
	    -artifact_prefix=regressions/$$t/ || exit 1; done

fuzz-cmin: setup-serve
	[ -d fuzz/corpus ] || python3 scripts/fuzz-corpus unpack
	cd fuzz && for t in $(FUZZ_TARGETS); do cargo +nightly fuzz cmin -s none $$t corpus/$$t -- -max_len=65536 || exit 1; done
	python3 scripts/fuzz-corpus pack

## Production network (contract v2, docs/training.md): trains msnet on DATA in the
## background-friendly, resumable way; on a GPU machine use scripts/gpu-pipeline.
MS_RUN ?= runs/ms
MS_ARGS ?= --steps 6000 --batch 8 --patch 64 --val-every 250 --val-frames 24
.PHONY: train-ms
train-ms: setup-train build
	cd training && $(PY) -m mcdenoise_train.train_ms --data $(abspath $(DATA)) --out $(abspath $(MS_RUN)) \
	  --device cpu $(MS_ARGS) --resume --export $(abspath $(MS_RUN))/models

## The `beauty` variant (frames without the diffuse/specular split, docs/model-contract.md):
## the shipped msnet fine-tuned on beauty-only patches (train_ms --beauty), exported as
## BEAUTY_RUN/models/beauty; copy it to models/beauty once evaluated.
BEAUTY_RUN ?= runs/beauty
BEAUTY_ARGS ?= --init $(CURDIR)/training/checkpoints/msnet.pt --steps 20000 --batch 8 --patch 64 --lr 5e-4 \
  --ssim 0.2 --val-every 2500 --val-frames 48
.PHONY: train-beauty
train-beauty: setup-train build
	cd training && $(PY) -m mcdenoise_train.train_ms --data $(abspath $(DATA)) --out $(abspath $(BEAUTY_RUN)) \
	  --device cpu --beauty $(BEAUTY_ARGS) --resume --export $(abspath $(BEAUTY_RUN))/models
