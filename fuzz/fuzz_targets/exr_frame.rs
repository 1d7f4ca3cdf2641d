//! cargo fuzz target `exr_frame`: see `mcdenoise_fuzz::harness::exr_frame`.
#![no_main]

libfuzzer_sys::fuzz_target!(|input: &[u8]| {
    mcdenoise_fuzz::harness::exr_frame_bytes(input);
});
