#!/usr/bin/env bash
# Builds the magg image offline: static binaries (glibc, +crt-static, so they run and
# resolve host names in an image holding nothing else), then `FROM scratch`.
# Also makes what docker-compose.yml mounts when it is missing: deploy/secrets/magg_secret
# (a fresh random secret) and deploy/input, deploy/out.
#   deploy/build-images.sh [TAG]     (default magg:latest)
set -euo pipefail
cd "$(dirname "$0")/.."
tag="${1:-magg:latest}"
target=x86_64-unknown-linux-gnu

# RUSTFLAGS replaces .cargo/config.toml's flags, so the instruction set is named again here:
# the image's binaries must be the same build as binaries built with the config.
RUSTFLAGS="-C target-feature=+crt-static -C target-cpu=x86-64-v3" \
    cargo build --release --locked --target "$target" \
    --bin magg-host --bin magg-fork-node --bin magg-render-node

context="$(mktemp -d)"
trap 'rm -rf "$context"' EXIT
cp deploy/Dockerfile "$context"/
for b in magg-host magg-fork-node magg-render-node; do
    cp "${CARGO_TARGET_DIR:-target}/$target/release/$b" "$context"/
    strip "$context/$b" 2>/dev/null || true
done
docker build --quiet -t "$tag" "$context" >/dev/null
echo "built $tag: $(docker image inspect "$tag" --format '{{.Size}}' | awk '{printf "%.1f MB", $1/1e6}')"

# The secret: readable inside the containers (which run as nobody) through the bind
# mount, but not by other users of this machine (the folder is the owner's alone).
if [ ! -s deploy/secrets/magg_secret ]; then
    mkdir -p deploy/secrets
    chmod 700 deploy/secrets
    head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' > deploy/secrets/magg_secret
    chmod 644 deploy/secrets/magg_secret
    echo "wrote a new cluster secret to deploy/secrets/magg_secret"
fi
mkdir -p deploy/input deploy/out
# Containers write the image as nobody (or as MAGG_USER).
chmod 1777 deploy/out
