#!/usr/bin/env bash
# Fuzzes every target for SECONDS (default 60) each, starting from the corpus in
# fuzz/corpus/<target>/. New inputs found go to a scratch copy, not into the repository;
# a fixed seed fixes the order of mutations, so CI mostly retraces a local run of at least
# that length (coverage feedback can still differ a little: hash tables are seeded per
# process), and a crash leaves its input in fuzz/artifacts/<target>/ and fails the run.
# cargo-fuzz needs nightly features; RUSTC_BOOTSTRAP lets the stable toolchain provide them.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"
seconds="${1:-60}"
export RUSTC_BOOTSTRAP=1
rm -rf artifacts
cargo fuzz build -O
for target in gltf topology frame chunk scene_header; do
    work="$(mktemp -d)"
    cp corpus/"$target"/* "$work"/
    echo "fuzzing $target for ${seconds}s"
    cargo fuzz run -O "$target" "$work" -- -seed=1 -max_total_time="$seconds" -rss_limit_mb=4096 2>&1 | grep -E "^Done|ERROR|panicked|SUMMARY" || true
    if ls artifacts/"$target"/crash-* >/dev/null 2>&1 || ls artifacts/"$target"/oom-* >/dev/null 2>&1; then
        echo "fuzzing $target found a failure: see fuzz/artifacts/$target/" >&2
        exit 1
    fi
    rm -rf "$work"
done
