#![no_main]
//! Fuzz target: see `magg::fuzzing::chunk`.

libfuzzer_sys::fuzz_target!(|data: &[u8]| magg_fuzz::fuzzing::chunk(data));
