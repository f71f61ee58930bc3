#!/usr/bin/env bash
# Every test: the workspace's tests (unit, property, golden-image, cross-process, cluster, and
# the replay of the fuzzing corpus), then a short bounded fuzz run of every target when
# cargo-fuzz is installed (.ci/run installs it). Needs ../shared beside the repository.
set -euo pipefail
cd "$(dirname "$0")/.."

cargo test --workspace --release

if cargo fuzz --version >/dev/null 2>&1; then
    scripts/fuzz.sh "${MAGG_FUZZ_SECONDS:-15}"
else
    echo "cargo-fuzz is not installed: skipping the bounded fuzz run (the corpus was replayed above)"
fi
