#![no_main]
//! Fuzz target: see `magg::fuzzing::gltf`.

libfuzzer_sys::fuzz_target!(|data: &[u8]| magg_fuzz::fuzzing::gltf(data));
