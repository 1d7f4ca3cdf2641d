//! mcdenoise denoises Monte Carlo path-traced frames with the kernel-predicting networks of
//! Lin et al. 2020 ("A Detail Preserving Neural Network Model for Monte Carlo Denoising"),
//! run through ONNX Runtime.
//!
//! # Layout
//!
//! - [`frame`]: OpenEXR frames to validated planar buffers (channel layout and aliases).
//! - [`engine`]: preprocessing, model loading (contract v1), tiled inference, kernel
//!   reconstruction. Synchronous; callers own the threads.
//! - [`metrics`]: RelMSE, DSSIM, PSNR, SMAPE.
//! - [`cli`]: the offline commands (`mcdenoise run`, `mcdenoise preprocess`).
//!
//! `docs/frame-layout.md` and `docs/model-contract.md` describe the formats.

pub mod cli;
pub mod engine;
pub mod frame;
pub mod metrics;
