//! The scene's way in, on the first fork node only: the host sends the scene description in
//! parts (a large scene does not fit one frame); once all are here it is prepared (chunks,
//! both BVH levels, lights, texture tiles) off the runtime, so that this node keeps
//! forwarding meanwhile, and its chunks and tiles are placed round-robin on the fork nodes.

use std::{borrow::Cow, sync::Arc};

use protocol::{DataId, Frame, Message, NodeId, bytes_to_words, decode_value, encode_value};
use renderer::{MemoryData, PrepareOptions, SceneDesc, SceneHeader};

use crate::ForkNode;

/// What every part of one scene says about the whole.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct PartOf {
    pub parts: u32,
    pub total: u64,
    pub chunk_triangles: u32,
}

/// The parts of a scene description received so far.
#[derive(Debug, Default)]
pub(crate) struct SceneAssembly {
    of: Option<PartOf>,
    parts: Vec<Option<Part>>,
}

/// One part as its frame brought it: kept as it came, not copied (a part is up to 16 MiB,
/// and fresh memory costs about as much as the copy on a virtual machine).
#[derive(Debug, Clone)]
pub(crate) struct Part {
    words: Box<[u32]>,
    len: usize,
}

impl Part {
    /// The first `len` bytes of `words`, if it holds that many.
    pub fn new(words: Box<[u32]>, len: usize) -> Option<Part> {
        protocol::words_to_bytes(&words, len)?;
        Some(Part { words, len })
    }

    fn bytes(&self) -> &[u8] {
        protocol::words_to_bytes(&self.words, self.len).expect("checked when the part came")
    }
}

/// Why a part was refused.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub(crate) enum PartError {
    #[error("scene part {part} of {parts} does not exist")]
    OutOfRange { part: u32, parts: u32 },
    #[error(
        "scene part {part} describes another scene ({got:?}) than its earlier parts ({expected:?})"
    )]
    Mismatch {
        part: u32,
        got: PartOf,
        expected: PartOf,
    },
}

impl SceneAssembly {
    /// Files part `part` (any order); returns the whole scene once every part is here, and
    /// starts afresh. A part counting a different number of parts starts a new scene (the
    /// host gave up on the old one); one agreeing on the count but not on the rest belongs
    /// to neither and is refused.
    pub fn add(
        &mut self,
        part: u32,
        of: PartOf,
        bytes: Part,
    ) -> Result<Option<SceneAssembly>, PartError> {
        if self.parts.len() != of.parts as usize {
            *self = SceneAssembly {
                of: Some(of),
                parts: vec![None; of.parts as usize],
            };
        }
        match self.of {
            Some(expected) if expected != of => {
                return Err(PartError::Mismatch {
                    part,
                    got: of,
                    expected,
                });
            }
            _ => self.of = Some(of),
        }
        let slot = self
            .parts
            .get_mut(part as usize)
            .ok_or(PartError::OutOfRange {
                part,
                parts: of.parts,
            })?;
        *slot = Some(bytes);
        if self.parts.iter().all(Option::is_some) {
            Ok(Some(std::mem::take(self)))
        } else {
            Ok(None)
        }
    }

    /// The parts' bytes in order: a scene of one part where it came, one of several joined
    /// once.
    fn bytes(&self) -> Cow<'_, [u8]> {
        match &self.parts[..] {
            [Some(only)] => Cow::Borrowed(only.bytes()),
            parts => {
                let len = parts.iter().flatten().map(|p| p.len).sum();
                let mut all = Vec::with_capacity(len);
                for p in parts.iter().flatten() {
                    all.extend_from_slice(p.bytes());
                }
                Cow::Owned(all)
            }
        }
    }
}

/// Why the scene the host sent cannot be prepared.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PrepareError {
    #[error("scene parts hold {got} bytes, expected {expected}")]
    Size { got: u64, expected: u64 },
    #[error("the scene description does not decode: {0}")]
    Decode(#[from] protocol::DecodeError),
    #[error("the scene description is invalid: {0}")]
    Invalid(#[from] renderer::scene::SceneError),
    #[error(
        "chunk {chunk} is {bytes} bytes, more than the {limit} bytes a frame carries between \
         processes; render with --chunk-triangles {fits} or fewer"
    )]
    ChunkTooLarge {
        chunk: usize,
        bytes: u64,
        limit: u32,
        fits: u64,
    },
}

/// Decodes the assembled scene description and prepares it.
pub(crate) fn prepare_scene(a: SceneAssembly) -> Result<(SceneHeader, MemoryData), PrepareError> {
    let of = a.of.unwrap_or(PartOf {
        parts: 0,
        total: 0,
        chunk_triangles: 0,
    });
    let bytes = a.bytes();
    if bytes.len() as u64 != of.total {
        return Err(PrepareError::Size {
            got: bytes.len() as u64,
            expected: of.total,
        });
    }
    let desc: SceneDesc = decode_value(&bytes)?;
    desc.validate()?;
    let opts = PrepareOptions {
        chunk_triangles: (of.chunk_triangles as usize).max(1),
    };
    let (header, data) = renderer::prepare(desc, &opts);
    chunks_fit_frames(&header, protocol::MAX_DATA)?;
    Ok((header, data))
}

/// Every chunk may have to cross a socket in one frame of at most `limit` bytes of data (to a
/// card or a render node on another machine, or by serial link): a scene with one that
/// cannot is refused before any chunk is placed, instead of ending the connection that would
/// carry it, with a chunk size that fits (from the largest chunk's bytes a triangle).
fn chunks_fit_frames(header: &SceneHeader, limit: u32) -> Result<(), PrepareError> {
    let largest = (header.chunks.iter().enumerate()).max_by_key(|(_, c)| c.byte_len);
    match largest {
        Some((chunk, c)) if c.byte_len > limit => {
            let fits = u64::from(c.tri_count) * u64::from(limit) / u64::from(c.byte_len);
            Err(PrepareError::ChunkTooLarge {
                chunk,
                bytes: u64::from(c.byte_len),
                limit,
                fits: fits.max(1),
            })
        }
        _ => Ok(()),
    }
}

/// Which fork node holds each of `count` items: round-robin, so that every card holds a
/// share and the G-bus traffic spreads over all of them.
pub(crate) fn round_robin(count: usize, forks: &[NodeId]) -> Vec<NodeId> {
    (0..count).map(|i| forks[i % forks.len()]).collect()
}

/// Where every chunk and tile of a prepared scene lives.
#[derive(Clone)]
pub(crate) struct Placement {
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
}

impl ForkNode {
    /// The first fork node collects the scene from the host, then prepares and places it.
    pub(crate) fn on_scene_part(
        self: Arc<ForkNode>,
        frame: Frame,
        part: u32,
        of: PartOf,
        len: u32,
    ) {
        let Some(bytes) = Part::new(frame.data, len as usize) else {
            tracing::warn!("fork node {}: scene part {part} is short", self.fabric.me());
            return;
        };
        let added = self
            .assembly
            .lock()
            .expect("assembly lock")
            .add(part, of, bytes);
        let assembly = match added {
            Ok(Some(whole)) => whole,
            Ok(None) => return,
            Err(e) => {
                tracing::warn!("fork node {}: {e}; ignored", self.fabric.me());
                return;
            }
        };
        tokio::spawn(async move {
            let prepared = tokio::task::spawn_blocking(move || prepare_scene(assembly)).await;
            let failure = match prepared {
                Ok(Ok((scene, data))) => return self.place(scene, data),
                Ok(Err(e)) => e.to_string(),
                Err(e) => format!("preparing the scene failed: {e}"),
            };
            tracing::error!("fork node {}: {failure}", self.fabric.me());
            let _ = self.fabric.send_control(
                0,
                &Message::Failed {
                    node: self.fabric.me(),
                    message: failure,
                },
            );
        });
    }

    /// Places chunks and tiles round-robin on the fork nodes and sends each its share, the
    /// header and the address table; the host gets the header too.
    fn place(self: &Arc<ForkNode>, scene: SceneHeader, data: MemoryData) {
        let f = &self.fabric;
        let forks = f.topology().fork_nodes();
        let placement = Placement {
            chunk_owner: round_robin(data.chunks.len(), &forks),
            tile_owner: round_robin(data.tiles.len(), &forks),
        };
        let header = encode_value(&scene);
        let header_msg = Message::Header {
            len: header.len() as u64,
            chunk_owner: placement.chunk_owner.clone(),
            tile_owner: placement.tile_owner.clone(),
        };
        let header_words = bytes_to_words(&header);
        tracing::info!(
            "fork node {}: prepared {} triangles in {} chunks ({} bytes), {} tiles; placing on {} fork nodes",
            f.me(),
            scene.triangle_count(),
            data.chunks.len(),
            scene.shape_bytes,
            data.tiles.len(),
            forks.len()
        );
        let _ = f.send_direct(0, &header_msg, header_words.clone(), 0, 0);
        // The cards on this machine get their shares as segments that this node writes (see
        // `segment`); the others over their sockets.
        let dir = self.segment_dir();
        let here: Vec<NodeId> = (forks.iter().copied())
            .filter(|&k| dir.is_some() && (k == f.me() || f.same_machine(k)))
            .collect();
        for &fork in forks.iter().filter(|&&k| k != f.me()) {
            let _ = f.send_direct(fork, &header_msg, header_words.clone(), 0, 0);
            if !here.contains(&fork) {
                self.send_share(fork, &placement, &data);
            }
        }
        self.on_header(
            header,
            placement.chunk_owner.clone(),
            placement.tile_owner.clone(),
        );
        match dir {
            Some(dir) if !here.is_empty() => {
                let node = self.clone();
                tokio::task::spawn_blocking(move || {
                    node.share_through_segments(dir, here, placement, data)
                });
            }
            _ => self.keep_share(&placement, &data),
        }
    }

    /// This node's own share goes straight into its memory (the header is there already).
    pub(crate) fn keep_share(self: &Arc<ForkNode>, placement: &Placement, data: &MemoryData) {
        let me = self.fabric.me();
        let mut count = 0u32;
        for (i, c) in owned(&data.chunks, &placement.chunk_owner, me) {
            // The walking form the preparation built, kept for the segment.
            let walk = c.accel().to_words();
            self.store(DataId::Chunk(i as u32), c.words().into(), Some(walk));
            count += 1;
        }
        for (i, t) in owned(&data.tiles, &placement.tile_owner, me) {
            self.store(DataId::Tile(i as u32), t.texels[..].into(), None);
            count += 1;
        }
        self.memory.lock().expect("memory lock").expected = Some(count);
        self.maybe_ready();
    }

    /// Another fork node's share travels to it, then the count that tells it all is there.
    pub(crate) fn send_share(&self, fork: NodeId, placement: &Placement, data: &MemoryData) {
        let f = &self.fabric;
        let hold = |id: DataId, words: Box<[u32]>| {
            let _ = f.send_direct(fork, &Message::Hold { id }, words, 0, 0);
        };
        let mut count = 0u32;
        for (i, c) in owned(&data.chunks, &placement.chunk_owner, fork) {
            hold(DataId::Chunk(i as u32), c.words().into());
            count += 1;
        }
        for (i, t) in owned(&data.tiles, &placement.tile_owner, fork) {
            hold(DataId::Tile(i as u32), t.texels[..].into());
            count += 1;
        }
        let _ = f.send_direct(fork, &Message::HoldDone { count }, Box::new([]), 0, 0);
    }
}

/// The items of `items` that `owners` places on `fork`, with their ids.
pub(crate) fn owned<'a, T>(
    items: &'a [T],
    owners: &'a [NodeId],
    fork: NodeId,
) -> impl Iterator<Item = (usize, &'a T)> + 'a {
    items
        .iter()
        .enumerate()
        .filter(move |(i, _)| owners[*i] == fork)
}

#[cfg(test)]
mod tests {
    use super::*;

    const OF: PartOf = PartOf {
        parts: 3,
        total: 9,
        chunk_triangles: 64,
    };

    fn bytes(whole: &SceneAssembly) -> Vec<u8> {
        whole.bytes().into_owned()
    }

    /// `bytes` as a part arrives: in a frame's words.
    fn part(bytes: &[u8]) -> Part {
        Part::new(bytes_to_words(bytes), bytes.len()).unwrap()
    }

    #[test]
    fn completes_from_parts_in_any_order() {
        for order in [[0, 1, 2], [2, 0, 1], [1, 2, 0]] {
            let mut a = SceneAssembly::default();
            let mut whole = None;
            for (n, &index) in order.iter().enumerate() {
                let data = [index as u8; 3];
                let added = a.add(index, OF, part(&data)).unwrap();
                assert_eq!(added.is_some(), n == 2, "order {order:?}");
                whole = whole.or(added);
            }
            assert_eq!(bytes(&whole.unwrap()), [0, 0, 0, 1, 1, 1, 2, 2, 2]);
            assert!(a.parts.is_empty(), "starts afresh after a whole scene");
        }
    }

    #[test]
    fn a_part_sent_twice_does_not_complete_the_scene() {
        let mut a = SceneAssembly::default();
        assert!(a.add(0, OF, part(&[0; 3])).unwrap().is_none());
        assert!(a.add(0, OF, part(&[0; 3])).unwrap().is_none());
        assert!(a.add(1, OF, part(&[1; 3])).unwrap().is_none());
    }

    #[test]
    fn refuses_a_part_beyond_the_count() {
        let mut a = SceneAssembly::default();
        assert_eq!(
            a.add(3, OF, part(&[0])).unwrap_err(),
            PartError::OutOfRange { part: 3, parts: 3 }
        );
    }

    #[test]
    fn refuses_a_part_of_another_scene_with_as_many_parts() {
        let mut a = SceneAssembly::default();
        a.add(0, OF, part(&[0; 3])).unwrap();
        let other = PartOf { total: 12, ..OF };
        assert_eq!(
            a.add(1, other, part(&[1; 3])).unwrap_err(),
            PartError::Mismatch {
                part: 1,
                got: other,
                expected: OF
            }
        );
        // The scene being assembled is untouched.
        a.add(1, OF, part(&[1; 3])).unwrap();
        assert!(a.add(2, OF, part(&[2; 3])).unwrap().is_some());
    }

    #[test]
    fn a_new_part_count_starts_a_new_scene() {
        let mut a = SceneAssembly::default();
        a.add(0, OF, part(&[0; 3])).unwrap();
        let single = PartOf {
            parts: 1,
            total: 2,
            chunk_triangles: 64,
        };
        let whole = a
            .add(0, single, part(&[7, 7]))
            .unwrap()
            .expect("one part is the whole");
        assert_eq!(bytes(&whole), [7, 7]);
    }

    #[test]
    fn prepares_the_whole_scene() {
        let desc = renderer::demo::demo_scene();
        let encoded = encode_value(&desc);
        let of = PartOf {
            parts: 2,
            total: encoded.len() as u64,
            chunk_triangles: 64,
        };
        let (first, second) = encoded.split_at(encoded.len() / 2);
        let mut a = SceneAssembly::default();
        assert!(a.add(1, of, part(second)).unwrap().is_none());
        let whole = a.add(0, of, part(first)).unwrap().unwrap();
        let (scene, data) = prepare_scene(whole).unwrap();
        assert_eq!(scene.chunks.len(), data.chunks.len());
        assert_eq!(scene.triangle_count(), desc.triangle_count() as u64);
    }

    /// A chunk larger than a frame carries is refused with a chunk size that fits (a render
    /// with 1.6 M triangles a chunk lost every connection that carried one, and waited).
    #[test]
    fn chunks_larger_than_a_frame_are_refused_with_a_size_that_fits() {
        let desc = renderer::demo::demo_scene();
        let (scene, _) = renderer::prepare(
            desc,
            &PrepareOptions {
                chunk_triangles: 64,
            },
        );
        assert!(chunks_fit_frames(&scene, protocol::MAX_DATA).is_ok());
        let largest = (scene.chunks.iter()).max_by_key(|c| c.byte_len).unwrap();
        let limit = largest.byte_len - 4;
        let e = chunks_fit_frames(&scene, limit).unwrap_err();
        let fits = u64::from(largest.tri_count) * u64::from(limit) / u64::from(largest.byte_len);
        assert!(fits < u64::from(largest.tri_count));
        assert!(
            e.to_string()
                .contains(&format!("render with --chunk-triangles {fits} or fewer")),
            "{e}"
        );
    }

    #[test]
    fn refuses_parts_that_do_not_add_up_to_the_total() {
        let mut a = SceneAssembly::default();
        let of = PartOf { parts: 1, ..OF };
        let whole = a.add(0, of, part(&[1, 2])).unwrap().unwrap();
        let err = prepare_scene(whole).unwrap_err();
        assert!(
            matches!(
                err,
                PrepareError::Size {
                    got: 2,
                    expected: 9
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn refuses_bytes_that_are_not_a_scene() {
        let mut a = SceneAssembly::default();
        let of = PartOf {
            parts: 1,
            total: 4,
            chunk_triangles: 64,
        };
        let whole = a.add(0, of, part(&[0xff; 4])).unwrap().unwrap();
        let err = prepare_scene(whole).unwrap_err();
        assert!(matches!(err, PrepareError::Decode(_)), "{err}");
    }

    #[test]
    fn places_round_robin_on_the_fork_nodes() {
        assert_eq!(round_robin(5, &[1, 8]), [1, 8, 1, 8, 1]);
        assert_eq!(round_robin(2, &[3]), [3, 3]);
        assert!(round_robin(0, &[1, 8]).is_empty());
    }
}
