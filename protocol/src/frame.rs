//! The frame header and the limits that keep a hostile peer from making us allocate.

use crate::message::Message;

pub type NodeId = u16;
pub const BROADCAST: NodeId = 0xFFFF;

pub const MAGIC: [u8; 4] = *b"MAGG";
pub const HEADER_LEN: usize = 40;
/// Largest control part of a frame: a scene header with many lights fits comfortably.
pub const MAX_META: u32 = 64 << 20;
/// Largest raw data part: a chunk or an image stripe.
pub const MAX_DATA: u32 = 64 << 20;
/// Frames that have crossed this many links are dropped (a routing loop, or a forged hop count).
pub const MAX_HOPS: u8 = 64;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    OneToOne = 0,
    Broadcast = 1,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameHeader {
    pub kind: u8,
    pub mode: Mode,
    pub flags: u8,
    pub hops: u8,
    pub sender: NodeId,
    pub receiver: NodeId,
    pub meta_len: u32,
    pub data_len: u32,
    pub tag: u32,
    pub first_ns: u64,
    pub last_ns: u64,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum HeaderError {
    #[error("bad magic {0:02x?} (not a magg peer)")]
    BadMagic([u8; 4]),
    #[error("unknown mode {0}")]
    BadMode(u8),
    #[error("control part of {0} bytes exceeds the limit of {MAX_META}")]
    MetaTooLarge(u32),
    #[error("data part of {0} bytes exceeds the limit of {MAX_DATA}")]
    DataTooLarge(u32),
    #[error("data part of {0} bytes is not a multiple of 4")]
    DataUnaligned(u32),
    #[error("frame has crossed {0} links (routing loop?)")]
    TooManyHops(u8),
}

impl FrameHeader {
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[0..4].copy_from_slice(&MAGIC);
        b[4] = self.kind;
        b[5] = self.mode as u8;
        b[6] = self.flags;
        b[7] = self.hops;
        b[8..10].copy_from_slice(&self.sender.to_le_bytes());
        b[10..12].copy_from_slice(&self.receiver.to_le_bytes());
        b[12..16].copy_from_slice(&self.meta_len.to_le_bytes());
        b[16..20].copy_from_slice(&self.data_len.to_le_bytes());
        b[20..24].copy_from_slice(&self.tag.to_le_bytes());
        b[24..32].copy_from_slice(&self.first_ns.to_le_bytes());
        b[32..40].copy_from_slice(&self.last_ns.to_le_bytes());
        b
    }

    /// Parses and checks a header. Nothing is allocated on the word of a peer until this passes.
    pub fn decode(b: &[u8; HEADER_LEN]) -> Result<FrameHeader, HeaderError> {
        let magic = [b[0], b[1], b[2], b[3]];
        if magic != MAGIC {
            return Err(HeaderError::BadMagic(magic));
        }
        let mode = match b[5] {
            0 => Mode::OneToOne,
            1 => Mode::Broadcast,
            m => return Err(HeaderError::BadMode(m)),
        };
        let u16_at = |i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
        let u32_at = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let u64_at = |i: usize| u64::from_le_bytes(b[i..i + 8].try_into().expect("8 bytes"));
        let h = FrameHeader {
            kind: b[4],
            mode,
            flags: b[6],
            hops: b[7],
            sender: u16_at(8),
            receiver: u16_at(10),
            meta_len: u32_at(12),
            data_len: u32_at(16),
            tag: u32_at(20),
            first_ns: u64_at(24),
            last_ns: u64_at(32),
        };
        if h.meta_len > MAX_META {
            return Err(HeaderError::MetaTooLarge(h.meta_len));
        }
        if h.data_len > MAX_DATA {
            return Err(HeaderError::DataTooLarge(h.data_len));
        }
        if !h.data_len.is_multiple_of(4) {
            return Err(HeaderError::DataUnaligned(h.data_len));
        }
        if h.hops > MAX_HOPS {
            return Err(HeaderError::TooManyHops(h.hops));
        }
        Ok(h)
    }

    /// Bytes of the whole frame on the wire.
    pub fn wire_len(&self) -> usize {
        HEADER_LEN + self.meta_len as usize + self.data_len as usize
    }
}

/// A whole frame: header, encoded control part, raw data in aligned words.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub header: FrameHeader,
    pub meta: Vec<u8>,
    pub data: Box<[u32]>,
}

impl Frame {
    /// A one-to-one frame carrying `message` and `data`.
    pub fn new(sender: NodeId, receiver: NodeId, message: &Message, data: Box<[u32]>) -> Frame {
        let meta = message.encode();
        let mode = if receiver == BROADCAST {
            Mode::Broadcast
        } else {
            Mode::OneToOne
        };
        Frame {
            header: FrameHeader {
                kind: message.kind(),
                mode,
                flags: u8::from(!data.is_empty()),
                hops: 0,
                sender,
                receiver,
                meta_len: meta.len() as u32,
                data_len: (data.len() * 4) as u32,
                tag: 0,
                first_ns: 0,
                last_ns: 0,
            },
            meta,
            data,
        }
    }

    pub fn with_tag(mut self, tag: u32) -> Frame {
        self.header.tag = tag;
        self
    }

    pub fn message(&self) -> Result<Message, crate::message::DecodeError> {
        Message::decode(&self.meta)
    }

    pub fn data_bytes(&self) -> &[u8] {
        bytemuck::cast_slice(&self.data)
    }

    pub fn wire_len(&self) -> usize {
        self.header.wire_len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn round_trip() {
        let h = FrameHeader {
            kind: 7,
            mode: Mode::Broadcast,
            flags: 1,
            hops: 3,
            sender: 5,
            receiver: BROADCAST,
            meta_len: 100,
            data_len: 64,
            tag: 99,
            first_ns: 123,
            last_ns: 456,
        };
        assert_eq!(FrameHeader::decode(&h.encode()).unwrap(), h);
    }

    proptest! {
        #[test]
        fn any_bytes_decode_or_fail_cleanly(bytes in proptest::collection::vec(any::<u8>(), HEADER_LEN)) {
            let arr: [u8; HEADER_LEN] = bytes.try_into().unwrap();
            if let Ok(h) = FrameHeader::decode(&arr) {
                prop_assert!(h.meta_len <= MAX_META && h.data_len <= MAX_DATA && h.data_len % 4 == 0);
            }
        }
    }
}
