//! Compiles the gRPC contract (proto/) into OUT_DIR with the pure-Rust `protox` (no
//! `protoc` needed), and writes the encoded descriptor set used by gRPC reflection.

use std::path::PathBuf;

use prost::Message;

const PROTOS: &[&str] = &["proto/mcdenoise/v1/denoise.proto"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // tonic-prost-build prints no rerun-if-changed lines of its own.
    println!("cargo:rerun-if-changed=build.rs");
    for proto in PROTOS {
        println!("cargo:rerun-if-changed={proto}");
    }
    let fds = protox::compile(PROTOS, ["proto"])?;
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("mcdenoise_v1_descriptor.bin"), fds.encode_to_vec())?;
    tonic_prost_build::configure().build_client(true).build_server(true).compile_fds(fds)?;
    Ok(())
}
