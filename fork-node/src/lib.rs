//! The fork node role (the paper's FP): one per card.
//!
//! The first fork node (the paper's FP (0,-1)) receives the scene from the host, prepares it
//! (chunks, both BVH levels, lights, texture tiles), places the chunks and tiles across all
//! fork nodes' shared memories and sends every fork node the header and address table. Each
//! fork node then gives the render nodes of its card the scene minus shape and texture data,
//! by DMA; serves their demand requests by serial link or DMA, reading other cards' memories
//! over the G-bus; and writes the pixel rows they send into the host's frame buffer. The
//! first fork node also arbitrates the two G-buses for everyone.

mod memory;

use std::{
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    time::Duration,
};

use fabric::{
    Delivery, Fabric, Route, Via,
    clock::now_ns,
    cluster::{ClusterError, JoinConfig, join},
    model::Buses,
};
use memory::SharedMemory;
use protocol::{
    ConnectionKind, DataId, Frame, JobSpec, Message, NodeId, NodeStats, Role, Transfer,
    TransferMode, bytes_to_words, decode_value, encode_value, words_to_bytes,
};
use renderer::{PrepareOptions, Scene, SceneDesc};

#[derive(Debug, thiserror::Error)]
pub enum ForkError {
    #[error("joining the cluster: {0}")]
    Join(#[from] ClusterError),
    #[error("lost the connection to the host")]
    HostLost,
}

pub struct Config {
    pub join: JoinConfig,
}

#[derive(Default)]
struct SceneAssembly {
    parts: Vec<Option<Vec<u8>>>,
    total: u64,
    chunk_triangles: u32,
}

struct State {
    fabric: Fabric,
    /// The G-buses, modelled here when this is the first fork node.
    buses: Mutex<Buses>,
    /// When this card's DMA bus is next free (model time).
    dma_free_at: Mutex<u64>,
    memory: Mutex<SharedMemory>,
    job: Mutex<Option<JobSpec>>,
    assembly: Mutex<SceneAssembly>,
    header_sent: AtomicBool,
    batch_started: AtomicBool,
    bytes_served: AtomicU64,
    bytes_gbus: AtomicU64,
}

const REQUEST_TIMEOUT: Duration = Duration::from_secs(120);

/// Runs a fork node until the host says stop or goes away.
pub async fn run(config: Config) -> Result<(), ForkError> {
    let joined = join(config.join).await?;
    let fabric = joined.fabric.clone();
    let mut inbox = joined.inbox;
    let state = Arc::new(State {
        buses: Mutex::new(Buses::new(fabric.model().params.gbus_count)),
        dma_free_at: Mutex::new(0),
        memory: Mutex::new(SharedMemory::default()),
        job: Mutex::new(None),
        assembly: Mutex::new(SceneAssembly::default()),
        header_sent: AtomicBool::new(false),
        batch_started: AtomicBool::new(false),
        bytes_served: AtomicU64::new(0),
        bytes_gbus: AtomicU64::new(0),
        fabric: fabric.clone(),
    });
    tracing::info!("fork node {} ready", fabric.me());
    let mut pending = joined.early;
    loop {
        let d = match pending.pop() {
            Some(d) => d,
            None => match inbox.recv().await {
                Some(d) => d,
                None => return Err(ForkError::HostLost),
            },
        };
        match d {
            Delivery::Frame { frame, via } => {
                let msg = match frame.message() {
                    Ok(m) => m,
                    Err(e) => {
                        tracing::warn!("undecodable frame from node {}: {e}", frame.header.sender);
                        continue;
                    }
                };
                if fabric::diag::handle(&fabric, &frame, &msg) {
                    continue;
                }
                match (&msg, via) {
                    (Message::Shutdown { reason }, Via::Control(0)) => {
                        tracing::info!("fork node {} stopping: {reason}", fabric.me());
                        fabric::cluster::leave(&fabric).await;
                        return Ok(());
                    }
                    (Message::NodeDown { node }, Via::Control(0)) => {
                        tracing::warn!(
                            "fork node {}: node {node} is gone; routing around it",
                            fabric.me()
                        );
                        fabric.mark_dead(*node);
                        continue;
                    }
                    _ => {}
                }
                state.clone().handle(frame, msg, via);
            }
            Delivery::Lost {
                peer: 0,
                kind: ConnectionKind::Control,
                ..
            } => {
                tracing::error!("fork node {}: lost the host; exiting", fabric.me());
                fabric.begin_shutdown();
                return Err(ForkError::HostLost);
            }
            Delivery::Lost { peer, kind, reason } => tracing::warn!(
                "fork node {}: lost {kind:?} connection to node {peer}: {reason}",
                fabric.me()
            ),
            Delivery::Incoming { .. } => {}
        }
    }
}

impl State {
    fn handle(self: Arc<State>, frame: Frame, msg: Message, via: Via) {
        let f = self.fabric.clone();
        match msg {
            Message::ScenePart {
                part,
                parts,
                total,
                len,
                chunk_triangles,
            } if via == Via::Direct(0) => {
                self.on_scene_part(frame, part, parts, total, len, chunk_triangles)
            }
            Message::Header {
                len,
                chunk_owner,
                tile_owner,
            } => {
                let Some(bytes) = words_to_bytes(&frame.data, len as usize) else {
                    tracing::warn!("short scene header from node {}", frame.header.sender);
                    return;
                };
                self.on_header(bytes.to_vec(), chunk_owner, tile_owner);
            }
            Message::Hold { id } => self.on_hold(id, frame.data),
            Message::HoldDone { count } => {
                self.memory.lock().expect("memory lock").expected = Some(count);
                self.maybe_ready();
            }
            Message::Job(job) => {
                *self.job.lock().expect("job lock") = Some(*job);
                self.maybe_ready();
            }
            Message::DataRequest {
                id,
                transfer,
                owner,
            } => {
                tokio::spawn(async move { self.serve_request(frame, id, transfer, owner).await });
            }
            Message::RemoteRead { id, .. } => {
                let data = self.read_local(id);
                let _ = f.reply(
                    &frame,
                    &Message::RemoteData { id, done_ns: 0 },
                    data,
                    Route::Direct,
                    0,
                );
            }
            Message::BusRequest { bytes, ready_ns } => {
                let done_ns = self.book_bus(bytes as u64, ready_ns);
                let _ = f.reply(
                    &frame,
                    &Message::BusGrant { done_ns },
                    Box::new([]),
                    Route::Direct,
                    0,
                );
            }
            Message::Pixels { .. } => {
                // Into the frame buffer, which the host holds, over the G-bus.
                let _ = f.send_direct(0, &msg, frame.data, 0, 0);
            }
            Message::StatsRequest => {
                let c = f.counters();
                let stats = NodeStats {
                    node: f.me(),
                    role: Some(Role::Fork),
                    bytes_served: self.bytes_served.load(Ordering::Relaxed),
                    bytes_gbus: self.bytes_gbus.load(Ordering::Relaxed),
                    frames_forwarded: c.frames_forwarded,
                    frames_around_mesh: c.frames_around_mesh,
                    bytes_forwarded: c.bytes_forwarded,
                    peak_rss_bytes: fabric::peak_rss_bytes(),
                    ..NodeStats::default()
                };
                let _ = f.send_control(0, &Message::NodeStats(Box::new(stats)));
            }
            other => tracing::debug!("fork node {} ignores {}", f.me(), other.name()),
        }
    }

    /// The first fork node collects the scene from the host, then prepares and places it.
    fn on_scene_part(
        self: Arc<State>,
        frame: Frame,
        part: u32,
        parts: u32,
        total: u64,
        len: u32,
        chunk_triangles: u32,
    ) {
        let complete = {
            let mut a = self.assembly.lock().expect("assembly lock");
            if a.parts.len() != parts as usize {
                *a = SceneAssembly {
                    parts: vec![None; parts as usize],
                    total,
                    chunk_triangles,
                };
            }
            let Some(bytes) = words_to_bytes(&frame.data, len as usize) else {
                return;
            };
            if let Some(slot) = a.parts.get_mut(part as usize) {
                *slot = Some(bytes.to_vec());
            }
            a.parts.iter().all(Option::is_some)
        };
        if !complete {
            return;
        }
        let assembly = std::mem::take(&mut *self.assembly.lock().expect("assembly lock"));
        tokio::spawn(async move {
            let prepared = tokio::task::spawn_blocking(move || prepare_scene(assembly)).await;
            let failure = match prepared {
                Ok(Ok((scene, data))) => return self.place(scene, data).await,
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
    async fn place(self: Arc<State>, scene: Scene, data: renderer::MemoryData) {
        let f = &self.fabric;
        let forks = f.topology().fork_nodes();
        let chunk_owner: Vec<NodeId> = (0..data.chunks.len())
            .map(|i| forks[i % forks.len()])
            .collect();
        let tile_owner: Vec<NodeId> = (0..data.tiles.len())
            .map(|i| forks[i % forks.len()])
            .collect();
        let header = encode_value(&scene);
        let header_msg = Message::Header {
            len: header.len() as u64,
            chunk_owner: chunk_owner.clone(),
            tile_owner: tile_owner.clone(),
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
        for &fork in &forks {
            let mut count = 0u32;
            let owned = |i: usize, owners: &[NodeId]| owners[i] == fork;
            if fork == f.me() {
                self.on_header(header.clone(), chunk_owner.clone(), tile_owner.clone());
                for (i, c) in data
                    .chunks
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| owned(*i, &chunk_owner))
                {
                    self.store(DataId::Chunk(i as u32), c.words().into());
                    count += 1;
                }
                for (i, t) in data
                    .tiles
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| owned(*i, &tile_owner))
                {
                    self.store(DataId::Tile(i as u32), t.texels.as_ref().into());
                    count += 1;
                }
                self.memory.lock().expect("memory lock").expected = Some(count);
                self.maybe_ready();
                continue;
            }
            let _ = f.send_direct(fork, &header_msg, header_words.clone(), 0, 0);
            for (i, c) in data
                .chunks
                .iter()
                .enumerate()
                .filter(|(i, _)| owned(*i, &chunk_owner))
            {
                let _ = f.send_direct(
                    fork,
                    &Message::Hold {
                        id: DataId::Chunk(i as u32),
                    },
                    c.words().into(),
                    0,
                    0,
                );
                count += 1;
            }
            for (i, t) in data
                .tiles
                .iter()
                .enumerate()
                .filter(|(i, _)| owned(*i, &tile_owner))
            {
                let _ = f.send_direct(
                    fork,
                    &Message::Hold {
                        id: DataId::Tile(i as u32),
                    },
                    t.texels.clone(),
                    0,
                    0,
                );
                count += 1;
            }
            let _ = f.send_direct(fork, &Message::HoldDone { count }, Box::new([]), 0, 0);
        }
    }

    fn on_header(
        self: &Arc<State>,
        bytes: Vec<u8>,
        chunk_owner: Vec<NodeId>,
        tile_owner: Vec<NodeId>,
    ) {
        let scene: Scene = match decode_value(&bytes) {
            Ok(s) => s,
            Err(e) => {
                tracing::error!(
                    "fork node {}: undecodable scene header: {e}",
                    self.fabric.me()
                );
                return;
            }
        };
        if let Err(e) = scene.validate() {
            tracing::error!("fork node {}: {e}", self.fabric.me());
            return;
        }
        if chunk_owner.len() != scene.chunks.len() || tile_owner.len() != scene.tile_count as usize
        {
            tracing::error!(
                "fork node {}: the address table does not match the scene",
                self.fabric.me()
            );
            return;
        }
        {
            let mut m = self.memory.lock().expect("memory lock");
            m.scene = Some(Arc::new(scene));
            m.header_bytes = Some(Arc::new(bytes));
            m.chunk_owner = chunk_owner;
            m.tile_owner = tile_owner;
        }
        self.maybe_ready();
    }

    fn on_hold(self: &Arc<State>, id: DataId, words: Box<[u32]>) {
        let valid = match id {
            DataId::Chunk(_) => renderer::chunk::Chunk::from_words(words.clone()).is_ok(),
            DataId::Tile(_) => words.len() == renderer::texture::TILE_TEXELS,
            DataId::Synthetic { .. } => false,
        };
        if !valid {
            tracing::error!(
                "fork node {}: received {id:?} is not valid data; ignored",
                self.fabric.me()
            );
            return;
        }
        self.store(id, words.into());
        self.maybe_ready();
    }

    fn store(&self, id: DataId, words: Arc<[u32]>) {
        let mut m = self.memory.lock().expect("memory lock");
        if m.data.insert(id, words).is_none() {
            m.received += 1;
        }
    }

    /// Once this card's memory is complete: give the card's render nodes the header (by
    /// DMA), and, for a batch job, everything else too.
    fn maybe_ready(self: &Arc<State>) {
        let (complete, header, table) = {
            let m = self.memory.lock().expect("memory lock");
            (
                m.complete(),
                m.header_bytes.clone(),
                (m.chunk_owner.clone(), m.tile_owner.clone()),
            )
        };
        if !complete {
            return;
        }
        let Some(header) = header else { return };
        let f = &self.fabric;
        let card: Vec<NodeId> = f
            .topology()
            .render_nodes()
            .into_iter()
            .filter(|&r| f.topology().fork_of(r) == Some(f.me()))
            .collect();
        if !self.header_sent.swap(true, Ordering::SeqCst) {
            let msg = Message::Header {
                len: header.len() as u64,
                chunk_owner: table.0,
                tile_owner: table.1,
            };
            let words = bytes_to_words(&header);
            for &r in &card {
                let ready = self.dma_time(words.len() as u64 * 4, now_ns());
                let _ = f.send_direct(r, &msg, words.clone(), 0, ready);
            }
        }
        let batch = matches!(self.job.lock().expect("job lock").as_ref(), Some(j) if j.transfer == TransferMode::Batch);
        if batch && !self.batch_started.swap(true, Ordering::SeqCst) {
            let me = self.clone();
            tokio::spawn(async move { me.send_batch(card).await });
        }
    }

    /// Batch transfer: every render node of the card gets every chunk and tile.
    async fn send_batch(self: Arc<State>, card: Vec<NodeId>) {
        let ids = self.memory.lock().expect("memory lock").all_ids();
        let f = &self.fabric;
        for id in &ids {
            let (data, ready) = match self.get(*id).await {
                Some(x) => x,
                None => return,
            };
            for &r in &card {
                let t = self.dma_time(data.len() as u64 * 4, ready);
                let _ = f.send_direct(
                    r,
                    &Message::Hold { id: *id },
                    data.to_vec().into_boxed_slice(),
                    0,
                    t,
                );
                self.bytes_served
                    .fetch_add(data.len() as u64 * 4, Ordering::Relaxed);
            }
        }
        for &r in &card {
            let _ = f.send_direct(
                r,
                &Message::HoldDone {
                    count: ids.len() as u32,
                },
                Box::new([]),
                0,
                0,
            );
        }
    }

    /// An item from this card's memory, or over the G-bus from the card that holds it, with
    /// the model time it is ready here.
    async fn get(&self, id: DataId) -> Option<(Arc<[u32]>, u64)> {
        let now = now_ns();
        if let Some(d) = self.memory.lock().expect("memory lock").data.get(&id) {
            return Some((d.clone(), now));
        }
        let owner = self.memory.lock().expect("memory lock").owner(id)?;
        self.fetch_remote(id, owner, now)
            .await
            .map(|(d, t)| (Arc::from(d), t))
    }

    /// Data this card's shared memory holds.
    fn read_local(&self, id: DataId) -> Box<[u32]> {
        match id {
            DataId::Synthetic { bytes } => {
                vec![0u32; (bytes as usize).div_ceil(4)].into_boxed_slice()
            }
            _ => self
                .memory
                .lock()
                .expect("memory lock")
                .data
                .get(&id)
                .map(|d| d.to_vec().into_boxed_slice())
                .unwrap_or_default(),
        }
    }

    fn book_bus(&self, bytes: u64, ready_ns: u64) -> u64 {
        let duration = self.fabric.model().gbus_ns(bytes);
        self.buses
            .lock()
            .expect("bus lock")
            .book(ready_ns, duration)
    }

    fn dma_time(&self, bytes: u64, ready: u64) -> u64 {
        if !self.fabric.model().links_delayed() {
            return 0;
        }
        let mut free = self.dma_free_at.lock().expect("dma lock");
        let done = (*free).max(ready) + self.fabric.model().dma_ns(bytes);
        *free = done;
        done
    }

    /// Fetches `id` from the fork node `owner` over the G-bus: the data from the owner, the
    /// bus time from the arbiter (the first fork node), both asked at once.
    async fn fetch_remote(
        &self,
        id: DataId,
        owner: NodeId,
        ready_ns: u64,
    ) -> Option<(Box<[u32]>, u64)> {
        let f = &self.fabric;
        let master = f.topology().master_fork();
        let read = Message::RemoteRead { id, ready_ns };
        let data = f.request(owner, &read, Box::new([]), Route::Direct, REQUEST_TIMEOUT);
        let bytes = match id {
            DataId::Synthetic { bytes } => bytes,
            DataId::Chunk(c) => self
                .memory
                .lock()
                .expect("memory lock")
                .scene
                .as_ref()
                .and_then(|s| s.chunks.get(c as usize))
                .map_or(0, |c| c.byte_len),
            DataId::Tile(_) => (renderer::texture::TILE_TEXELS * 4) as u32,
        };
        let (data, done) = if master == f.me() {
            (data.await, self.book_bus(bytes as u64, ready_ns))
        } else {
            let ask = Message::BusRequest { bytes, ready_ns };
            let grant = f.request(master, &ask, Box::new([]), Route::Direct, REQUEST_TIMEOUT);
            let (d, g) = tokio::join!(data, grant);
            let done = match g.ok().and_then(|g| g.message().ok()) {
                Some(Message::BusGrant { done_ns }) => done_ns,
                _ => ready_ns,
            };
            (d, done)
        };
        match data {
            Ok(frame) => {
                self.bytes_gbus
                    .fetch_add(frame.data.len() as u64 * 4, Ordering::Relaxed);
                Some((frame.data, done))
            }
            Err(e) => {
                tracing::warn!(
                    "fork node {}: G-bus read of {id:?} from node {owner} failed: {e}",
                    f.me()
                );
                None
            }
        }
    }

    /// Answers a render node's demand request, by DMA or through the mesh.
    async fn serve_request(&self, request: Frame, id: DataId, transfer: Transfer, owner: NodeId) {
        let f = &self.fabric;
        let ready = now_ns();
        // Our own address table decides where data lives, when we have one.
        let owner = self
            .memory
            .lock()
            .expect("memory lock")
            .owner(id)
            .unwrap_or(owner);
        let (data, ready) = if owner == f.me() {
            (self.read_local(id), ready)
        } else {
            match self.fetch_remote(id, owner, ready).await {
                Some(x) => x,
                None => return,
            }
        };
        let bytes = data.len() as u64 * 4;
        self.bytes_served.fetch_add(bytes, Ordering::Relaxed);
        let result = match transfer {
            Transfer::Dma => {
                let done = self.dma_time(bytes, ready);
                f.reply(
                    &request,
                    &Message::DataReply { id },
                    data,
                    Route::Direct,
                    done,
                )
            }
            Transfer::Serial => f.reply(
                &request,
                &Message::DataReply { id },
                data,
                Route::Mesh,
                ready,
            ),
        };
        if let Err(e) = result {
            tracing::warn!(
                "fork node {}: cannot answer node {}: {e}",
                f.me(),
                request.header.sender
            );
        }
    }
}

/// Decodes the assembled scene description and prepares it.
/// Why the scene the host sent cannot be prepared.
#[derive(Debug, thiserror::Error)]
enum PrepareError {
    #[error("scene parts hold {got} bytes, expected {expected}")]
    Size { got: u64, expected: u64 },
    #[error("the scene description does not decode: {0}")]
    Decode(#[from] protocol::DecodeError),
    #[error("the scene description is invalid: {0}")]
    Invalid(#[from] renderer::scene::SceneError),
}

fn prepare_scene(a: SceneAssembly) -> Result<(Scene, renderer::MemoryData), PrepareError> {
    let mut bytes = Vec::with_capacity(a.total as usize);
    for p in a.parts.into_iter().flatten() {
        bytes.extend_from_slice(&p);
    }
    if bytes.len() as u64 != a.total {
        return Err(PrepareError::Size {
            got: bytes.len() as u64,
            expected: a.total,
        });
    }
    let desc: SceneDesc = decode_value(&bytes)?;
    desc.validate()?;
    let opts = PrepareOptions {
        chunk_triangles: (a.chunk_triangles as usize).max(1),
    };
    Ok(renderer::prepare(desc, &opts))
}
