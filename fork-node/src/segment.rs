//! This card's memory as real shared memory ([`fabric::shm`]): once the memory is complete,
//! the items it holds are written into a segment, and every render node of the cluster hears
//! of it (this card's directly, other cards' through their own fork node, which passes the
//! announcement on). Render nodes on this machine then read the card's items from the
//! mapping; the rest keep asking over TCP. The segment is removed when the fork node that
//! wrote it ends (`run`), or by the next fork node to start on this machine if that one was
//! killed.
//!
//! Each chunk goes in twice: its words, and its walking form, transcoded once for the card
//! instead of once in every render node that reads it. Render nodes walk the chunk in place,
//! so the scene is in this machine's memory once per card rather than once per render node,
//! and a render node's own memory holds only what came over TCP.
//!
//! The first fork node holds every chunk, with its walking form, once it has prepared the
//! scene. So it writes the segments of all the cards on its machine itself
//! ([`ForkNode::share_through_segments`]), its own among them, instead of sending each
//! card's share over a socket for that card's fork node to check, transcode, copy and write
//! out again. Each of those fork nodes takes its segment as its card's memory (it serves
//! what it is asked for from the mapping), and all of them tell their render nodes of every
//! card's segment before the header, so that no render node starts before it can read every
//! card of its machine in place. A fork node that cannot map its segment (a container with a
//! `/dev/shm` of its own on the same machine) says so, and gets its share over the socket.

use std::{
    collections::{HashMap, HashSet},
    path::Path,
    sync::{Arc, Mutex},
};

use fabric::shm::{self, Item, Part, Published, Segment, ShmError};
use protocol::{CardSegment, DataId, Message, NodeId};
use renderer::{MemoryData, accel::WalkHeader, chunk::Chunk};

use crate::{
    ForkNode,
    assembly::{Placement, owned},
    memory::SharedMemory,
};

/// The segments this fork node wrote (its card's; on the first fork node, those of the
/// other cards on its machine too), shared with `run` so that they are removed when the
/// role ends even though tasks may still hold the node.
pub(crate) type SegmentSlot = Arc<Mutex<HashMap<NodeId, Published>>>;

/// What this card's render nodes are told of segments, before their header.
#[derive(Default)]
pub(crate) struct Announced {
    /// This card's segment, written here or by the first fork node.
    own: Option<CardSegment>,
    /// The other cards' segments that the first fork node wrote.
    others: Vec<CardSegment>,
}

/// On the first fork node: the fork nodes that have not yet answered for the segment
/// written for them, and the prepared scene, kept meanwhile in case one cannot use it and
/// needs its share over the socket.
#[derive(Default)]
pub(crate) struct SharesInSegments {
    waiting: HashSet<NodeId>,
    scene: Option<Prepared>,
}

/// The prepared scene and where its items go, for a share sent over a socket.
type Prepared = (Arc<MemoryData>, Placement);

impl SharesInSegments {
    /// Fork node `from` answered: `None` if it was not waited for, else the prepared scene
    /// (while kept), which is let go once nobody is waited for.
    fn answered(&mut self, from: NodeId) -> Option<Option<Prepared>> {
        if !self.waiting.remove(&from) {
            return None;
        }
        let scene = self.scene.clone();
        if self.waiting.is_empty() {
            self.scene = None;
        }
        Some(scene)
    }

    /// Stops waiting for fork nodes that are gone (the host rebuilds their shares from its
    /// own copy), so that the prepared scene is not kept for an answer that cannot come.
    pub(crate) fn forget_gone(&mut self, alive: impl Fn(NodeId) -> bool) {
        self.waiting.retain(|&n| alive(n));
        if self.waiting.is_empty() {
            self.scene = None;
        }
    }
}

/// Why a fork node does not take the segment written for its card.
#[derive(Debug, thiserror::Error)]
pub(crate) enum AdoptError {
    #[error("no segment is listed for this card")]
    NotListed,
    #[error(transparent)]
    Shm(#[from] ShmError),
    #[error(
        "it holds {held} items, {count} announced, where the address table gives this card {own}"
    )]
    NotThisShare { held: usize, count: u32, own: usize },
}

impl ForkNode {
    /// The machine's shared-memory directory, where this node writes segments, with the
    /// segments of fork nodes that died before removing theirs cleared out; `None` (said
    /// once) where there is none, and every render node then reads over TCP.
    pub(crate) fn segment_dir(&self) -> Option<&'static Path> {
        let me = self.fabric.me();
        let dir = Path::new(shm::SHM_DIR);
        if !dir.is_dir() {
            tracing::info!(
                "fork node {me}: no {} here; render nodes read over TCP",
                shm::SHM_DIR
            );
            return None;
        }
        let stale = shm::remove_stale(dir);
        if stale > 0 {
            tracing::info!("fork node {me}: removed {stale} segments left by fork nodes that died");
        }
        Some(dir)
    }

    /// On the first fork node, with the scene prepared and its header taken: writes the
    /// segment of each card of `here` (this one and the others on this machine; their fork
    /// nodes have the header), tells each other fork node that its share is in its segment,
    /// and takes its own. A share whose segment cannot be written goes over the socket. Runs
    /// off the runtime (it writes the shares: tens of megabytes).
    pub(crate) fn share_through_segments(
        self: &Arc<ForkNode>,
        dir: &Path,
        here: Vec<NodeId>,
        placement: Placement,
        data: MemoryData,
    ) {
        let f = &self.fabric;
        let me = f.me();
        let data = Arc::new(data);
        let mut notices = Vec::new();
        let mut counts = Vec::new();
        for (fork, written) in write_shares(dir, &here, &placement, &data) {
            match written {
                Ok((published, count)) => {
                    tracing::debug!(
                        "fork node {me}: wrote card {fork}'s share, {count} items, {} bytes, as {}",
                        published.bytes,
                        published.path().display()
                    );
                    notices.push(CardSegment {
                        card: fork,
                        name: published.name.clone(),
                        nonce: published.nonce,
                        bytes: published.bytes,
                    });
                    counts.push((fork, count));
                    (self.segment.lock().expect("segment lock")).insert(fork, published);
                }
                Err(e) if fork == me => {
                    tracing::warn!("fork node {me}: {e}; keeps its own share in its memory")
                }
                Err(e) => {
                    tracing::warn!(
                        "fork node {me}: {e}; fork node {fork}'s share goes over the socket"
                    );
                    self.send_share(fork, &placement, &data);
                }
            }
        }
        let others: Vec<(NodeId, u32)> = counts.iter().copied().filter(|c| c.0 != me).collect();
        if !others.is_empty() {
            // Waiting before any is asked: an answer may come at once.
            let mut s = self.shares.lock().expect("shares lock");
            s.waiting = others.iter().map(|c| c.0).collect();
            s.scene = Some((data.clone(), placement.clone()));
        }
        for (fork, count) in others {
            let msg = Message::ShareInSegment {
                count,
                segments: notices.clone(),
            };
            let _ = f.send_direct(fork, &msg, Box::new([]), 0, 0);
        }
        let own = counts.iter().find(|c| c.0 == me).map(|c| c.1);
        let taken = own.map(|count| self.take_segment(&notices, count));
        match taken {
            Some(Ok(())) => self.maybe_ready(),
            Some(Err(e)) => {
                tracing::warn!("fork node {me}: cannot take its own segment ({e}); keeps a copy");
                self.keep_share(&placement, &data);
            }
            None => self.keep_share(&placement, &data),
        }
    }

    /// On the first fork node: fork node `from` took the segment written for its card, or
    /// could not map it and gets its share over the socket instead.
    pub(crate) fn on_share_answer(&self, from: NodeId, adopted: bool) {
        let answered = self.shares.lock().expect("shares lock").answered(from);
        // An answer to nothing asked is ignored.
        let Some(scene) = answered else { return };
        if adopted {
            return;
        }
        // Its segment goes, and its render nodes read the card over TCP.
        drop(self.segment.lock().expect("segment lock").remove(&from));
        if let Some((data, placement)) = scene {
            tracing::info!(
                "fork node {}: fork node {from} cannot map the segment written for it; its share goes over the socket",
                self.fabric.me()
            );
            self.send_share(from, &placement, &data);
        }
    }

    /// A fork node told by the first fork node (`from`) that its share is in a segment:
    /// takes it as its card's memory, and answers.
    pub(crate) fn on_share_in_segment(
        self: &Arc<ForkNode>,
        from: NodeId,
        count: u32,
        segments: Vec<CardSegment>,
    ) {
        let f = &self.fabric;
        let taken = self.take_segment(&segments, count);
        match &taken {
            Ok(()) => tracing::debug!(
                "fork node {}: took the segment fork node {from} wrote, {count} items",
                f.me()
            ),
            Err(e) => tracing::info!(
                "fork node {}: cannot take the segment fork node {from} wrote ({e}); asks for its share over the socket",
                f.me()
            ),
        }
        let answer = Message::ShareAnswer {
            adopted: taken.is_ok(),
        };
        let _ = f.send_direct(from, &answer, Box::new([]), 0, 0);
        if taken.is_ok() {
            self.maybe_ready();
        }
    }

    /// Takes this card's segment among `segments` as its memory: mapped, and holding exactly
    /// the `count` items the address table (in the header, which came first) gives this
    /// card. The others are kept to be announced to this card's render nodes.
    fn take_segment(&self, segments: &[CardSegment], count: u32) -> Result<(), AdoptError> {
        let me = self.fabric.me();
        let own = (segments.iter())
            .find(|s| s.card == me)
            .ok_or(AdoptError::NotListed)?;
        let dir = Path::new(shm::SHM_DIR);
        let segment = Segment::open(dir, &own.name, own.nonce, own.bytes)?;
        {
            let mut m = self.memory.lock().expect("memory lock");
            share_fits(&m, me, &segment, count)?;
            m.adopt(segment);
        }
        let mut a = self.announced.lock().expect("announced lock");
        a.own = Some(own.clone());
        a.others = segments.iter().filter(|s| s.card != me).cloned().collect();
        Ok(())
    }

    /// Tells this card's render nodes (once) of every segment they may read, and the other
    /// fork nodes of this card's: the segment written by the first fork node, or one written
    /// now. Without a shared-memory directory, or if writing fails, this card's is not
    /// announced and every render node reads it over TCP.
    pub(crate) fn publish_segment(&self, card: &[NodeId]) {
        let f = &self.fabric;
        // Taken whether or not a segment is written, so that none stays held for nothing.
        let kept = {
            let mut m = self.memory.lock().expect("memory lock");
            m.walks_taken = true;
            std::mem::take(&mut m.walks)
        };
        let (own, others) = {
            let a = self.announced.lock().expect("announced lock");
            (a.own.clone(), a.others.clone())
        };
        for announce in others.into_iter().map(Message::SharedSegment) {
            for &r in card {
                let _ = f.send_direct(r, &announce, Box::new([]), 0, 0);
            }
        }
        let Some(own) = own.or_else(|| self.write_segment(kept)) else {
            return;
        };
        let forks = f.topology().fork_nodes();
        let other_forks = forks.into_iter().filter(|&n| n != f.me());
        let announce = Message::SharedSegment(own);
        for to in card.iter().copied().chain(other_forks) {
            let _ = f.send_direct(to, &announce, Box::new([]), 0, 0);
        }
    }

    /// Writes this card's memory as its segment, with the walking forms `kept` from the
    /// checks on arrival (transcoded here for a chunk held without one).
    fn write_segment(&self, mut kept: HashMap<DataId, Vec<u32>>) -> Option<CardSegment> {
        let f = &self.fabric;
        let dir = self.segment_dir()?;
        let items: Vec<(DataId, Arc<[u32]>)> = {
            let m = self.memory.lock().expect("memory lock");
            let mut items: Vec<_> = m.data.iter().map(|(id, w)| (*id, w.clone())).collect();
            items.sort_by_key(|(id, _)| match *id {
                DataId::Chunk(c) => (0, c),
                DataId::Tile(t) => (1, t),
                DataId::Synthetic { bytes } => (2, bytes),
            });
            items
        };
        // Each chunk's walking form as its check on arrival made it (or the preparation, on
        // the first fork node); transcoded here only for a chunk held without one.
        let walks: Vec<(DataId, Vec<u32>)> = items
            .iter()
            .filter(|(id, _)| matches!(id, DataId::Chunk(_)))
            .filter_map(|(id, w)| match kept.remove(id) {
                Some(walk) => Some((*id, walk)),
                None => match Chunk::from_words(w[..].into()) {
                    Ok(chunk) => Some((*id, chunk.accel().to_words())),
                    Err(e) => {
                        // Render nodes refuse it as well, whichever way it reaches them.
                        tracing::warn!("fork node {}: {id:?} is not a valid chunk: {e}", f.me());
                        None
                    }
                },
            })
            .collect();
        let refs: Vec<Item> = items
            .iter()
            .map(|(id, w)| Item::whole(*id, Part::Words, &w[..]))
            .chain(walks.iter().map(|(id, w)| Item::whole(*id, Part::Walk, w)))
            .collect();
        let published = match Published::create(dir, f.me(), &refs) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!(
                    "fork node {}: {e}; render nodes read this card over TCP",
                    f.me()
                );
                return None;
            }
        };
        tracing::debug!(
            "fork node {}: published {} items, {} bytes, as {}",
            f.me(),
            refs.len(),
            published.bytes,
            published.path().display()
        );
        let own = CardSegment {
            card: f.me(),
            name: published.name.clone(),
            nonce: published.nonce,
            bytes: published.bytes,
        };
        (self.segment.lock().expect("segment lock")).insert(f.me(), published);
        self.announced.lock().expect("announced lock").own = Some(own.clone());
        Some(own)
    }

    /// Another fork node's announcement: passed on to this card's render nodes, which may
    /// share that fork node's machine too.
    pub(crate) fn relay_segment(&self, from: NodeId, announce: &Message) {
        let f = &self.fabric;
        if !matches!(announce, Message::SharedSegment(s) if s.card == from) {
            return;
        }
        for r in self.card_render_nodes() {
            let _ = f.send_direct(r, announce, Box::new([]), 0, 0);
        }
    }
}

/// Whether `segment` holds exactly the `count` items that the address table in `m` gives
/// card `me`: a segment for another card, or from another placement, is not taken.
fn share_fits(
    m: &SharedMemory,
    me: NodeId,
    segment: &Segment,
    count: u32,
) -> Result<(), AdoptError> {
    let mine = |id: &DataId| m.owner(*id) == Some(me);
    let held = segment.ids(Part::Words).count();
    let own = m.all_ids().iter().filter(|id| mine(id)).count();
    if held != count as usize || held != own || !segment.ids(Part::Words).all(|id| mine(&id)) {
        return Err(AdoptError::NotThisShare { held, count, own });
    }
    Ok(())
}

/// A card's share written as its segment, with the number of items in it.
type Written = Result<(Published, u32), ShmError>;

/// Writes the share of each card of `forks` as its segment in `dir`, on as many threads as
/// there are CPUs (up to one a card): what writing costs is mostly the kernel's, clearing the
/// pages of the shared-memory file system, so it scales with the CPUs.
fn write_shares(
    dir: &Path,
    forks: &[NodeId],
    placement: &Placement,
    data: &MemoryData,
) -> Vec<(NodeId, Written)> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = threads.clamp(1, forks.len().max(1));
    let mut done: Vec<_> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads)
            .map(|t| {
                s.spawn(move || {
                    (forks.iter().skip(t).step_by(threads))
                        .map(|&fork| (fork, write_share(dir, fork, placement, data)))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        (workers.into_iter())
            .flat_map(|w| w.join().expect("a segment writer panicked"))
            .collect()
    });
    done.sort_by_key(|(fork, _)| forks.iter().position(|f| f == fork));
    done
}

/// Card `fork`'s share of the prepared scene as that card's segment in `dir`, words and
/// walking forms.
fn write_share(dir: &Path, fork: NodeId, placement: &Placement, data: &MemoryData) -> Written {
    let chunks: Vec<(usize, &Chunk)> = owned(&data.chunks, &placement.chunk_owner, fork).collect();
    let tiles: Vec<_> = owned(&data.tiles, &placement.tile_owner, fork).collect();
    // Written from the trees as they are: joined first, each would be copied into fresh
    // memory on the way to the segment that the render nodes wait for.
    let heads: Vec<WalkHeader> = chunks
        .iter()
        .map(|(_, c)| c.accel().walk_header())
        .collect();
    let words =
        (chunks.iter()).map(|&(i, c)| Item::whole(DataId::Chunk(i as u32), Part::Words, c.words()));
    let tile_items = (tiles.iter())
        .map(|&(i, t)| Item::whole(DataId::Tile(i as u32), Part::Words, &t.texels[..]));
    let walk_items = chunks.iter().zip(&heads).map(|(&(i, c), head)| Item {
        id: DataId::Chunk(i as u32),
        part: Part::Walk,
        pieces: c.accel().word_pieces(head).to_vec(),
    });
    let items: Vec<Item> = words.chain(tile_items).chain(walk_items).collect();
    let published = Published::create(dir, fork, &items)?;
    Ok((published, (chunks.len() + tiles.len()) as u32))
}

#[cfg(test)]
mod tests {
    use renderer::PrepareOptions;

    use super::*;
    use crate::assembly::round_robin;

    /// A private directory, removed at the end.
    struct Dir(std::path::PathBuf);

    impl Dir {
        fn new() -> Dir {
            let p =
                std::env::temp_dir().join(format!("magg-fork-segment-test-{}", std::process::id()));
            std::fs::create_dir_all(&p).unwrap();
            Dir(p)
        }
    }

    impl Drop for Dir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn scene() -> (renderer::SceneHeader, MemoryData) {
        let opts = PrepareOptions {
            chunk_triangles: 64,
        };
        renderer::prepare(renderer::demo::demo_scene(), &opts)
    }

    /// The card memory a fork node has once the header came: the address table.
    fn memory_of(placement: &Placement, header: &renderer::SceneHeader) -> SharedMemory {
        SharedMemory {
            scene: Some(Arc::new(header.clone())),
            chunk_owner: placement.chunk_owner.clone(),
            tile_owner: placement.tile_owner.clone(),
            ..SharedMemory::default()
        }
    }

    #[test]
    fn the_prepared_scene_is_kept_until_every_fork_node_still_alive_has_answered() {
        let (_, data) = scene();
        let placement = Placement {
            chunk_owner: vec![],
            tile_owner: vec![],
        };
        let mut s = SharesInSegments {
            waiting: [2, 3, 4].into(),
            scene: Some((Arc::new(data), placement)),
        };
        assert!(s.answered(9).is_none(), "not waited for");
        assert!(matches!(s.answered(2), Some(Some(_))), "kept for a refusal");
        s.forget_gone(|n| n != 3);
        assert!(s.scene.is_some(), "4 has not answered");
        assert!(matches!(s.answered(4), Some(Some(_))));
        assert!(s.scene.is_none() && s.waiting.is_empty(), "let go");
        assert!(s.answered(4).is_none(), "answered once");
        let mut s = SharesInSegments {
            waiting: [2].into(),
            scene: Some((
                Arc::new(scene().1),
                Placement {
                    chunk_owner: vec![],
                    tile_owner: vec![],
                },
            )),
        };
        s.forget_gone(|_| false);
        assert!(s.scene.is_none(), "nobody left to answer");
    }

    #[test]
    fn each_card_segment_holds_its_share_with_the_walking_forms_and_is_taken_by_that_card_only() {
        let (header, data) = scene();
        assert!(data.chunks.len() >= 3, "{} chunks", data.chunks.len());
        let forks = [1, 2, 3];
        let placement = Placement {
            chunk_owner: round_robin(data.chunks.len(), &forks),
            tile_owner: round_robin(data.tiles.len(), &forks),
        };
        let dir = Dir::new();
        let written = write_shares(&dir.0, &forks, &placement, &data);
        assert_eq!(written.iter().map(|w| w.0).collect::<Vec<_>>(), forks);
        let mut total = 0;
        for (fork, w) in written {
            let (published, count) = w.unwrap();
            let segment =
                Segment::open(&dir.0, &published.name, published.nonce, published.bytes).unwrap();
            for (i, c) in owned(&data.chunks, &placement.chunk_owner, fork) {
                let id = DataId::Chunk(i as u32);
                assert_eq!(segment.read(id).unwrap(), c.words(), "card {fork}, {id:?}");
                let (start, end) = segment.place(id, Part::Walk).unwrap();
                assert_eq!(segment.words()[start..end], c.accel().to_words()[..]);
            }
            for (i, t) in owned(&data.tiles, &placement.tile_owner, fork) {
                let id = DataId::Tile(i as u32);
                assert_eq!(
                    segment.read(id).unwrap(),
                    &t.texels[..],
                    "card {fork}, {id:?}"
                );
            }
            let mut m = memory_of(&placement, &header);
            share_fits(&m, fork, &segment, count).unwrap();
            // Another card's segment, or a count that disagrees, is not taken.
            let other = forks[fork as usize % forks.len()];
            let e = share_fits(&m, other, &segment, count).unwrap_err();
            assert!(matches!(e, AdoptError::NotThisShare { .. }), "{e}");
            let e = share_fits(&m, fork, &segment, count + 1).unwrap_err();
            assert!(matches!(e, AdoptError::NotThisShare { .. }), "{e}");
            // Taken, the card serves its items from the mapping.
            m.adopt(segment);
            assert!(m.complete());
            assert_eq!(m.adopted_items(), count);
            for (i, c) in owned(&data.chunks, &placement.chunk_owner, fork) {
                assert_eq!(&m.item(DataId::Chunk(i as u32)).unwrap()[..], c.words());
            }
            let foreign = owned(&data.chunks, &placement.chunk_owner, other).next();
            let foreign = DataId::Chunk(foreign.unwrap().0 as u32);
            assert!(m.item(foreign).is_none(), "not this card's");
            total += count as usize;
        }
        assert_eq!(total, data.chunks.len() + data.tiles.len());
    }
}
