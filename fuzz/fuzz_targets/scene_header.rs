#![no_main]
//! Fuzz target: see `magg::fuzzing::scene_header`.

libfuzzer_sys::fuzz_target!(|data: &[u8]| magg_fuzz::fuzzing::scene_header(data));
