//! Fuzz targets of mcdenoise (`cargo +nightly fuzz run <target>`, see docs/reliability.md).
//! The harnesses live in `harness.rs`, which the main crate's `tests/fuzz_regressions.rs`
//! also includes to replay the kept corpus on stable Rust in every test run.

#[path = "harness.rs"]
pub mod harness;
