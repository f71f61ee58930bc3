//! magg's wire format.
//!
//! Every connection carries frames. A frame is a fixed 40-byte header, then `meta_len` bytes
//! of control data (a [`Message`] encoded with bincode 2, standard configuration), then
//! `data_len` bytes of raw bulk data (shape chunks, texture tiles, pixels), which the receiver
//! reads straight into 4-byte aligned memory and uses in place. All integers are
//! little-endian.
//!
//! | offset | size | field | meaning |
//! |---:|---:|---|---|
//! | 0 | 4 | `magic` | `b"MAGG"` |
//! | 4 | 1 | `kind` | the [`Message`] variant index (the bincode enum tag), so a router need not decode `meta` |
//! | 5 | 1 | `mode` | 0 one-to-one, 1 broadcast (the paper's communication mode) |
//! | 6 | 1 | `flags` | bit 0: `data` is present and 4-byte aligned in length (always set when `data_len > 0`) |
//! | 7 | 1 | `hops` | links crossed so far (incremented by each forwarding node; frames past 64 hops are dropped) |
//! | 8 | 2 | `sender` | node id of the original sender (the host is 0) |
//! | 10 | 2 | `receiver` | node id of the final receiver; 0xFFFF for broadcast |
//! | 12 | 4 | `meta_len` | bytes of bincode control data, at most [`MAX_META`] |
//! | 16 | 4 | `data_len` | bytes of raw data, a multiple of 4, at most [`MAX_DATA`] |
//! | 20 | 4 | `tag` | request id that a reply repeats, 0 if none |
//! | 24 | 8 | `first_ns` | modelled time the first packet of this message is ready at the receiver of the last link crossed (CLOCK_MONOTONIC ns of that receiver's machine; 0 when no delay model applies) |
//! | 32 | 8 | `last_ns` | the same for the last packet (messages longer than one paper packet pipeline through the mesh) |
//!
//! The paper's packet header held mode, data size, sender and receiver; those are `mode`,
//! `meta_len + data_len`, `sender` and `receiver` here.
//!
//! A connection starts with the [`handshake`]: version, cluster id and build identity, then a challenge and
//! response proving on both sides knowledge of the cluster secret (HMAC-SHA256), before any
//! other frame is accepted. The secret itself never crosses the wire.

pub mod codec;
pub mod frame;
pub mod handshake;
pub mod message;

pub use codec::{FrameReader, FrameWriter, ReadError};
pub use frame::{BROADCAST, Frame, FrameHeader, HEADER_LEN, MAX_DATA, MAX_META, Mode, NodeId};
pub use handshake::{ConnectionKind, HandshakeError, Identity, Secret};
pub use message::{
    AskVia, CardSegment, CoherentRays, DataId, DecodeError, DmaTransport, JobSpec, Message,
    NodeStats, Rect, Role, SubscreenWork, Transfer, TransferMode, bytes_to_words, decode_value,
    encode_value, words_to_bytes,
};

/// Bumped whenever the frame layout or the message set changes incompatibly.
pub const PROTOCOL_VERSION: u32 = 10;

/// What this process was built from: crate version, hashes of the workspace's sources and of
/// the lock file, target architecture and instruction-set features (the root package's
/// `build.rs` computes it; its binaries stamp it with [`stamp_build_id`] before anything
/// else). Every process of a cluster must show the same, or the handshake refuses it:
/// processes built from different code could render different bytes for the same pixel.
/// A process that never stamped it (a library's own tests) shows the crate version marked
/// unstamped, which no stamped binary accepts.
pub fn build_id() -> &'static str {
    BUILD_ID
        .get()
        .copied()
        .unwrap_or(concat!(env!("CARGO_PKG_VERSION"), " unstamped"))
}

/// Sets this process's [`build_id`]; the first stamp wins.
pub fn stamp_build_id(id: &'static str) {
    let _ = BUILD_ID.set(id);
}

static BUILD_ID: std::sync::OnceLock<&'static str> = std::sync::OnceLock::new();
