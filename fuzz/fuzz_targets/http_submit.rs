//! cargo fuzz target `http_submit`: see `mcdenoise_fuzz::harness::http_submit`.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    mcdenoise_fuzz::harness::http_submit_bytes(input);
});
