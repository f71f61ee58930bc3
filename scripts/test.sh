#!/usr/bin/env bash
# Every test: the code's habits (scripts/check.sh: fmt, clippy, docs, --locked, layering),
# the workspace's tests (unit, property, golden-image, cross-process, cluster, and
# the replay of the fuzzing corpus), the container deployment's tests when a Docker daemon
# answers, then a short bounded fuzz run of every target when
# cargo-fuzz is installed (.ci/run installs it). The repository carries the data it needs
# (tests/data); with ../shared beside it, the scene sweep covers every shared scene as well.
set -euo pipefail
cd "$(dirname "$0")/.."

scripts/check.sh
cargo test --workspace --release --locked

# The container deployment needs a Docker daemon; without one it is skipped, and says so.
if docker info >/dev/null 2>&1; then
    cargo test --workspace --release --locked --test docker -- --ignored --test-threads=1
else
    echo "SKIPPED: tests/docker.rs (no Docker daemon answers 'docker info')"
fi

if cargo fuzz --version >/dev/null 2>&1; then
    scripts/fuzz.sh "${MAGG_FUZZ_SECONDS:-15}"
else
    echo "cargo-fuzz is not installed: skipping the bounded fuzz run (the corpus was replayed above)"
fi
