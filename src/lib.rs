//! mcdenoise denoises Monte Carlo path-traced frames with the kernel-predicting networks of
//! Lin et al. 2020 ("A Detail Preserving Neural Network Model for Monte Carlo Denoising"),
//! run through ONNX Runtime.
//!
//! # Layout
//!
//! - [`frame`]: OpenEXR frames to validated planar buffers (channel layout and aliases).
//! - [`engine`]: preprocessing, model loading (contract v1), tiled inference, kernel
//!   reconstruction. Synchronous; callers own the threads.
//! - [`quality`]: image-quality metrics (RelMSE, DSSIM, PSNR, SMAPE).
//! - [`pipeline`]: one frame through a denoiser: decode, denoise, encode, quality metrics
//!   (shared by `mcdenoise run` and the daemon's workers).
//! - [`preview`]: tone-mapped PNG previews of linear frames (the dashboard's images).
//! - [`cli`]: the offline commands (`mcdenoise run`, `mcdenoise preprocess`).
//! - The daemon (`mcdenoise serve`, `docs/api.md`): [`config`] (flags, environment, file),
//!   [`jobs`] (the transport-free core: admission, persistent store, priority queue,
//!   workers that own engines, progress events), [`http`] and [`grpc`] (the two
//!   transports over one core; `http` also serves the dashboard), [`server`] (startup and
//!   graceful shutdown), [`telemetry`] (logs and Prometheus metrics), [`otlp`] (optional
//!   OpenTelemetry traces), [`error`] (one error type, two mappings), [`client`]
//!   (`mcdenoise submit`), [`wire`] (the job's typed wire forms and their
//!   protobuf conversions), [`auth`] (bearer tokens, client identity), [`tls`] (rustls
//!   for both listeners), [`conn`] (every connection in its own task, with its timeouts).
//!
//! [`atomic`] writes every file the crate writes (temporary name, fsync, rename); [`memory`]
//! sets how the process asks for memory (mapped blocks, huge pages).
//!
//! `docs/frame-layout.md` and `docs/model-contract.md` describe the formats.

pub mod atomic;
pub mod auth;
pub mod cli;
pub mod client;
pub mod config;
pub mod conn;
pub mod engine;
pub mod error;
pub mod frame;
pub mod grpc;
pub mod http;
pub mod jobs;
pub mod memory;
pub mod otlp;
pub mod pipeline;
pub mod preview;
pub mod quality;
pub mod server;
pub mod telemetry;
pub mod tls;
pub mod wire;
