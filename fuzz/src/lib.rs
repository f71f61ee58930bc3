//! The fuzz targets' entry points: `src/fuzzing.rs` of the `magg` crate, compiled here as a
//! module of this crate. One file serves both the fuzzer and the corpus replay of the tests
//! (`tests/fuzz_corpus.rs`, through `magg::fuzzing`), while the fuzz build compiles only the
//! crates that file uses, not everything `magg` depends on.

#[path = "../../src/fuzzing.rs"]
pub mod fuzzing;
