//! Model directories assembled from the test fixtures for the contract-v2 and variant
//! tests: metadata and graph names edited in the ONNX bytes.

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use crate::common::tiny_models;

/// The tiny contract-v2 models (`full/model.onnx`, `nocov/model.onnx`).
pub fn tiny_v2() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/models/tiny-v2")
}

/// A tiny contract-v2 `full` network with detail gains (`full/model.onnx`).
pub fn tiny_v2_gain() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/models/tiny-v2-gain")
}

/// Replaces every occurrence of `from` by `to` (same length) in an ONNX file's bytes.
pub fn rename(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    assert_eq!(from.len(), to.len());
    let (from, to) = (from.as_bytes(), to.as_bytes());
    let mut out = bytes.to_vec();
    let mut i = 0;
    let mut found = false;
    while i + from.len() <= out.len() {
        if &out[i..i + from.len()] == from {
            out[i..i + from.len()].copy_from_slice(to);
            found = true;
            i += from.len();
        } else {
            i += 1;
        }
    }
    assert!(found, "{} not found", String::from_utf8_lossy(from));
    out
}

/// Sets metadata `key` to `value`: the old entry's key is renamed out of the way (same
/// length) and a new `metadata_props` entry (ModelProto field 14) appended to the message.
pub fn set_meta(bytes: &[u8], key: &str, value: &str) -> Vec<u8> {
    let hidden = key.replacen("mcdenoise.", "mcdenoise_", 1);
    let mut out = if bytes.windows(key.len()).any(|w| w == key.as_bytes()) {
        rename(bytes, key, &hidden)
    } else {
        bytes.to_vec()
    };
    let mut entry = vec![0x0a, key.len() as u8];
    entry.extend_from_slice(key.as_bytes());
    entry.extend_from_slice(&[0x12, value.len() as u8]);
    entry.extend_from_slice(value.as_bytes());
    assert!(entry.len() < 128);
    out.extend_from_slice(&[0x72, entry.len() as u8]);
    out.extend_from_slice(&entry);
    out
}

pub fn read(dir: &Path, variant: &str, file: &str) -> Vec<u8> {
    std::fs::read(dir.join(variant).join(file)).unwrap()
}

pub fn write(root: &Path, variant: &str, file: &str, bytes: &[u8]) {
    std::fs::create_dir_all(root.join(variant)).unwrap();
    std::fs::write(root.join(variant).join(file), bytes).unwrap();
}

/// A models directory holding `full` in contract v2, `nocov` in contract v1, `lin2020` (the
/// v1 `full` pair renamed) and a directory without models.
pub fn mixed() -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    write(root, "full", "model.onnx", &read(&tiny_v2(), "full", "model.onnx"));
    for c in ["diffuse", "specular"] {
        let file = format!("{c}.onnx");
        write(root, "nocov", &file, &read(&tiny_models(), "nocov", &file));
        write(root, "lin2020", &file, &set_meta(&read(&tiny_models(), "full", &file), "mcdenoise.variant", "lin2020"));
    }
    std::fs::create_dir_all(root.join("notes")).unwrap();
    std::fs::write(root.join("notes/README.md"), "not a model").unwrap();
    tmp
}
