//! The render node role (the paper's NP): renders the subscreens the host hands it, fetching
//! the shape and texture data its rays need from its fork node (or, once that one is lost,
//! the one [`fabric::Fabric::serving_fork`] names) into a bounded cache
//! ([`cache`]), on rendering threads of its own ([`worker`]), while this runtime relays other
//! nodes' packets through the mesh.
//!
//! The node's life (joining, stopping, losing the host) is [`fabric::role::run_role`]'s;
//! this crate adds what a render node does with its messages: collect the scene header, the
//! job and any batch data until rendering can start (`start`), map the cards' memories
//! their fork nodes publish on this machine (`shared`), give back unbegun rows when
//! the host asks, report its statistics, and run the host's measurements (`measure`).

pub mod cache;
pub mod forms;
mod measure;
pub mod shared;
mod start;
pub mod worker;

use std::sync::{Arc, atomic::Ordering};

use cache::DemandCache;
use fabric::{
    Fabric, Via,
    cluster::JoinConfig,
    node::CounterSnapshot,
    role::{RoleError, RoleHandler, run_role},
};
use protocol::{Frame, Message, NodeId, NodeStats, Role, decode_value, words_to_bytes};
use renderer::SceneHeader;
use start::Render;
use worker::{ActiveMap, WorkStats};

pub struct Config {
    pub join: JoinConfig,
}

/// Runs a render node until the host says stop or goes away.
pub async fn run(config: Config) -> Result<(), RoleError> {
    run_role(config.join, |fabric| RenderNode {
        fabric: fabric.clone(),
        render: Render::default(),
        active: ActiveMap::default(),
        stats: Arc::default(),
    })
    .await
}

/// A render node's state between messages. Only the node's runtime touches it; the
/// rendering threads share just the subscreens in progress and the work counters.
struct RenderNode {
    fabric: Fabric,
    render: Render,
    active: ActiveMap,
    stats: Arc<WorkStats>,
}

impl RoleHandler for RenderNode {
    const NAME: &'static str = "render node";

    fn on_message(&mut self, frame: Frame, message: Message, via: Via) {
        let fabric = &self.fabric;
        match message {
            Message::SharedSegment(s)
                if via == Via::Direct(fabric.serving_fork(fabric.me()).unwrap_or(0)) =>
            {
                let card = s.card;
                match self.render.segments.add(card, &s.name, s.nonce, s.bytes) {
                    Ok(()) => tracing::debug!(
                        "render node {}: reads card {card}'s memory through shared memory",
                        fabric.me()
                    ),
                    Err(e) => tracing::info!(
                        "render node {}: {e}; reads card {card}'s memory over TCP",
                        fabric.me()
                    ),
                }
            }
            Message::Header {
                len,
                chunk_owner,
                tile_owner,
            } => match decode_header(&frame.data, len, &chunk_owner, &tile_owner) {
                Ok(scene) => {
                    self.render.scene = Some(Arc::new(scene));
                    self.render.chunk_owner = chunk_owner;
                    self.render.tile_owner = tile_owner;
                }
                Err(e) => fail(
                    fabric,
                    &format!("scene header from node {}: {e}", frame.header.sender),
                ),
            },
            Message::Job(job) => self.render.job = Some(Arc::new(*job)),
            Message::Hold { id } => self.render.batch.push((id, frame.data)),
            Message::HoldDone { count } => self.render.batch_expected = Some(count),
            Message::GiveBack { subscreen } => {
                let found = self
                    .active
                    .lock()
                    .expect("active lock")
                    .get(&subscreen)
                    .cloned();
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
                let s = node_stats(
                    fabric.me(),
                    fabric.counters(),
                    &self.stats,
                    self.render.cache.as_deref(),
                );
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
                    async move { measure::run_probes(f, to, bytes, count, round_trip).await },
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
                    measure::run_transfers(f, transfer, bytes, count, owner_card, start_ns).await
                });
            }
            other => {
                tracing::debug!("render node {} ignores {}", fabric.me(), other.name())
            }
        }
        self.maybe_start();
    }
}

impl RenderNode {
    /// Starts the rendering threads once the header, the job and (for a batch job) all the
    /// data are here; a render that cannot start is reported to the host, once.
    fn maybe_start(&mut self) {
        let fabric = &self.fabric;
        let fork = fabric.topology().fork_of(fabric.me());
        let started = start::decide(&self.render, fork).and_then(|ready| match ready {
            Some(ready) => start::build_cache(fabric, &mut self.render, &ready)
                .map(|cache| Some((ready, Arc::new(cache)))),
            None => Ok(None),
        });
        match started {
            Ok(None) => {}
            Ok(Some((ready, cache))) => {
                self.render.started = true;
                self.render.cache = Some(cache.clone());
                start::spawn_workers(fabric, ready, cache, &self.active, &self.stats);
            }
            Err(e) => {
                self.render.started = true;
                fail(fabric, &e.to_string());
            }
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

/// The scene in a header's `data`, checked against the address table that came with it.
fn decode_header(
    data: &[u32],
    len: u64,
    chunk_owner: &[NodeId],
    tile_owner: &[NodeId],
) -> Result<SceneHeader, HeaderError> {
    let bytes = words_to_bytes(data, len as usize).ok_or(HeaderError::Short)?;
    let scene: SceneHeader = decode_value(bytes)?;
    scene.validate()?;
    if chunk_owner.len() != scene.chunks.len() || tile_owner.len() != scene.tile_count as usize {
        return Err(HeaderError::AddressTable);
    }
    Ok(scene)
}

/// Logs a failure and tells the host, which ends the render with this message.
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

/// This node's statistics for the host, from the fabric's counters, the rendering threads'
/// counters and the cache's (none before rendering starts).
fn node_stats(
    me: NodeId,
    c: CounterSnapshot,
    w: &WorkStats,
    cache: Option<&DemandCache>,
) -> NodeStats {
    let g = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let wait = cache.map_or(0, |c| g(&c.stats.wait_ns));
    let render = g(&w.render_ns);
    NodeStats {
        node: me,
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
        bytes_fetched_shared: cache.map_or(0, |c| g(&c.stats.bytes_shared)),
        shared_segments: cache.map_or(0, |c| c.shared_segments()),
        frames_forwarded: c.frames_forwarded,
        frames_around_mesh: c.frames_around_mesh,
        bytes_forwarded: c.bytes_forwarded,
        // Time spent waiting for data is inside the rendering time; it is told apart.
        busy_s: render.saturating_sub(wait) as f64 * 1e-9,
        waiting_s: wait as f64 * 1e-9,
        idle_s: w.idle.total().as_secs_f64(),
        peak_rss_bytes: fabric::peak_rss_bytes(),
        peak_private_bytes: g(&w.peak_private).max(fabric::private_rss_bytes()),
        chunks_in_place: cache.map_or(0, |c| g(&c.stats.in_place)),
        paths_deferred: g(&w.paths_deferred),
        deferred_fetches: g(&w.deferred_fetches),
        records: w.records.lock().expect("records lock").clone(),
        ..NodeStats::default()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicU64;

    use protocol::{bytes_to_words, encode_value};

    use super::*;

    fn demo() -> SceneHeader {
        let opts = renderer::PrepareOptions {
            chunk_triangles: 64,
        };
        renderer::prepare(renderer::demo::demo_scene(), &opts).0
    }

    fn header(scene: &SceneHeader) -> (Box<[u32]>, u64) {
        let bytes = encode_value(scene);
        (bytes_to_words(&bytes), bytes.len() as u64)
    }

    #[test]
    fn decode_header_accepts_a_scene_with_its_address_table() {
        let scene = demo();
        let (words, len) = header(&scene);
        let chunks = vec![1; scene.chunks.len()];
        let tiles = vec![1; scene.tile_count as usize];
        let decoded = decode_header(&words, len, &chunks, &tiles).unwrap();
        assert_eq!(decoded.chunks.len(), scene.chunks.len());
        assert_eq!(decoded.tile_count, scene.tile_count);
    }

    #[test]
    fn decode_header_refuses_a_header_shorter_than_it_says() {
        let (words, len) = header(&demo());
        let err = decode_header(&words, len + 4, &[], &[]).unwrap_err();
        assert!(matches!(err, HeaderError::Short), "{err}");
    }

    #[test]
    fn decode_header_refuses_bytes_that_are_not_a_scene() {
        let words = bytes_to_words(&[0xff; 16]);
        let err = decode_header(&words, 16, &[], &[]).unwrap_err();
        assert!(matches!(err, HeaderError::Decode(_)), "{err}");
    }

    #[test]
    fn decode_header_refuses_an_address_table_of_another_scene() {
        let scene = demo();
        let (words, len) = header(&scene);
        let tiles = vec![1; scene.tile_count as usize];
        let short = vec![1; scene.chunks.len() - 1];
        let err = decode_header(&words, len, &short, &tiles).unwrap_err();
        assert!(matches!(err, HeaderError::AddressTable), "{err}");
        let chunks = vec![1; scene.chunks.len()];
        let more_tiles = vec![1; scene.tile_count as usize + 1];
        let err = decode_header(&words, len, &chunks, &more_tiles).unwrap_err();
        assert!(matches!(err, HeaderError::AddressTable), "{err}");
    }

    #[test]
    fn node_stats_before_rendering_has_only_the_fabric_counters() {
        let counters = CounterSnapshot {
            frames_forwarded: 7,
            frames_around_mesh: 2,
            bytes_forwarded: 900,
            ..CounterSnapshot::default()
        };
        let s = node_stats(5, counters, &WorkStats::default(), None);
        assert_eq!(s.node, 5);
        assert_eq!(s.role, Some(Role::Render));
        assert_eq!(
            (s.frames_forwarded, s.frames_around_mesh, s.bytes_forwarded),
            (7, 2, 900)
        );
        assert_eq!((s.rows, s.cache_hits, s.bytes_fetched_dma), (0, 0, 0));
        assert_eq!((s.busy_s, s.waiting_s), (0.0, 0.0));
    }

    #[test]
    fn node_stats_counts_a_wait_for_work_still_going_on() {
        let work = WorkStats::default();
        let began = work.idle.begin();
        std::thread::sleep(std::time::Duration::from_millis(20));
        let open = node_stats(4, CounterSnapshot::default(), &work, None).idle_s;
        assert!(open >= 0.02, "{open}");
        work.idle.end(began);
        let ended = node_stats(4, CounterSnapshot::default(), &work, None).idle_s;
        assert!(ended >= open, "{ended} < {open}");
        std::thread::sleep(std::time::Duration::from_millis(5));
        let later = node_stats(4, CounterSnapshot::default(), &work, None).idle_s;
        assert_eq!(later, ended, "an ended wait no longer grows");
    }

    #[test]
    fn node_stats_counts_waiting_for_data_apart_from_rendering() {
        let work = WorkStats {
            rows: AtomicU64::new(12),
            render_ns: AtomicU64::new(3_000_000_000),
            idle: worker::IdleClock::with_ended(std::time::Duration::from_millis(500)),
            ..WorkStats::default()
        };
        let scene = demo();
        let cache = DemandCache::new(
            scene.chunk_rules(),
            scene.tile_count as usize,
            1 << 30,
            None,
        );
        cache.stats.wait_ns.store(1_000_000_000, Ordering::Relaxed);
        cache.stats.hits.store(40, Ordering::Relaxed);
        cache.stats.bytes_serial.store(4096, Ordering::Relaxed);
        let s = node_stats(3, CounterSnapshot::default(), &work, Some(&cache));
        assert_eq!(s.rows, 12);
        assert_eq!((s.cache_hits, s.bytes_fetched_serial), (40, 4096));
        assert!((s.busy_s - 2.0).abs() < 1e-9, "{}", s.busy_s);
        assert!((s.waiting_s - 1.0).abs() < 1e-9, "{}", s.waiting_s);
        assert!((s.idle_s - 0.5).abs() < 1e-9, "{}", s.idle_s);
    }
}
