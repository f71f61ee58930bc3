#!/usr/bin/env bash
# The code's habits, checked: formatting, clippy with warnings as errors on every target,
# documentation that builds without warnings, the lock file as committed, and the layering
# invariants that the renderer core reaches no network, runtime or process crate and that
# the roles carry no lab code.
# scripts/test.sh runs this first. In the release profile, so that clippy and rustdoc reuse
# the proc macros and build scripts the release build and tests compile anyway.
set -euo pipefail
cd "$(dirname "$0")/.."

cargo fmt --all --check
cargo clippy --release --workspace --all-targets --locked -- -D warnings
RUSTDOCFLAGS="-D warnings" cargo doc --release --workspace --no-deps --locked --quiet

# The renderer core (and the file formats under it) know nothing of sockets, async
# runtimes or processes: ARCHITECTURE.md's first invariant.
for crate in renderer scene-io; do
    forbidden=$(cargo tree --locked -p "$crate" -e normal --prefix none --format '{p}' \
        | awk '{print $1}' | sort -u \
        | grep -E '^(tokio|mio|socket2|async-std|smol|futures|nix|rustix|protocol|fabric|host|fork-node|render-node)$' || true)
    if [ -n "$forbidden" ]; then
        echo "invariant broken: $crate depends on: $forbidden" >&2
        exit 1
    fi
done
# The roles and the fabric carry no lab code (benchmarks, experiments, plots).
for crate in host fork-node render-node fabric; do
    forbidden=$(cargo tree --locked -p "$crate" -e normal --prefix none --format '{p}' \
        | awk '{print $1}' | sort -u | grep -E '^(lab|plotters)$' || true)
    if [ -n "$forbidden" ]; then
        echo "invariant broken: $crate depends on: $forbidden" >&2
        exit 1
    fi
done
echo "checks passed: fmt, clippy, docs, --locked, renderer and role layering"
