# syntax=docker/dockerfile:1.7
# mcdenoise: the denoising daemon with the shipped models (docs/deploy.md).
#
#   docker build -t mcdenoise .
#   docker run -p 8080:8080 -p 50051:50051 -v mcdenoise-data:/var/lib/mcdenoise mcdenoise
#
#   docker build --target gpu -t mcdenoise:gpu .        # the GPU image (NVIDIA, CUDA 13)
#   docker run --gpus all -p 8080:8080 -p 50051:50051 mcdenoise:gpu
#
# Stages: the ONNX Runtime library from the pinned wheels (scripts/install-ort: the CPU
# build with OpenVINO's execution provider plugin, or for the GPU image the CUDA build with the CUDA 13 runtime, cuBLAS, cuRAND and
# cuDNN 9 from NVIDIA's wheels), the release binary (scripts/build-release; CI runs the
# same script through `make test`), and a small runtime image with a non-root user, in two
# flavours: `gpu`, and `cpu`, the last stage and so the default. The GPU image needs only
# the NVIDIA driver on the host (libcuda.so.1, which the NVIDIA container toolkit mounts).
# Dependency builds are cached across builds in BuildKit cache mounts (cargo registry, git
# checkouts and target/).

ARG RUST_IMAGE=rust:1.95-slim-bookworm
ARG PYTHON_IMAGE=python:3.11-slim-bookworm
ARG RUNTIME_IMAGE=debian:bookworm-slim

# --- ONNX Runtime: libonnxruntime.so.1.31.1 from the onnxruntime==1.31.1 wheel -----------
FROM ${PYTHON_IMAGE} AS ort
WORKDIR /src
COPY scripts/install-ort scripts/install-ort
RUN --mount=type=cache,target=/root/.cache/pip \
    bash scripts/install-ort /out/lib

# --- ONNX Runtime for the GPU image: the CUDA build and its libraries (about 1.8 GB) -----
FROM ${PYTHON_IMAGE} AS ort-cuda
WORKDIR /src
COPY scripts/install-ort scripts/install-ort
RUN --mount=type=cache,target=/root/.cache/pip \
    bash scripts/install-ort --cuda /out/lib

# --- Build: target/release/mcdenoise -----------------------------------------------------
FROM ${RUST_IMAGE} AS build
WORKDIR /src
# Manifests first: the fetch layer is rebuilt only when the dependencies change.
COPY Cargo.toml Cargo.lock ./
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/usr/local/cargo/git \
    cargo fetch --locked
COPY build.rs rustfmt.toml ./
COPY proto proto
COPY src src
COPY scripts/build-release scripts/build-release
ENV CARGO_TARGET_DIR=/cache/target
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/usr/local/cargo/git \
    --mount=type=cache,target=/cache/target \
    bash scripts/build-release /out/bin

# --- Runtime: what both images share ----------------------------------------------------
FROM ${RUNTIME_IMAGE} AS runtime
# UID/GID 10001, also named in USER below and in deploy/ (runAsUser, fsGroup).
RUN groupadd --system --gid 10001 mcdenoise \
 && useradd --system --uid 10001 --gid mcdenoise --home-dir /var/lib/mcdenoise --no-create-home \
      --shell /usr/sbin/nologin mcdenoise \
 && mkdir -p /var/lib/mcdenoise \
 && chown mcdenoise:mcdenoise /var/lib/mcdenoise
COPY --from=build /out/bin/mcdenoise /usr/local/bin/mcdenoise
COPY scripts/healthcheck /usr/local/bin/mcdenoise-healthcheck
COPY models/full /opt/mcdenoise/models/full
COPY models/nocov /opt/mcdenoise/models/nocov
COPY models/lin2020 /opt/mcdenoise/models/lin2020
COPY models/lin2020-narrow /opt/mcdenoise/models/lin2020-narrow
COPY models/beauty /opt/mcdenoise/models/beauty
COPY models/MODEL_CARD.md /opt/mcdenoise/models/

# Defaults; every option of `mcdenoise serve` is an environment variable (docs/api.md).
ENV MCDENOISE_HTTP=0.0.0.0:8080 \
    MCDENOISE_GRPC=0.0.0.0:50051 \
    MCDENOISE_PROBE_HTTP=0.0.0.0:8081 \
    MCDENOISE_DATA_DIR=/var/lib/mcdenoise \
    MCDENOISE_MODELS=/opt/mcdenoise/models \
    ORT_DYLIB_PATH=/opt/mcdenoise/lib/libonnxruntime.so.1.31.1 \
    MCDENOISE_LOG_FORMAT=json \
    MCDENOISE_SHUTDOWN_TIMEOUT=30s

# Numeric, so that Kubernetes can check runAsNonRoot.
USER 10001:10001
WORKDIR /var/lib/mcdenoise
VOLUME ["/var/lib/mcdenoise"]
EXPOSE 8080 8081 50051
STOPSIGNAL SIGTERM
HEALTHCHECK --interval=15s --timeout=5s --start-period=10s --retries=3 \
  CMD ["mcdenoise-healthcheck"]
ENTRYPOINT ["mcdenoise"]
CMD ["serve"]

# --- GPU image: the networks on CUDA (`--device cuda`: without a GPU the daemon stops at
# start and names what is missing), their kernels applied inside the graph
# (`--reconstruction auto`), two workers so that one frame's CPU work overlaps another's
# inference. The CUDA libraries are found through LD_LIBRARY_PATH beside the provider.
FROM runtime AS gpu
COPY --from=ort-cuda /out/lib/ /opt/mcdenoise/lib/
ENV LD_LIBRARY_PATH=/opt/mcdenoise/lib \
    MCDENOISE_DEVICE=cuda \
    MCDENOISE_WORKERS=2 \
    NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility

# --- CPU image (the default) -------------------------------------------------------------
FROM runtime AS cpu
COPY --from=ort /out/lib/libonnxruntime.so.1.31.1 /opt/mcdenoise/lib/
# OpenVINO's execution provider plugin and runtime (91 MB): `--device auto` runs the
# networks through it in bfloat16 on CPUs with AMX, and AMD CPUs with AVX512-BF16
# (docs/api.md, `--device`).
COPY --from=ort /out/lib/openvino/ /opt/mcdenoise/lib/openvino/
