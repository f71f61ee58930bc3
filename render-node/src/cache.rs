//! The shape data cache (the paper's figure 1.8): chunks and texture tiles a render node has
//! fetched from its fork node, within a byte budget, the least recently used evicted first.
//!
//! It is the renderer's [`SceneData`] on a render node. A miss blocks the rendering thread
//! while the request travels to the fork node and the data comes back (by DMA or through the
//! mesh); the bytes received are validated once and then used in place.

use std::{
    sync::{
        Arc, Mutex, RwLock,
        atomic::{AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::{Fabric, Route};
use protocol::{DataId, Message, NodeId, Transfer};
use renderer::{DataError, SceneData, chunk::Chunk, scene::ChunkRules, texture::Tile};

#[derive(Clone)]
enum Item {
    Chunk(Arc<Chunk>),
    Tile(Arc<Tile>),
}

/// One cache slot per chunk and per tile id (ids are dense), so a hit is a read lock and a
/// timestamp, never a search. Eviction, on the rare miss, scans for the oldest timestamp:
/// exact least-recently-used order without bookkeeping on the hit path.
#[derive(Default)]
struct Slot {
    item: RwLock<Option<Item>>,
    last_use: AtomicU64,
    bytes: AtomicU64,
}

/// Counters of the cache's work.
#[derive(Default)]
pub struct CacheStats {
    pub hits: AtomicU64,
    pub misses: AtomicU64,
    pub evictions: AtomicU64,
    pub peak_bytes: AtomicU64,
    pub bytes_dma: AtomicU64,
    pub bytes_serial: AtomicU64,
    /// Nanoseconds rendering threads spent waiting for fetches.
    pub wait_ns: AtomicU64,
}

/// Where misses go.
pub struct Source {
    pub fabric: Fabric,
    pub runtime: tokio::runtime::Handle,
    pub fork: NodeId,
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
    pub via: Transfer,
}

pub struct DemandCache {
    /// What a chunk must agree with before it is used.
    rules: ChunkRules,
    chunks: Vec<Slot>,
    tiles: Vec<Slot>,
    clock: AtomicU64,
    /// Bytes resident; changed only under `insert_lock`.
    used: AtomicU64,
    insert_lock: Mutex<()>,
    budget: u64,
    /// `None` in batch mode: everything is already here and nothing may be fetched.
    source: Option<Source>,
    pub stats: CacheStats,
}

const FETCH_TIMEOUT: Duration = Duration::from_secs(120);

thread_local! {
    /// Hits counted on this thread and not yet added to the shared counter: a hit is the
    /// renderer's commonest operation, so it must not touch shared cache lines.
    static LOCAL_HITS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

impl DemandCache {
    /// A cache for a scene whose chunks follow `rules`, with `tiles` texture tiles.
    pub fn new(
        rules: ChunkRules,
        tiles: usize,
        budget: u64,
        source: Option<Source>,
    ) -> DemandCache {
        DemandCache {
            chunks: (0..rules.len()).map(|_| Slot::default()).collect(),
            rules,
            tiles: (0..tiles).map(|_| Slot::default()).collect(),
            clock: AtomicU64::new(1),
            used: AtomicU64::new(0),
            insert_lock: Mutex::new(()),
            budget,
            source,
            stats: CacheStats::default(),
        }
    }

    fn slot(&self, id: DataId) -> Result<&Slot, DataError> {
        match id {
            DataId::Chunk(c) => self.chunks.get(c as usize).ok_or(DataError::NoChunk(c)),
            DataId::Tile(t) => self.tiles.get(t as usize).ok_or(DataError::NoTile(t)),
            DataId::Synthetic { .. } => {
                Err(DataError::Fetch("synthetic data is not cached".into()))
            }
        }
    }

    /// Puts data in without fetching (batch transfer), validated like fetched data.
    pub fn preload(&self, id: DataId, words: Box<[u32]>) -> Result<(), DataError> {
        let item = validate(&self.rules, id, words)?;
        let bytes = item_bytes(&item);
        self.insert(id, item, bytes, false)?;
        Ok(())
    }

    pub fn used_bytes(&self) -> u64 {
        self.used.load(Ordering::Relaxed)
    }

    /// Puts an item in its slot, first evicting the least recently used until it fits.
    /// Returns the item now in the slot (another thread may have put it there first).
    fn insert(&self, id: DataId, item: Item, bytes: u64, evict: bool) -> Result<Item, DataError> {
        let _guard = self.insert_lock.lock().expect("cache lock");
        let slot = self.slot(id)?;
        if let Some(existing) = slot.item.read().expect("slot lock").clone() {
            return Ok(existing);
        }
        if evict {
            while self.used.load(Ordering::Relaxed) + bytes > self.budget {
                let oldest = self
                    .chunks
                    .iter()
                    .chain(self.tiles.iter())
                    .filter(|s| s.bytes.load(Ordering::Relaxed) > 0)
                    .min_by_key(|s| s.last_use.load(Ordering::Relaxed));
                let Some(victim) = oldest else { break };
                *victim.item.write().expect("slot lock") = None;
                let freed = victim.bytes.swap(0, Ordering::Relaxed);
                self.used.fetch_sub(freed, Ordering::Relaxed);
                self.stats.evictions.fetch_add(1, Ordering::Relaxed);
            }
        }
        *slot.item.write().expect("slot lock") = Some(item.clone());
        slot.bytes.store(bytes, Ordering::Relaxed);
        slot.last_use
            .store(self.clock.load(Ordering::Relaxed), Ordering::Relaxed);
        let used = self.used.fetch_add(bytes, Ordering::Relaxed) + bytes;
        self.stats.peak_bytes.fetch_max(used, Ordering::Relaxed);
        Ok(item)
    }

    /// Advances the recency clock; rendering threads call it once per pixel, so recency is
    /// known to the pixel and a hit needs no read-modify-write of a shared counter.
    pub fn tick(&self) {
        self.clock.fetch_add(1, Ordering::Relaxed);
    }

    /// Adds this thread's hits to the shared counter.
    pub fn flush_thread_counts(&self) {
        let h = LOCAL_HITS.with(|c| c.replace(0));
        self.stats.hits.fetch_add(h, Ordering::Relaxed);
    }

    fn get(&self, id: DataId) -> Result<Item, DataError> {
        let slot = self.slot(id)?;
        if let Some(item) = slot.item.read().expect("slot lock").clone() {
            slot.last_use
                .store(self.clock.load(Ordering::Relaxed), Ordering::Relaxed);
            LOCAL_HITS.with(|c| c.set(c.get() + 1));
            return Ok(item);
        }
        self.stats.misses.fetch_add(1, Ordering::Relaxed);
        let Some(src) = &self.source else {
            return Err(DataError::Fetch(format!(
                "{id:?} is missing from the batch transfer"
            )));
        };
        let owner = match id {
            DataId::Chunk(c) => src.chunk_owner.get(c as usize),
            DataId::Tile(t) => src.tile_owner.get(t as usize),
            DataId::Synthetic { .. } => None,
        }
        .copied()
        .ok_or(DataError::Fetch(format!(
            "{id:?} is not in the address table"
        )))?;
        let start = Instant::now();
        let request = Message::DataRequest {
            id,
            transfer: src.via,
            owner,
        };
        let fabric = src.fabric.clone();
        let fork = src.fork;
        let reply = src
            .runtime
            .block_on(async move {
                fabric
                    .request(fork, &request, Box::new([]), Route::Mesh, FETCH_TIMEOUT)
                    .await
            })
            .map_err(|e| DataError::Fetch(e.to_string()))?;
        self.stats
            .wait_ns
            .fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
        let bytes = reply.data.len() as u64 * 4;
        match src.via {
            Transfer::Dma => self.stats.bytes_dma.fetch_add(bytes, Ordering::Relaxed),
            Transfer::Serial => self.stats.bytes_serial.fetch_add(bytes, Ordering::Relaxed),
        };
        let item = validate(&self.rules, id, reply.data)?;
        let size = item_bytes(&item);
        if size > self.budget {
            return Err(DataError::Fetch(format!(
                "{id:?} is {size} bytes, more than the whole cache budget of {} bytes",
                self.budget
            )));
        }
        self.insert(id, item, size, true)
    }
}

fn item_bytes(item: &Item) -> u64 {
    match item {
        Item::Chunk(c) => c.byte_len() as u64,
        Item::Tile(t) => t.as_bytes().len() as u64,
    }
}

fn validate(rules: &ChunkRules, id: DataId, words: Box<[u32]>) -> Result<Item, DataError> {
    match id {
        DataId::Chunk(c) => {
            let chunk = Chunk::from_words(words)
                .map_err(|e| DataError::Corrupt(format!("chunk {c}: {e}")))?;
            rules.check(c, &chunk).map_err(DataError::Corrupt)?;
            Ok(Item::Chunk(Arc::new(chunk)))
        }
        DataId::Tile(_) => Ok(Item::Tile(Arc::new(Tile::from_words(words)?))),
        DataId::Synthetic { .. } => Err(DataError::Corrupt("synthetic data in the cache".into())),
    }
}

impl SceneData for DemandCache {
    type ChunkRef<'a> = Arc<Chunk>;
    type TileRef<'a> = Arc<Tile>;

    fn chunk(&self, id: u32) -> Result<Arc<Chunk>, DataError> {
        match self.get(DataId::Chunk(id))? {
            Item::Chunk(c) => Ok(c),
            Item::Tile(_) => Err(DataError::Corrupt(format!("chunk {id} holds a tile"))),
        }
    }

    fn tile(&self, id: u32) -> Result<Arc<Tile>, DataError> {
        match self.get(DataId::Tile(id))? {
            Item::Tile(t) => Ok(t),
            Item::Chunk(_) => Err(DataError::Corrupt(format!("tile {id} holds a chunk"))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use renderer::chunk::{MeshData, build_chunk};

    fn chunk(id: u32, tris: u32) -> Box<[u32]> {
        let mut m = MeshData::default();
        for i in 0..tris {
            let x = i as f32;
            m.positions
                .extend([glam_vec(x, 0.0), glam_vec(x + 1.0, 0.0), glam_vec(x, 1.0)]);
            m.triangles.push([3 * i, 3 * i + 1, 3 * i + 2]);
        }
        let all: Vec<u32> = (0..tris).collect();
        build_chunk(&m, &all, id, 0).unwrap().words().into()
    }

    fn rules(chunks: usize) -> ChunkRules {
        ChunkRules::new(vec![(0, 4); chunks], 0)
    }

    fn glam_vec(x: f32, y: f32) -> glam::Vec3 {
        glam::Vec3::new(x, y, 0.0)
    }

    #[test]
    fn evicts_least_recently_used_within_budget() {
        let size = chunk(0, 4).len() as u64 * 4;
        let cache = DemandCache::new(rules(3), 0, size * 2, None);
        cache.preload(DataId::Chunk(0), chunk(0, 4)).unwrap();
        cache.tick();
        cache.preload(DataId::Chunk(1), chunk(1, 4)).unwrap();
        cache.tick();
        assert!(cache.chunk(0).is_ok());
        cache.tick();
        // A third, inserted with eviction, pushes out chunk 1 (used least recently).
        let item = validate(&rules(3), DataId::Chunk(2), chunk(2, 4)).unwrap();
        cache.insert(DataId::Chunk(2), item, size, true).unwrap();
        assert!(cache.used_bytes() <= size * 2);
        assert!(cache.chunk(0).is_ok());
        assert!(cache.chunk(1).is_err(), "chunk 1 should have been evicted");
        assert_eq!(cache.stats.evictions.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn wrong_or_corrupt_data_is_refused() {
        let rules = ChunkRules::new(vec![(0, 2); 6], 0);
        assert!(validate(&rules, DataId::Chunk(5), chunk(5, 2)).is_ok());
        assert!(validate(&rules, DataId::Chunk(5), chunk(4, 2)).is_err());
        // The right id, but not what the scene says chunk 5 is.
        assert!(validate(&rules, DataId::Chunk(5), chunk(5, 3)).is_err());
        let other = ChunkRules::new(vec![(1, 2); 6], 0);
        assert!(validate(&other, DataId::Chunk(5), chunk(5, 2)).is_err());
        let mut w = chunk(5, 2).to_vec();
        w.truncate(w.len() - 1);
        assert!(validate(&rules, DataId::Chunk(5), w.into_boxed_slice()).is_err());
        assert!(validate(&rules, DataId::Tile(0), vec![0u32; 7].into_boxed_slice()).is_err());
    }
}
