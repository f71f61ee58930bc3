#!/usr/bin/env bash
# Builds the magg image offline, from nothing (no base image to pull): a root filesystem made
# here from the release binaries, the very files `cargo build --release` leaves in target/
# (so a render's build identity is the same inside and outside containers, and the image
# costs no second build), and the few shared libraries they load, copied from this machine
# at the paths its dynamic loader looks in. glibc 2.34+ resolves host names inside libc
# itself (files and DNS), so nothing else is needed for compose's service names.
# Also makes what docker-compose.yml mounts when it is missing: deploy/secrets/magg_secret
# (a fresh random secret) and deploy/input, deploy/out.
#   deploy/build-images.sh [TAG]     (default magg:latest)
set -euo pipefail
cd "$(dirname "$0")/.."
tag="${1:-magg:latest}"
binaries=(magg-host magg-fork-node magg-render-node)

cargo build --release --locked "${binaries[@]/#/--bin=}"

context="$(mktemp -d)"
trap 'rm -rf "$context"' EXIT
cp deploy/Dockerfile "$context"/
rootfs="$context/rootfs"
mkdir -p "$rootfs/bin"
for b in "${binaries[@]}"; do
    cp "${CARGO_TARGET_DIR:-target}/release/$b" "$rootfs/bin/"
    strip "$rootfs/bin/$b" 2>/dev/null || true
done
# Every library the binaries load, and the loader itself, at the path the binaries name:
# `ldd` prints "name => /path (addr)" for libraries and "/path (addr)" for the loader.
libraries=$(ldd "${binaries[@]/#/$rootfs/bin/}" | awk '$2 == "=>" && $3 ~ /^\// {print $3} $1 ~ /^\// && $1 !~ /:$/ {print $1}' | sort -u)
for lib in $libraries; do
    mkdir -p "$rootfs$(dirname "$lib")"
    cp -L "$lib" "$rootfs$lib"
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
