#![no_main]
//! Fuzz target: see `magg::fuzzing::frame`.

libfuzzer_sys::fuzz_target!(|data: &[u8]| magg_fuzz::fuzzing::frame(data));
