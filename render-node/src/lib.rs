//! The render node role (the paper's NP): renders the subscreens the host hands it, fetching
//! the shape and texture data its rays need from its fork node into a bounded cache
//! ([`cache`]), on rendering threads of its own ([`worker`]), while this runtime relays other
//! nodes' packets through the mesh.

pub mod cache;
pub mod worker;

use std::{
    sync::{Arc, Mutex, atomic::Ordering},
    time::Duration,
};

use cache::{DemandCache, Source};
use fabric::{
    Delivery, Fabric, Route, Via,
    clock::now_ns,
    cluster::{ClusterError, JoinConfig, join},
};
use protocol::{
    ConnectionKind, DataId, Frame, JobSpec, Message, NodeId, NodeStats, Role, Transfer,
    TransferMode, decode_value, words_to_bytes,
};
use renderer::Scene;
use worker::{ActiveMap, WorkStats, Worker};

#[derive(Debug, thiserror::Error)]
pub enum RenderNodeError {
    #[error("joining the cluster: {0}")]
    Join(#[from] ClusterError),
    #[error("lost the connection to the host")]
    HostLost,
}

pub struct Config {
    pub join: JoinConfig,
}

/// What this node knows of the current render.
#[derive(Default)]
struct Render {
    scene: Option<Arc<Scene>>,
    chunk_owner: Vec<NodeId>,
    tile_owner: Vec<NodeId>,
    job: Option<Arc<JobSpec>>,
    /// Batch data received before rendering starts, and how much is coming.
    batch: Vec<(DataId, Box<[u32]>)>,
    batch_expected: Option<u32>,
    cache: Option<Arc<DemandCache>>,
    started: bool,
}

/// Runs a render node until the host says stop or goes away.
pub async fn run(config: Config) -> Result<(), RenderNodeError> {
    let joined = join(config.join).await?;
    let fabric = joined.fabric.clone();
    let mut inbox = joined.inbox;
    tracing::info!("render node {} ready", fabric.me());
    let mut render = Render::default();
    let active: ActiveMap = Arc::default();
    let stats = Arc::new(WorkStats::default());
    let threads: Arc<Mutex<Vec<std::thread::JoinHandle<()>>>> = Arc::default();
    let mut pending = joined.early;
    loop {
        let d = match pending.pop() {
            Some(d) => d,
            None => match inbox.recv().await {
                Some(d) => d,
                None => return Err(RenderNodeError::HostLost),
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
                match msg {
                    Message::Shutdown { reason } if via == Via::Control(0) => {
                        tracing::info!("render node {} stopping: {reason}", fabric.me());
                        fabric::cluster::leave(&fabric).await;
                        return Ok(());
                    }
                    Message::NodeDown { node } if via == Via::Control(0) => {
                        tracing::warn!(
                            "render node {}: node {node} is gone; routing around it",
                            fabric.me()
                        );
                        fabric.mark_dead(node);
                    }
                    Message::Header {
                        len,
                        chunk_owner,
                        tile_owner,
                    } => match decode_header(&frame, len, &chunk_owner, &tile_owner) {
                        Ok(scene) => {
                            render.scene = Some(Arc::new(scene));
                            render.chunk_owner = chunk_owner;
                            render.tile_owner = tile_owner;
                        }
                        Err(e) => fail(
                            &fabric,
                            &format!("scene header from node {}: {e}", frame.header.sender),
                        ),
                    },
                    Message::Job(job) => render.job = Some(Arc::new(*job)),
                    Message::Hold { id } => render.batch.push((id, frame.data)),
                    Message::HoldDone { count } => render.batch_expected = Some(count),
                    Message::GiveBack { subscreen } => {
                        let found = active.lock().expect("active lock").get(&subscreen).cloned();
                        let from_row = found.map_or(u32::MAX, |a| a.give_back());
                        let _ = fabric.send(
                            0,
                            &Message::Returned {
                                subscreen,
                                from_row,
                            },
                            Box::new([]),
                            0,
                        );
                    }
                    Message::StatsRequest => {
                        let s = node_stats(&fabric, &stats, render.cache.as_deref());
                        let _ = fabric.send_control(0, &Message::NodeStats(Box::new(s)));
                    }
                    Message::RunProbes {
                        to,
                        bytes,
                        count,
                        round_trip,
                    } => {
                        let f = fabric.clone();
                        tokio::spawn(
                            async move { run_probes(f, to, bytes, count, round_trip).await },
                        );
                    }
                    Message::RunTransfers {
                        transfer,
                        bytes,
                        count,
                        owner_card,
                        start_ns,
                    } => {
                        let f = fabric.clone();
                        tokio::spawn(async move {
                            run_transfers(f, transfer, bytes, count, owner_card, start_ns).await
                        });
                    }
                    other => {
                        tracing::debug!("render node {} ignores {}", fabric.me(), other.name())
                    }
                }
                maybe_start(&fabric, &mut render, &active, &stats, &threads);
            }
            Delivery::Lost {
                peer: 0,
                kind: ConnectionKind::Control,
                ..
            } => {
                tracing::error!("render node {}: lost the host; exiting", fabric.me());
                fabric.begin_shutdown();
                return Err(RenderNodeError::HostLost);
            }
            Delivery::Lost { peer, kind, reason } => tracing::warn!(
                "render node {}: lost {kind:?} connection to node {peer}: {reason}",
                fabric.me()
            ),
            Delivery::Incoming { .. } => {}
        }
    }
}

/// Why a scene header from the fork node cannot be used.
#[derive(Debug, thiserror::Error)]
enum HeaderError {
    #[error("shorter than it says")]
    Short,
    #[error(transparent)]
    Decode(#[from] protocol::DecodeError),
    #[error(transparent)]
    Invalid(#[from] renderer::scene::SceneError),
    #[error("the address table does not match the scene")]
    AddressTable,
}

fn decode_header(
    frame: &Frame,
    len: u64,
    chunk_owner: &[NodeId],
    tile_owner: &[NodeId],
) -> Result<Scene, HeaderError> {
    let bytes = words_to_bytes(&frame.data, len as usize).ok_or(HeaderError::Short)?;
    let scene: Scene = decode_value(bytes)?;
    scene.validate()?;
    if chunk_owner.len() != scene.chunks.len() || tile_owner.len() != scene.tile_count as usize {
        return Err(HeaderError::AddressTable);
    }
    Ok(scene)
}

fn fail(fabric: &Fabric, message: &str) {
    tracing::error!("render node {}: {message}", fabric.me());
    let _ = fabric.send_control(
        0,
        &Message::Failed {
            node: fabric.me(),
            message: message.to_string(),
        },
    );
}

/// Starts the rendering threads once the header, the job and (for a batch job) all the data
/// are here.
fn maybe_start(
    fabric: &Fabric,
    r: &mut Render,
    active: &ActiveMap,
    stats: &Arc<WorkStats>,
    threads: &Arc<Mutex<Vec<std::thread::JoinHandle<()>>>>,
) {
    if r.started {
        return;
    }
    let (Some(scene), Some(job)) = (r.scene.clone(), r.job.clone()) else {
        return;
    };
    let Some(fork) = fabric.topology().fork_of(fabric.me()) else {
        return;
    };
    let cache = match job.transfer {
        TransferMode::Demand => {
            let source = Source {
                fabric: fabric.clone(),
                runtime: tokio::runtime::Handle::current(),
                fork,
                chunk_owner: r.chunk_owner.clone(),
                tile_owner: r.tile_owner.clone(),
                via: job.demand_via,
            };
            let largest = scene
                .chunks
                .iter()
                .map(|c| c.byte_len as u64)
                .max()
                .unwrap_or(0);
            if largest > job.cache_bytes {
                r.started = true;
                fail(
                    fabric,
                    &format!(
                        "the cache budget of {} bytes is smaller than the largest chunk ({largest} bytes)",
                        job.cache_bytes
                    ),
                );
                return;
            }
            DemandCache::new(
                scene.chunk_rules(),
                scene.tile_count as usize,
                job.cache_bytes,
                Some(source),
            )
        }
        TransferMode::Batch => {
            if r.batch_expected != Some(r.batch.len() as u32) {
                return;
            }
            let cache = DemandCache::new(
                scene.chunk_rules(),
                scene.tile_count as usize,
                u64::MAX,
                None,
            );
            for (id, words) in r.batch.drain(..) {
                if let Err(e) = cache.preload(id, words) {
                    r.started = true;
                    fail(fabric, &format!("batch data {id:?}: {e}"));
                    return;
                }
            }
            cache
        }
    };
    r.started = true;
    let cache = Arc::new(cache);
    r.cache = Some(cache.clone());
    for t in 0..job.render_threads.max(1) {
        let worker = Worker {
            fabric: fabric.clone(),
            runtime: tokio::runtime::Handle::current(),
            scene: scene.clone(),
            job: job.clone(),
            cache: cache.clone(),
            fork,
            active: active.clone(),
            stats: stats.clone(),
        };
        let f = fabric.clone();
        let handle = std::thread::Builder::new()
            .name(format!("render-{t}"))
            .spawn(move || {
                if let Err(e) = worker.run() {
                    fail(&f, &e.to_string());
                }
            })
            .expect("spawn a rendering thread");
        threads.lock().expect("threads lock").push(handle);
    }
}

fn node_stats(fabric: &Fabric, w: &WorkStats, cache: Option<&DemandCache>) -> NodeStats {
    let c = fabric.counters();
    let wait = cache.map_or(0, |c| c.stats.wait_ns.load(Ordering::Relaxed));
    let render = w.render_ns.load(Ordering::Relaxed);
    let g = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    NodeStats {
        node: fabric.me(),
        role: Some(Role::Render),
        subscreens: w.subscreens.load(Ordering::Relaxed),
        rows: g(&w.rows),
        pixels: g(&w.pixels),
        samples: g(&w.samples),
        rays: g(&w.rays),
        camera_rays: g(&w.camera_rays),
        secondary_rays: g(&w.secondary_rays),
        shadow_rays: g(&w.shadow_rays),
        bad_samples: g(&w.bad_samples),
        cache_hits: cache.map_or(0, |c| g(&c.stats.hits)),
        cache_misses: cache.map_or(0, |c| g(&c.stats.misses)),
        cache_evictions: cache.map_or(0, |c| g(&c.stats.evictions)),
        cache_peak_bytes: cache.map_or(0, |c| g(&c.stats.peak_bytes)),
        bytes_fetched_dma: cache.map_or(0, |c| g(&c.stats.bytes_dma)),
        bytes_fetched_serial: cache.map_or(0, |c| g(&c.stats.bytes_serial)),
        frames_forwarded: c.frames_forwarded,
        frames_around_mesh: c.frames_around_mesh,
        bytes_forwarded: c.bytes_forwarded,
        busy_s: render.saturating_sub(wait) as f64 * 1e-9,
        waiting_s: wait as f64 * 1e-9,
        idle_s: g(&w.idle_ns) as f64 * 1e-9,
        peak_rss_bytes: fabric::peak_rss_bytes(),
        ..NodeStats::default()
    }
}

const TIMEOUT: Duration = Duration::from_secs(120);

/// Sends `count` probes of about `bytes` to `to`, one at a time, and reports their one-way
/// times (sender and receiver share CLOCK_MONOTONIC on one machine), or round trips.
async fn run_probes(f: Fabric, to: NodeId, bytes: u32, count: u32, round_trip: bool) {
    let mut samples = Vec::with_capacity(count as usize);
    for id in 0..count {
        let sent = now_ns();
        let probe = Message::Probe { id, sent_ns: sent };
        // Pad the frame to the requested size (the paper's figure is for 84-byte packets).
        let bare = Frame::new(f.me(), to, &probe, Box::new([])).wire_len();
        let pad = (bytes as usize).saturating_sub(bare).div_ceil(4);
        match f
            .request(
                to,
                &probe,
                vec![0u32; pad].into_boxed_slice(),
                Route::Mesh,
                TIMEOUT,
            )
            .await
        {
            Ok(reply) => {
                if let Ok(Message::ProbeEcho { received_ns, .. }) = reply.message() {
                    samples.push(if round_trip {
                        now_ns() - sent
                    } else {
                        received_ns.saturating_sub(sent)
                    });
                }
            }
            Err(e) => {
                tracing::warn!("probe {id} to node {to} failed: {e}");
                break;
            }
        }
    }
    let _ = f.send_control(
        0,
        &Message::Measured {
            node: f.me(),
            samples_ns: samples,
        },
    );
}

/// Measures `count` demand transfers of `bytes` from this card's fork node, the data held
/// by card `owner_card`, starting together with the other nodes at `start_ns`.
async fn run_transfers(
    f: Fabric,
    transfer: Transfer,
    bytes: u32,
    count: u32,
    owner_card: u16,
    start_ns: u64,
) {
    let t = f.topology();
    let (Some(fork), Some(owner)) = (t.fork_of(f.me()), t.fork_of_card(owner_card)) else {
        let _ = f.send_control(
            0,
            &Message::Measured {
                node: f.me(),
                samples_ns: Vec::new(),
            },
        );
        return;
    };
    f.timer().sleep_until(start_ns).await;
    let mut samples = Vec::with_capacity(count as usize);
    for _ in 0..count {
        let t0 = now_ns();
        let request = Message::DataRequest {
            id: DataId::Synthetic { bytes },
            transfer,
            owner,
        };
        match f
            .request(fork, &request, Box::new([]), Route::Mesh, TIMEOUT)
            .await
        {
            Ok(reply) if reply.data.len() * 4 >= bytes as usize => samples.push(now_ns() - t0),
            Ok(_) => tracing::warn!("short reply to a transfer of {bytes} bytes"),
            Err(e) => {
                tracing::warn!("transfer of {bytes} bytes failed: {e}");
                break;
            }
        }
    }
    let _ = f.send_control(
        0,
        &Message::Measured {
            node: f.me(),
            samples_ns: samples,
        },
    );
}
