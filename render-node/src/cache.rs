//! The shape data cache (the paper's figure 1.8): chunks and texture tiles a render node has
//! fetched from its fork node, within a byte budget, the least recently used evicted first.
//! The budget counts what an item takes once usable: a chunk's words and its walking form
//! (which is larger than the words), so that the cache is the memory it claims to be.
//!
//! Rendering threads read it through a [`Reader`], the renderer's [`SceneData`] on a render
//! node. A hit is what the renderer does most, so it costs one atomic load (the slot's
//! pointer) and a check of the slot's recency stamp: no lock, no reference count, no clock
//! read. That is safe because an evicted item is not freed at once: it is retired, and freed
//! only when every reader has since announced a newer epoch (epoch-based reclamation), which
//! a reader does between pixels (or batches of rays), when it holds no reference into the cache (the borrow
//! checker sees to that: [`Reader::refresh`] takes the reader mutably).
//!
//! A miss blocks the rendering thread while the request travels to the fork node and the
//! data comes back (by DMA or through the mesh); the bytes received are validated once (and
//! the chunk transcoded for the walk) and then used in place. A DMA read of a chunk from a
//! card whose shared-memory segment this node mapped ([`crate::shared`]) copies nothing: the
//! chunk's words and its walking form (which the fork node transcoded once for the card)
//! are checked where they lie in the mapping and walked there, and a tile's texels are
//! read there. The budget and the least-recently-used order count such items exactly as
//! copied ones, so what is fetched and evicted does not depend on the transport; only the
//! copy and the node's memory go.

use std::{
    cell::Cell,
    sync::{
        Arc, Mutex,
        atomic::{AtomicPtr, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::{Fabric, Route, shm::Part};
use protocol::{DataId, Message, NodeId, Transfer};
use renderer::{
    DataError, SceneData,
    accel::WalkPlace,
    chunk::Chunk,
    region::{Block, Region},
    scene::ChunkRules,
    source::{Deferral, Item},
    texture::Tile,
};

use crate::{
    forms::{self, FormArena},
    shared::Mapped,
};

/// What a miss brings: words of this node's own, or an item's place in a card's mapping.
enum Fetched {
    Words(Box<[u32]>),
    InPlace {
        segment: Arc<Mapped>,
        words: (usize, usize),
        walk: Option<(usize, usize)>,
    },
}

impl Fetched {
    fn word_count(&self) -> usize {
        match self {
            Fetched::Words(w) => w.len(),
            Fetched::InPlace { words, .. } => words.1 - words.0,
        }
    }

    /// The words wherever they lie, and where a chunk's walking form lies if the mapping
    /// holds one.
    fn into_parts(self) -> Result<(Region<u32>, Option<WalkPlace>), DataError> {
        match self {
            Fetched::Words(w) => Ok((Region::own(w), None)),
            Fetched::InPlace {
                segment,
                words,
                walk,
            } => {
                let block: Arc<dyn Block> = segment;
                let region =
                    Region::in_block(block.clone(), words.0, words.1).ok_or_else(|| {
                        DataError::Corrupt("an item misplaced in its card's segment".into())
                    })?;
                Ok((
                    region,
                    walk.map(|(start, end)| WalkPlace { block, start, end }),
                ))
            }
        }
    }
}

/// One slot per chunk and per tile id (ids are dense), so a hit is a load, never a search.
/// Eviction, on the rare miss, scans for the oldest stamp: least-recently-used order to the
/// pixel, with no bookkeeping on a hit beyond the stamp.
struct Slot<T> {
    item: AtomicPtr<T>,
    /// The recency clock when last used.
    last_use: AtomicU64,
    bytes: AtomicU64,
}

impl<T> Default for Slot<T> {
    fn default() -> Self {
        Slot {
            item: AtomicPtr::new(std::ptr::null_mut()),
            last_use: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
        }
    }
}

/// An evicted item waiting until no reader can still hold it.
enum Retired {
    Chunk(*mut Chunk),
    Tile(*mut Tile),
}

// SAFETY: a retired pointer is owned by the cache alone (unlinked from its slot), and chunks
// and tiles are themselves Send.
unsafe impl Send for Retired {}

impl Retired {
    /// # Safety
    /// No reader may still hold the item (its epoch has passed).
    unsafe fn free(self) {
        // SAFETY: the pointer came from Box::into_raw and is freed once (the caller's promise).
        unsafe {
            match self {
                Retired::Chunk(p) => drop(Box::from_raw(p)),
                Retired::Tile(p) => drop(Box::from_raw(p)),
            }
        }
    }
}

/// What only the inserting thread changes, under one lock: misses are rare.
#[derive(Default)]
struct State {
    /// Bytes resident in slots.
    used: u64,
    /// Evicted items, the epoch at which each was unlinked, and their bytes.
    retired: Vec<(Retired, u64, u64)>,
    retired_bytes: u64,
    /// The least recently used items as one scan of the slots found them, oldest first:
    /// (recency stamp then, tile or chunk, slot). See [`DemandCache::evict_oldest`].
    oldest: std::collections::VecDeque<(u64, bool, usize)>,
}

/// How many of the oldest items one scan of the slots keeps for the evictions that follow.
const OLDEST_PER_SCAN: usize = 64;

/// Counters of the cache's work.
#[derive(Default)]
pub struct CacheStats {
    pub hits: AtomicU64,
    pub misses: AtomicU64,
    pub evictions: AtomicU64,
    /// Most bytes held at once, resident and evicted-but-not-yet-freed together.
    pub peak_bytes: AtomicU64,
    /// Bytes read by DMA, whichever way they really travelled.
    pub bytes_dma: AtomicU64,
    /// Of `bytes_dma`, those read from a shared-memory segment rather than received.
    pub bytes_shared: AtomicU64,
    pub bytes_serial: AtomicU64,
    /// Chunks validated and walked where they lie in a card's shared memory.
    pub in_place: AtomicU64,
    /// Nanoseconds rendering threads spent waiting for fetches.
    pub wait_ns: AtomicU64,
}

/// Where misses go.
pub struct Source {
    pub fabric: Fabric,
    pub runtime: tokio::runtime::Handle,
    /// This card's fork node; while it is lost, [`Fabric::serving_fork`] names the one
    /// standing in.
    pub fork: NodeId,
    pub chunk_owner: Vec<NodeId>,
    pub tile_owner: Vec<NodeId>,
    pub via: Transfer,
    /// Cards' memories mapped on this machine, for DMA reads; `None` when the job wants
    /// every byte over TCP (or its reads are not DMA).
    pub shared: Option<Arc<crate::shared::SharedSegments>>,
}

/// A reader that holds no reference into the cache.
const IDLE: u64 = u64::MAX;

pub struct DemandCache {
    /// What a chunk must agree with before it is used.
    rules: ChunkRules,
    chunks: Vec<Slot<Chunk>>,
    tiles: Vec<Slot<Tile>>,
    /// Recency clock, advanced once per pixel by each reader.
    clock: AtomicU64,
    /// Reclamation epoch, advanced at every eviction.
    epoch: AtomicU64,
    /// The epoch each reader last announced ([`IDLE`] when it holds nothing).
    readers: Mutex<Vec<Arc<AtomicU64>>>,
    state: Mutex<State>,
    budget: u64,
    /// `None` in batch mode: everything is already here and nothing may be fetched.
    source: Option<Source>,
    /// Chunks once validated in place in a card's shared memory, by id. The bytes they
    /// point at never change (the segment is read-only, written before it was announced),
    /// so when the least-recently-used order evicts one and a ray needs it again, the
    /// check is not repeated: the slot gets this copy back (a few pointers; the chunk's
    /// bytes stay in the mapping). Eviction and the bytes counted as fetched are the
    /// paper's either way.
    validated_in_place: Mutex<Vec<Option<Chunk>>>,
    /// Where the walking forms of chunks in this node's own memory go, when the budget is
    /// large enough ([`crate::forms`]).
    forms: Option<FormArena>,
    pub stats: CacheStats,
}

const FETCH_TIMEOUT: Duration = Duration::from_secs(120);

impl DemandCache {
    /// A cache for a scene whose chunks follow `rules`, with `tiles` texture tiles.
    pub fn new(
        rules: ChunkRules,
        tiles: usize,
        budget: u64,
        source: Option<Source>,
    ) -> DemandCache {
        let chunks = rules.len();
        DemandCache {
            chunks: (0..chunks).map(|_| Slot::default()).collect(),
            rules,
            tiles: (0..tiles).map(|_| Slot::default()).collect(),
            clock: AtomicU64::new(1),
            epoch: AtomicU64::new(1),
            readers: Mutex::new(Vec::new()),
            state: Mutex::new(State::default()),
            budget,
            source,
            validated_in_place: Mutex::new(vec![None; chunks]),
            forms: (budget >= forms::MIN_BUDGET).then(FormArena::default),
            stats: CacheStats::default(),
        }
    }

    /// A handle for one rendering thread.
    pub fn reader(&self) -> Reader<'_> {
        let announced = Arc::new(AtomicU64::new(self.epoch.load(Ordering::SeqCst)));
        self.readers
            .lock()
            .expect("readers lock")
            .push(announced.clone());
        Reader {
            cache: self,
            announced,
            now: Cell::new(self.clock.load(Ordering::Relaxed)),
            hits: Cell::new(0),
            fetches: Cell::new(0),
            fetched_bytes: Cell::new(0),
            deferring: Cell::new(false),
        }
    }

    /// Puts data in without fetching (batch transfer), validated like fetched data.
    pub fn preload(&self, id: DataId, words: Box<[u32]>) -> Result<(), DataError> {
        match id {
            DataId::Chunk(c) => {
                let chunk = self.own_chunk(c, Fetched::Words(words))?;
                let bytes = chunk.memory_bytes() as u64;
                self.insert(&self.chunks, c, chunk, bytes, false)?;
            }
            DataId::Tile(t) => {
                let tile = Tile::from_words(words)?;
                let bytes = tile.as_bytes().len() as u64;
                self.insert(&self.tiles, t, tile, bytes, false)?;
            }
            DataId::Synthetic { .. } => {
                return Err(DataError::Corrupt("synthetic data in the cache".into()));
            }
        }
        Ok(())
    }

    /// How many cards' shared segments DMA reads use.
    pub fn shared_segments(&self) -> u32 {
        self.source
            .as_ref()
            .and_then(|s| s.shared.as_ref())
            .map_or(0, |s| s.count())
    }

    /// Whether the cache has had to evict: until then a miss is fetched at once even when
    /// deferring, since waiting saves no fetch (and a cache that holds the whole scene never
    /// makes a path wait).
    fn full(&self) -> bool {
        self.stats.evictions.load(Ordering::Relaxed) > 0
    }

    /// Bytes resident (not counting evicted items not yet freed).
    pub fn used_bytes(&self) -> u64 {
        self.state.lock().expect("cache lock").used
    }

    /// Puts an item in its slot, first evicting the least recently used until it fits (when
    /// `evict`). Returns the item now in the slot (another thread may have put it there first).
    fn insert<T: Retire>(
        &self,
        slots: &[Slot<T>],
        id: u32,
        item: T,
        bytes: u64,
        evict: bool,
    ) -> Result<*mut T, DataError> {
        let mut state = self.state.lock().expect("cache lock");
        let slot = slots.get(id as usize).ok_or_else(|| T::missing(id))?;
        let existing = slot.item.load(Ordering::Acquire);
        if !existing.is_null() {
            return Ok(existing);
        }
        if evict {
            while state.used + bytes > self.budget {
                if !self.evict_oldest(&mut state) {
                    break;
                }
            }
        }
        let p = Box::into_raw(Box::new(item));
        slot.bytes.store(bytes, Ordering::Relaxed);
        slot.last_use
            .store(self.clock.load(Ordering::Relaxed), Ordering::Relaxed);
        slot.item.store(p, Ordering::Release);
        state.used += bytes;
        self.stats
            .peak_bytes
            .fetch_max(state.used + state.retired_bytes, Ordering::Relaxed);
        self.reclaim(&mut state);
        Ok(p)
    }

    /// Unlinks the least recently used item and retires it; false if nothing is resident.
    ///
    /// A small cache evicts at nearly every fetch, and finding the oldest item is a scan of
    /// every slot, so one scan keeps the [`OLDEST_PER_SCAN`] oldest for the evictions after
    /// it. Stamps only grow (a use sets the current clock; an insertion, the clock then), so
    /// a kept item whose stamp is unchanged is still older than, or as old as, every item
    /// not kept; one used since is dropped from the list. Items last used in the same pixel
    /// are equally old and go in any order.
    fn evict_oldest(&self, state: &mut State) -> bool {
        let retired = loop {
            let Some((stamp, is_tile, slot)) = state.oldest.pop_front().or_else(|| {
                self.scan_oldest(state);
                state.oldest.pop_front()
            }) else {
                break None;
            };
            let unlinked = if is_tile {
                unlink_if_unchanged(&self.tiles[slot], stamp).map(|(p, b)| (Retired::Tile(p), b))
            } else {
                unlink_if_unchanged(&self.chunks[slot], stamp).map(|(p, b)| (Retired::Chunk(p), b))
            };
            if unlinked.is_some() {
                break unlinked;
            }
        };
        let Some((retired, bytes)) = retired else {
            return false;
        };
        // Readers that announced an epoch after this one cannot have seen the pointer.
        let unlinked_at = self.epoch.fetch_add(1, Ordering::SeqCst);
        state.used -= bytes;
        state.retired_bytes += bytes;
        state.retired.push((retired, unlinked_at, bytes));
        self.stats.evictions.fetch_add(1, Ordering::Relaxed);
        true
    }

    /// Fills `state.oldest` with the resident items of the smallest stamps, oldest first.
    fn scan_oldest(&self, state: &mut State) {
        fn resident<T>(
            slots: &[Slot<T>],
            is_tile: bool,
        ) -> impl Iterator<Item = (u64, bool, usize)> + '_ {
            slots
                .iter()
                .enumerate()
                .filter(|(_, s)| !s.item.load(Ordering::Relaxed).is_null())
                .map(move |(i, s)| (s.last_use.load(Ordering::Relaxed), is_tile, i))
        }
        let mut all: Vec<(u64, bool, usize)> = resident(&self.chunks, false)
            .chain(resident(&self.tiles, true))
            .collect();
        if all.len() > OLDEST_PER_SCAN {
            all.select_nth_unstable(OLDEST_PER_SCAN);
            all.truncate(OLDEST_PER_SCAN);
        }
        all.sort_unstable();
        state.oldest.clear();
        state.oldest.extend(all);
    }

    /// Frees retired items that no reader can hold any more.
    fn reclaim(&self, state: &mut State) {
        if state.retired.is_empty() {
            return;
        }
        let oldest_reader = self
            .readers
            .lock()
            .expect("readers lock")
            .iter()
            .map(|r| r.load(Ordering::SeqCst))
            .min()
            .unwrap_or(IDLE);
        let mut freed = 0;
        state.retired.retain_mut(|(item, unlinked_at, bytes)| {
            if *unlinked_at < oldest_reader {
                let item = std::mem::replace(item, Retired::Chunk(std::ptr::null_mut()));
                // SAFETY: every reader has announced an epoch after the unlink, so none
                // holds the item.
                unsafe { item.free() };
                freed += *bytes;
                false
            } else {
                true
            }
        });
        state.retired_bytes -= freed;
    }

    /// Fetches a missing item from the fork node (blocking this thread), validates it and
    /// inserts it; its validated bytes.
    fn fetch(&self, id: DataId) -> Result<Fetched, DataError> {
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
        if let Some(fetched) = self.read_shared(src, id, owner)? {
            self.stats
                .wait_ns
                .fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
            let bytes = fetched.word_count() as u64 * 4;
            self.stats.bytes_dma.fetch_add(bytes, Ordering::Relaxed);
            self.stats.bytes_shared.fetch_add(bytes, Ordering::Relaxed);
            return self.within_budget(id, fetched);
        }
        let request = Message::DataRequest {
            id,
            transfer: src.via,
            owner,
        };
        let reply = ask_fork(src, &request)?;
        self.stats
            .wait_ns
            .fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
        let bytes = reply.data.len() as u64 * 4;
        match src.via {
            Transfer::Dma => self.stats.bytes_dma.fetch_add(bytes, Ordering::Relaxed),
            Transfer::Serial => self.stats.bytes_serial.fetch_add(bytes, Ordering::Relaxed),
        };
        self.within_budget(id, Fetched::Words(reply.data))
    }

    /// Refuses an item that could never fit (the scene checks bound chunks, not senders).
    fn within_budget(&self, id: DataId, words: Fetched) -> Result<Fetched, DataError> {
        let bytes = words.word_count() as u64 * 4;
        if bytes > self.budget {
            return Err(DataError::Fetch(format!(
                "{id:?} is {bytes} bytes, more than the whole cache budget of {} bytes",
                self.budget
            )));
        }
        Ok(words)
    }

    /// `id` from the shared segment of `owner`'s card, if this node mapped it and it holds
    /// the item: the DMA read without a socket, nothing copied. When the links are delayed the
    /// fork node is still asked, for the transfer's model time only (an answer without
    /// data, delivered when the DMA transfer would complete), so the model charges the same.
    fn read_shared(
        &self,
        src: &Source,
        id: DataId,
        owner: NodeId,
    ) -> Result<Option<Fetched>, DataError> {
        let Some(segment) = src.shared.as_ref().and_then(|s| s.get(owner)) else {
            return Ok(None);
        };
        let Some(words) = segment.place(id, Part::Words) else {
            return Ok(None);
        };
        if src.fabric.model().links_delayed() {
            ask_fork(src, &Message::SharedRead { id, owner })?;
        }
        Ok(Some(Fetched::InPlace {
            walk: segment.place(id, Part::Walk),
            segment,
            words,
        }))
    }
}

/// How long a request that failed while its fork node is not (yet) known lost waits before
/// it is sent again: the host's word of the loss is on its way.
const RETRY_AFTER: Duration = Duration::from_millis(100);

/// Asks the fork node serving this node and waits for its answer. When that fork node is
/// lost meanwhile (the host declares it dead, which ends the request at once), the fork node
/// standing in for it is asked instead: the items are the same wherever they are held.
fn ask_fork(src: &Source, request: &Message) -> Result<protocol::Frame, DataError> {
    let me = src.fabric.me();
    let deadline = Instant::now() + FETCH_TIMEOUT;
    loop {
        let fork = src.fabric.serving_fork(me).unwrap_or(src.fork);
        let fabric = src.fabric.clone();
        let message = request.clone();
        let left = deadline.saturating_duration_since(Instant::now());
        let answer = src.runtime.block_on(async move {
            fabric
                .request(fork, &message, Box::new([]), Route::Mesh, left)
                .await
        });
        match answer {
            Ok(frame) => return Ok(frame),
            Err(e) if Instant::now() >= deadline => return Err(DataError::Fetch(e.to_string())),
            Err(e) => {
                if src.fabric.serving_fork(me) == Some(fork) {
                    tracing::debug!("render node {me}: asking fork node {fork} failed: {e}");
                    std::thread::sleep(RETRY_AFTER);
                }
            }
        }
    }
}

impl Drop for DemandCache {
    fn drop(&mut self) {
        let state = self.state.get_mut().expect("cache lock");
        for (item, _, _) in state.retired.drain(..) {
            // SAFETY: the cache is being dropped, so no reader exists.
            unsafe { item.free() };
        }
        for s in &self.chunks {
            let p = s.item.swap(std::ptr::null_mut(), Ordering::AcqRel);
            if !p.is_null() {
                // SAFETY: as above; the pointer came from Box::into_raw.
                unsafe { Retired::Chunk(p).free() };
            }
        }
        for s in &self.tiles {
            let p = s.item.swap(std::ptr::null_mut(), Ordering::AcqRel);
            if !p.is_null() {
                // SAFETY: as above.
                unsafe { Retired::Tile(p).free() };
            }
        }
    }
}

impl DemandCache {
    /// Chunk `id` in words of this node's own (received or preloaded), validated, its walking
    /// form moved into large pages where this cache places forms there (see
    /// [`crate::forms`]: a large budget, and more than a few forms held already) and has
    /// room.
    fn own_chunk(&self, id: u32, words: Fetched) -> Result<Chunk, DataError> {
        let mut chunk = validate_chunk(&self.rules, id, words)?;
        let Some(arena) = &self.forms else {
            return Ok(chunk);
        };
        if self.used_bytes() < forms::MIN_HELD {
            return Ok(chunk);
        }
        let form = chunk.accel();
        if let Some(place) = arena.place(form.words_len(), |out| form.write_words(out)) {
            // Written from a form that was walked already, so it reads back; were it
            // refused, the chunk would keep the form it has.
            let moved = chunk.walk_in(place);
            debug_assert!(
                moved.is_ok(),
                "a walking form copied into large pages: {moved:?}"
            );
        }
        Ok(chunk)
    }

    /// Bytes of large-page blocks alive and of the walking forms alive in them.
    pub fn large_page_bytes(&self) -> (usize, usize) {
        self.forms.as_ref().map_or((0, 0), FormArena::bytes)
    }

    /// Chunk `id` walked where it lies in a card's mapping: validated the first time only.
    fn in_place(&self, id: u32, fetched: Fetched) -> Result<Chunk, DataError> {
        self.stats.in_place.fetch_add(1, Ordering::Relaxed);
        let known = self
            .validated_in_place
            .lock()
            .expect("in-place lock")
            .get(id as usize)
            .cloned()
            .flatten();
        if let Some(chunk) = known {
            return Ok(chunk);
        }
        let chunk = validate_chunk(&self.rules, id, fetched)?;
        if let Some(entry) = self
            .validated_in_place
            .lock()
            .expect("in-place lock")
            .get_mut(id as usize)
        {
            *entry = Some(chunk.clone());
        }
        Ok(chunk)
    }
}

/// Takes an item out of its slot: its pointer and bytes, if it held one.
fn unlink<T>(slot: &Slot<T>) -> Option<(*mut T, u64)> {
    let p = slot.item.swap(std::ptr::null_mut(), Ordering::AcqRel);
    (!p.is_null()).then(|| (p, slot.bytes.swap(0, Ordering::Relaxed)))
}

/// Takes an item out of its slot if it is still there and unused since its recency stamp
/// read `stamp`.
fn unlink_if_unchanged<T>(slot: &Slot<T>, stamp: u64) -> Option<(*mut T, u64)> {
    let resident = !slot.item.load(Ordering::Relaxed).is_null();
    if resident && slot.last_use.load(Ordering::Relaxed) == stamp {
        unlink(slot)
    } else {
        None
    }
}

/// What differs between chunk and tile slots.
trait Retire: Sized {
    fn missing(id: u32) -> DataError;
}

impl Retire for Chunk {
    fn missing(id: u32) -> DataError {
        DataError::NoChunk(id)
    }
}

impl Retire for Tile {
    fn missing(id: u32) -> DataError {
        DataError::NoTile(id)
    }
}

fn validate_chunk(rules: &ChunkRules, id: u32, fetched: Fetched) -> Result<Chunk, DataError> {
    let (words, walk) = fetched.into_parts()?;
    let chunk = Chunk::from_region(words, walk)
        .map_err(|e| DataError::Corrupt(format!("chunk {id}: {e}")))?;
    rules
        .check(id, &chunk)
        .map_err(|e| DataError::Corrupt(e.to_string()))?;
    Ok(chunk)
}

/// One rendering thread's view of the cache: its [`SceneData`]. References it hands out
/// stay valid until [`Reader::refresh`], which needs the reader mutably, so none can outlive
/// it.
pub struct Reader<'c> {
    cache: &'c DemandCache,
    announced: Arc<AtomicU64>,
    /// This thread's recency stamp (the clock at its current pixel).
    now: Cell<u64>,
    /// Hits not yet added to the shared counter.
    hits: Cell<u64>,
    /// Misses this thread fetched, and their bytes, since [`Reader::take_fetched`].
    fetches: Cell<u32>,
    fetched_bytes: Cell<u64>,
    /// While set, a miss in a cache that has had to evict is answered with
    /// [`DataError::Missing`], and fetched only when the renderer asks ([`Deferral::bring`]).
    deferring: Cell<bool>,
}

impl Reader<'_> {
    /// Lets evicted items that this thread may have used be freed: call it where the
    /// thread holds no reference into the cache (between pixels, or batches of rays).
    pub fn refresh(&mut self) {
        self.announce();
    }

    /// Announces the current epoch: this reader holds nothing retired before it. Called
    /// only where no reference handed out by this reader is alive.
    fn announce(&self) {
        self.flush();
        self.announced
            .store(self.cache.epoch.load(Ordering::SeqCst), Ordering::SeqCst);
    }

    /// How many items this thread fetched, and their bytes, since it last asked.
    pub fn take_fetched(&self) -> (u32, u64) {
        (self.fetches.replace(0), self.fetched_bytes.replace(0))
    }

    /// Counts a miss this thread waited for (the miss path only; a hit is not slowed).
    fn fetched(&self, words: usize) {
        self.fetches.set(self.fetches.get() + 1);
        self.fetched_bytes
            .set(self.fetched_bytes.get() + words as u64 * 4);
    }

    /// Advances the recency clock: rendering threads call it once per pixel, so recency is
    /// known to the pixel and a hit needs no read-modify-write of a shared counter.
    pub fn tick(&self) {
        self.now
            .set(self.cache.clock.fetch_add(1, Ordering::Relaxed) + 1);
    }

    fn flush(&self) {
        let h = self.hits.replace(0);
        if h > 0 {
            self.cache.stats.hits.fetch_add(h, Ordering::Relaxed);
        }
    }

    #[inline(always)]
    fn hit<'a, T>(&self, slot: &'a Slot<T>, p: *mut T) -> &'a T {
        // A stamp written only when it changes keeps a shared line clean on most hits.
        let now = self.now.get();
        if slot.last_use.load(Ordering::Relaxed) != now {
            slot.last_use.store(now, Ordering::Relaxed);
        }
        self.hits.set(self.hits.get() + 1);
        // SAFETY: the pointer was loaded from the slot after this reader announced its
        // epoch; it is freed only once every reader has announced a later one, which this
        // reader does only through `refresh(&mut self)`, after every reference is gone.
        unsafe { &*p }
    }
}

impl Drop for Reader<'_> {
    fn drop(&mut self) {
        self.flush();
        self.announced.store(IDLE, Ordering::SeqCst);
    }
}

impl SceneData for Reader<'_> {
    type ChunkRef<'a>
        = &'a Chunk
    where
        Self: 'a;
    type TileRef<'a>
        = &'a Tile
    where
        Self: 'a;

    const MAY_DEFER: bool = true;

    #[inline(always)]
    fn chunk(&self, id: u32) -> Result<&Chunk, DataError> {
        let slot = self
            .cache
            .chunks
            .get(id as usize)
            .ok_or(DataError::NoChunk(id))?;
        let p = slot.item.load(Ordering::Acquire);
        if !p.is_null() {
            return Ok(self.hit(slot, p));
        }
        if self.defers() {
            return Err(DataError::Missing(Item::Chunk(id)));
        }
        self.fetch_chunk(id)
    }

    #[inline(always)]
    fn tile(&self, id: u32) -> Result<&Tile, DataError> {
        let slot = self
            .cache
            .tiles
            .get(id as usize)
            .ok_or(DataError::NoTile(id))?;
        let p = slot.item.load(Ordering::Acquire);
        if !p.is_null() {
            return Ok(self.hit(slot, p));
        }
        if self.defers() {
            return Err(DataError::Missing(Item::Tile(id)));
        }
        self.fetch_tile(id)
    }
}

impl Reader<'_> {
    /// Whether a miss is now answered with [`DataError::Missing`] instead of fetched.
    #[inline(always)]
    fn defers(&self) -> bool {
        self.deferring.get() && self.cache.full()
    }

    /// The miss path of a chunk: fetched (this thread waits), validated, inserted.
    #[inline(never)]
    fn fetch_chunk(&self, id: u32) -> Result<&Chunk, DataError> {
        let fetched = self.cache.fetch(DataId::Chunk(id))?;
        self.fetched(fetched.word_count());
        let chunk = match fetched {
            Fetched::InPlace { .. } => self.cache.in_place(id, fetched)?,
            Fetched::Words(_) => self.cache.own_chunk(id, fetched)?,
        };
        let bytes = chunk.memory_bytes() as u64;
        let p = self
            .cache
            .insert(&self.cache.chunks, id, chunk, bytes, true)?;
        // SAFETY: as in `hit`: loaded (inserted) after this reader announced its epoch.
        Ok(unsafe { &*p })
    }

    /// The miss path of a tile, as of a chunk.
    #[inline(never)]
    fn fetch_tile(&self, id: u32) -> Result<&Tile, DataError> {
        let fetched = self.cache.fetch(DataId::Tile(id))?;
        self.fetched(fetched.word_count());
        let tile = Tile::from_region(fetched.into_parts()?.0)?;
        let bytes = tile.as_bytes().len() as u64;
        let p = self
            .cache
            .insert(&self.cache.tiles, id, tile, bytes, true)?;
        // SAFETY: as in `hit`.
        Ok(unsafe { &*p })
    }
}

impl Deferral for Reader<'_> {
    fn defer(&self, on: bool) {
        self.deferring.set(on);
    }

    unsafe fn bring(&self, item: Item) -> Result<(), DataError> {
        // The caller holds nothing of the cache (the trait's contract), as between scan
        // lines: what was evicted may be freed.
        self.announce();
        let was = self.deferring.replace(false);
        let got = match item {
            Item::Chunk(id) => self.chunk(id).map(drop),
            Item::Tile(id) => self.tile(id).map(drop),
        };
        self.deferring.set(was);
        got
    }

    fn tick(&self) {
        Reader::tick(self);
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

    /// What a cache charges for one of the test chunks: its words and its walking form.
    fn memory_size() -> u64 {
        let c = validate_chunk(&rules(1), 0, Fetched::Words(chunk(0, 4))).unwrap();
        assert!(
            c.memory_bytes() > c.byte_len(),
            "the walking form is counted too"
        );
        c.memory_bytes() as u64
    }

    fn rules(chunks: usize) -> ChunkRules {
        ChunkRules::new(vec![(0, 4); chunks], 0)
    }

    fn glam_vec(x: f32, y: f32) -> glam::Vec3 {
        glam::Vec3::new(x, y, 0.0)
    }

    #[test]
    fn a_large_cache_walks_forms_in_large_pages_and_finds_the_same_hits() {
        use renderer::ray::{Ray, RayQuery};
        let tris = 2000;
        let own = Chunk::from_words(chunk(0, tris)).unwrap();
        let held = forms::MIN_HELD / own.memory_bytes() as u64 + 1;
        let rules = || ChunkRules::new(vec![(0, tris); held as usize + 1], 0);
        let small = DemandCache::new(rules(), 0, 1 << 20, None);
        let large = DemandCache::new(rules(), 0, forms::MIN_BUDGET, None);
        small.preload(DataId::Chunk(0), chunk(0, tris)).unwrap();
        for id in 0..=held as u32 {
            large.preload(DataId::Chunk(id), chunk(id, tris)).unwrap();
        }
        assert_eq!(
            small.large_page_bytes(),
            (0, 0),
            "a small cache keeps the heap"
        );
        // The forms of the first 8 MiB held stay in the heap; the next go to large pages.
        let (blocks, live) = large.large_page_bytes();
        let form = own.accel().words_len() * 4;
        assert!(live >= form && live.is_multiple_of(form) && blocks >= live);
        let reader = large.reader();
        assert!(!reader.chunk(0).unwrap().accel().nodes.is_shared());
        drop(reader);
        let (small_reader, large_reader) = (small.reader(), large.reader());
        let (in_heap, in_pages) = (
            small_reader.chunk(0).unwrap(),
            large_reader.chunk(held as u32).unwrap(),
        );
        assert!(!in_heap.accel().nodes.is_shared() && in_pages.accel().nodes.is_shared());
        assert_eq!(in_heap.memory_bytes(), in_pages.memory_bytes());
        for i in 0..2 * tris {
            let x = i as f32 * 0.5 + 0.25;
            let ray = Ray::new(
                glam::Vec3A::new(x, 0.2, 1.0),
                glam::Vec3A::new(0.01, 0.02, -1.0),
                f32::INFINITY,
            );
            let q = RayQuery::new(&ray);
            let hit = |c: &Chunk| {
                let mut t = f32::INFINITY;
                c.intersect(&q, &mut t).map(|(tri, h)| (tri, h.t.to_bits()))
            };
            let want = hit(&own);
            assert!(want.is_some() || i >= 2 * tris - 1, "ray {i} missed");
            assert_eq!(hit(in_heap), want, "ray {i}");
            assert_eq!(hit(in_pages), want, "ray {i}");
        }
    }

    #[test]
    fn a_deferring_reader_says_what_it_lacks_only_once_the_cache_has_evicted() {
        let size = memory_size();
        let cache = DemandCache::new(rules(3), 0, size * 2, None);
        cache.preload(DataId::Chunk(0), chunk(0, 4)).unwrap();
        cache.preload(DataId::Chunk(1), chunk(1, 4)).unwrap();
        let mut reader = cache.reader();
        reader.defer(true);
        // Nothing evicted yet: a miss is fetched at once (here: refused, having no source).
        assert!(matches!(reader.chunk(2), Err(DataError::Fetch(_))));
        reader.tick();
        assert!(reader.chunk(1).is_ok());
        let third = validate_chunk(&rules(3), 2, Fetched::Words(chunk(2, 4))).unwrap();
        reader.refresh();
        cache.insert(&cache.chunks, 2, third, size, true).unwrap();
        // Chunk 0 was evicted: now a miss is reported, not fetched.
        let misses = cache.stats.misses.load(Ordering::Relaxed);
        assert_eq!(
            reader.chunk(0).err(),
            Some(DataError::Missing(Item::Chunk(0)))
        );
        assert_eq!(cache.stats.misses.load(Ordering::Relaxed), misses);
        // Brought on request, and resident items are simply there.
        // SAFETY: no reference from the reader is alive.
        assert!(matches!(
            unsafe { reader.bring(Item::Chunk(0)) },
            Err(DataError::Fetch(_))
        ));
        assert_eq!(cache.stats.misses.load(Ordering::Relaxed), misses + 1);
        // SAFETY: as above.
        assert!(unsafe { reader.bring(Item::Chunk(2)) }.is_ok());
        assert!(reader.chunk(1).is_ok());
        reader.defer(false);
        assert!(matches!(reader.chunk(0), Err(DataError::Fetch(_))));
    }

    #[test]
    fn evicts_least_recently_used_within_budget() {
        let size = memory_size();
        let cache = DemandCache::new(rules(3), 0, size * 2, None);
        cache.preload(DataId::Chunk(0), chunk(0, 4)).unwrap();
        let mut reader = cache.reader();
        reader.tick();
        cache.preload(DataId::Chunk(1), chunk(1, 4)).unwrap();
        reader.tick();
        assert!(reader.chunk(0).is_ok());
        reader.tick();
        // A third, inserted with eviction, pushes out chunk 1 (used least recently).
        let third = validate_chunk(&rules(3), 2, Fetched::Words(chunk(2, 4))).unwrap();
        reader.refresh();
        cache.insert(&cache.chunks, 2, third, size, true).unwrap();
        assert!(cache.used_bytes() <= size * 2);
        assert!(reader.chunk(0).is_ok());
        assert!(reader.chunk(1).is_err(), "chunk 1 should have been evicted");
        assert_eq!(cache.stats.evictions.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn evictions_follow_use_across_the_oldest_kept_by_one_scan() {
        // More chunks than one scan keeps, so later evictions come from the kept list, and
        // a kept chunk used after the scan must not be the one to go.
        let n = OLDEST_PER_SCAN as u32 + 40;
        let size = memory_size();
        let cache = DemandCache::new(rules(n as usize + 20), 0, size * n as u64, None);
        let mut reader = cache.reader();
        let insert = |reader: &mut Reader, id: u32| {
            let c =
                validate_chunk(&rules(n as usize + 20), id, Fetched::Words(chunk(id, 4))).unwrap();
            reader.refresh();
            cache.insert(&cache.chunks, id, c, size, true).unwrap();
        };
        for id in 0..n {
            reader.tick();
            insert(&mut reader, id);
        }
        // A scan keeps chunks 0.. as the oldest; then chunk 1 is used again.
        reader.tick();
        insert(&mut reader, n);
        assert!(reader.chunk(0).is_err());
        reader.tick();
        assert!(reader.chunk(1).is_ok());
        for id in n + 1..n + 20 {
            reader.tick();
            insert(&mut reader, id);
        }
        // Twenty evictions in all: chunk 0, then 2..=20, never 1.
        assert!(reader.chunk(1).is_ok(), "chunk 1 was used after the scan");
        for id in 2..=20 {
            assert!(reader.chunk(id).is_err(), "chunk {id} should have gone");
        }
        assert!(reader.chunk(21).is_ok());
        assert_eq!(cache.stats.evictions.load(Ordering::Relaxed), 20);
    }

    #[test]
    fn an_evicted_chunk_lives_until_its_readers_move_on() {
        let size = memory_size();
        let cache = DemandCache::new(rules(2), 0, size, None);
        cache.preload(DataId::Chunk(0), chunk(0, 4)).unwrap();
        let mut reader = cache.reader();
        reader.refresh();
        let held: &Chunk = reader.chunk(0).unwrap();
        // Another thread's miss evicts chunk 0 while this reader holds it.
        std::thread::scope(|s| {
            s.spawn(|| {
                let c = validate_chunk(&rules(2), 1, Fetched::Words(chunk(1, 4))).unwrap();
                cache.insert(&cache.chunks, 1, c, size, true).unwrap();
            });
        });
        assert_eq!(cache.stats.evictions.load(Ordering::Relaxed), 1);
        assert_eq!(held.header().chunk_id, 0, "still readable");
        assert_eq!(cache.state.lock().unwrap().retired.len(), 1);
        reader.refresh();
        // The next eviction frees it: every reader has announced a later epoch.
        let c = validate_chunk(&rules(2), 0, Fetched::Words(chunk(0, 4))).unwrap();
        cache.insert(&cache.chunks, 0, c, size, true).unwrap();
        let state = cache.state.lock().unwrap();
        assert_eq!(state.retired.len(), 1, "only the newly evicted one waits");
        assert_eq!(cache.stats.evictions.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn wrong_or_corrupt_data_is_refused() {
        let rules = ChunkRules::new(vec![(0, 2); 6], 0);
        assert!(validate_chunk(&rules, 5, Fetched::Words(chunk(5, 2))).is_ok());
        assert!(validate_chunk(&rules, 5, Fetched::Words(chunk(4, 2))).is_err());
        // The right id, but not what the scene says chunk 5 is.
        assert!(validate_chunk(&rules, 5, Fetched::Words(chunk(5, 3))).is_err());
        let other = ChunkRules::new(vec![(1, 2); 6], 0);
        assert!(validate_chunk(&other, 5, Fetched::Words(chunk(5, 2))).is_err());
        let mut w = chunk(5, 2).to_vec();
        w.truncate(w.len() - 1);
        assert!(validate_chunk(&rules, 5, Fetched::Words(w.into_boxed_slice())).is_err());
        let cache = DemandCache::new(rules, 1, 1 << 20, None);
        assert!(
            cache
                .preload(DataId::Tile(0), vec![0u32; 7].into_boxed_slice())
                .is_err()
        );
    }
}
