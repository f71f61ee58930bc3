//! Replays every saved fuzzing input (`fuzz/corpus/<target>/`) through its target, so inputs
//! that once crashed stay fixed, with no fuzzer needed. `MAGG_WRITE_SEEDS=1` (re)writes the
//! seed inputs, which are made in code (`magg::fuzzing::seeds`).

use std::path::Path;

fn corpus() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus")
}

#[test]
fn every_corpus_input_is_handled_without_a_panic() {
    if std::env::var_os("MAGG_WRITE_SEEDS").is_some() {
        for (target, name, bytes) in magg::fuzzing::seeds() {
            let dir = corpus().join(target);
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join(format!("seed-{name}")), bytes).unwrap();
        }
    }
    let mut count = 0;
    for target in magg::fuzzing::TARGETS {
        let dir = corpus().join(target);
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for e in entries {
            let p = e.unwrap().path();
            let data = std::fs::read(&p).unwrap();
            magg::fuzzing::run(target, &data);
            count += 1;
        }
    }
    assert!(count >= magg::fuzzing::TARGETS.len(), "the corpus is empty");
}
