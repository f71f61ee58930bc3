//! Computes the build identity every process shows at the handshake: the crate version, a
//! hash of the workspace's sources and manifests, a hash of the lock file, and the target's
//! architecture and instruction-set features. Two processes render the same bytes only when
//! they run the same code on the same instruction set, so a cluster refuses a peer whose
//! identity differs from its own.
//!
//! The sources are the `src/` folders, manifests and build scripts of the workspace's
//! packages (every folder here with a `Cargo.toml`, `fuzz` aside) and of the root package;
//! tests, benchmarks and documents do not enter it.
//!
//! It lives in the root package, whose binaries stamp it into `protocol` at start-up, and not
//! in `protocol` itself: there, any edit anywhere in the workspace rebuilt `protocol` and
//! every crate above it.

use std::{
    fs,
    path::{Path, PathBuf},
};

use sha2::{Digest, Sha256};

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets it"));
    let root = manifest.as_path();

    let mut packages: Vec<PathBuf> = vec![root.to_path_buf()];
    if let Ok(entries) = fs::read_dir(root) {
        for e in entries.flatten() {
            let p = e.path();
            let name = e.file_name();
            if p.join("Cargo.toml").is_file() && name != "fuzz" && name != "target" {
                packages.push(p);
            }
        }
    }
    packages.sort();

    let mut files = Vec::new();
    for p in &packages {
        for name in ["Cargo.toml", "build.rs"] {
            let f = p.join(name);
            if f.is_file() {
                println!("cargo:rerun-if-changed={}", f.display());
                files.push(f);
            }
        }
        let src = p.join("src");
        if src.is_dir() {
            println!("cargo:rerun-if-changed={}", src.display());
            collect(&src, &mut files);
        }
    }
    files.sort();
    let mut sources = Sha256::new();
    for f in &files {
        let rel = f.strip_prefix(root).unwrap_or(f);
        sources.update(rel.to_string_lossy().as_bytes());
        sources.update([0]);
        let bytes = fs::read(f).unwrap_or_default();
        sources.update((bytes.len() as u64).to_le_bytes());
        sources.update(&bytes);
    }

    let lock = root.join("Cargo.lock");
    println!("cargo:rerun-if-changed={}", lock.display());
    let lock_hash = Sha256::digest(fs::read(&lock).unwrap_or_default());

    // Features that change what the code computes. `crt-static` changes only how the binary
    // is linked (the container image's static build renders the same bytes).
    let arch = std::env::var("CARGO_CFG_TARGET_ARCH").unwrap_or_default();
    let mut features: Vec<String> = std::env::var("CARGO_CFG_TARGET_FEATURE")
        .unwrap_or_default()
        .split(',')
        .filter(|f| !f.is_empty() && *f != "crt-static")
        .map(str::to_string)
        .collect();
    features.sort();

    let id = format!(
        "{} src {} lock {} {} {}",
        std::env::var("CARGO_PKG_VERSION").unwrap_or_default(),
        &hex(&sources.finalize())[..12],
        &hex(&lock_hash)[..12],
        arch,
        features.join(","),
    );
    println!("cargo:rustc-env=MAGG_BUILD_ID={id}");
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}
