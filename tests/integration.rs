//! The integration tests, one binary: each file beside this one is a module (`engine`,
//! `daemon_http`, `hostile`, ...). One binary links the crate and its dependencies once
//! instead of once per file, which is most of `make test`'s build time. Run one file's tests
//! with a filter: `cargo test --release --test integration hostile::`. The exception is
//! `shared_arena.rs`, its own binary: it measures the resident memory of its process, which
//! no other test may share.

mod common;
mod daemon_common;
mod model_dirs;

mod bad_inputs;
mod cli;
mod daemon_grpc;
mod daemon_http;
mod daemon_lifecycle;
mod daemon_v2;
mod engine;
mod engine_v2;
mod fireflies;
mod frame;
mod fuzz_regressions;
mod gpu;
mod hostile;
mod scale_out;
mod security;
mod shipped_models;
mod soak;
mod variance;
