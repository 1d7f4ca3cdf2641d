//! cargo fuzz target `grpc_chunks`: see `mcdenoise_fuzz::harness::grpc_chunks`.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    mcdenoise_fuzz::harness::grpc_chunks_bytes(input);
});
