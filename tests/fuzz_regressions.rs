//! Replays the kept fuzz corpus and every crash reproducer (`<target>/` in fuzz/corpus.zip,
//! fuzz/regressions/<target>) through the same harnesses `cargo fuzz` runs, on stable Rust,
//! so that what the fuzzer once found stays fixed (docs/reliability.md). The corpus is kept
//! as one archive (scripts/fuzz-corpus): thousands of small files would cost a kilobyte each
//! in the checkout a GPU lease carries.

#[path = "../fuzz/src/harness.rs"]
#[allow(dead_code)]
mod harness;

use std::path::PathBuf;

fn inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut out = Vec::new();
    let archive = root.join("corpus.zip");
    let mut zip = zip::ZipArchive::new(std::fs::File::open(&archive).unwrap()).unwrap();
    for i in 0..zip.len() {
        let mut entry = zip.by_index(i).unwrap();
        if entry.is_file() && entry.name().starts_with(&format!("{target}/")) {
            let mut bytes = Vec::new();
            std::io::Read::read_to_end(&mut entry, &mut bytes).unwrap();
            out.push((archive.join(entry.name()), bytes));
        }
    }
    let Ok(entries) = std::fs::read_dir(root.join("regressions").join(target)) else { return out };
    for entry in entries.flatten() {
        let path = entry.path();
        let bytes = std::fs::read(&path).unwrap();
        out.push((path, bytes));
    }
    out.sort();
    out
}

/// Runs every kept input; `run` says whether the input made it through (a valid frame, an
/// accepted job). Some must: a corpus that never gets past the parsers tests little.
fn replay(target: &str, run: fn(&[u8]) -> bool) {
    let inputs = inputs(target);
    assert!(inputs.len() >= 20, "{target}: only {} kept inputs", inputs.len());
    let mut through = 0;
    for (path, bytes) in &inputs {
        let outcome = std::panic::catch_unwind(|| run(bytes));
        assert!(outcome.is_ok(), "{target}: {} fails again", path.display());
        through += usize::from(outcome.unwrap());
    }
    eprintln!("{target}: {} inputs replayed, {through} made it through", inputs.len());
    assert!(through > 0, "{target}: no kept input gets past the parsers");
}

#[test]
fn exr_frame_corpus_replays_clean() {
    replay("exr_frame", harness::exr_frame_bytes);
}

#[test]
fn http_submit_corpus_replays_clean() {
    replay("http_submit", harness::http_submit_bytes);
}

#[test]
fn grpc_chunks_corpus_replays_clean() {
    replay("grpc_chunks", harness::grpc_chunks_bytes);
}
