#![no_main]
//! Fuzz target: see `magg::fuzzing::topology`.

libfuzzer_sys::fuzz_target!(|data: &[u8]| magg_fuzz::fuzzing::topology(data));
