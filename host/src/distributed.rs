//! Rendering on the cluster: the host's part of the paper's section 1.3.2.
//!
//! The host reads the scene and sends it to the first fork node, which prepares and places
//! it and returns the header. The host then fixes the camera and settings exactly as an
//! in-process render would, sends every node the job, and hands out subscreens as render
//! nodes ask (the paper's simple dynamic load balancing). With `adaptive`, once no
//! subscreen is left, an idle node's request makes the host ask the busiest node to give back
//! the unbegun half of its subscreen (the paper's announced adaptive redivision). Pixel rows
//! reach the host's frame buffer through the fork nodes; when every pixel is in, the host
//! writes the image, collects every node's statistics and stops the cluster.

use std::{
    collections::{HashMap, VecDeque},
    sync::atomic::{AtomicBool, Ordering},
    time::{Duration, Instant},
};

use fabric::{Delivery, Via};
use protocol::{
    Frame, JobSpec, Message, NodeId, NodeStats, Rect, Role, Transfer, TransferMode, bytes_to_words,
    decode_value, encode_value, words_to_bytes,
};
use renderer::{Image, Scene};
use serde::Serialize;

use crate::{
    cluster::{Cluster, ClusterConfig, start},
    inprocess::{RenderConfig, RenderError, check_settings},
    progress::Progress,
    stats::RenderStats,
};

#[derive(Clone, Debug)]
pub struct ClusterRenderConfig {
    pub render: RenderConfig,
    pub cluster: ClusterConfig,
    pub transfer: TransferMode,
    pub demand_via: Transfer,
    /// Cache budget per render node, as a percentage of the scene's chunk and tile bytes.
    pub cache_percent: f64,
    pub subscreens: Option<u32>,
    pub adaptive: bool,
    pub render_threads: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum ClusterRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Start(#[from] crate::cluster::StartError),
    #[error("{0}")]
    Failed(String),
    #[error("interrupted")]
    Interrupted,
}

/// The `--stats` report of a cluster render: the in-process fields plus every node's.
#[derive(Clone, Debug, Serialize)]
pub struct ClusterStats {
    #[serde(flatten)]
    pub render: RenderStats,
    pub topology: String,
    pub processes: usize,
    pub transfer: String,
    pub cache_percent: f64,
    pub cache_bytes: u64,
    pub subscreens: u32,
    pub subscreens_split: u32,
    pub adaptive: bool,
    pub link_model: String,
    pub time_scale: f64,
    pub totals: NodeStats,
    pub host_peak_rss_bytes: u64,
    pub cluster_peak_rss_bytes: u64,
    pub nodes: Vec<NodeStats>,
    /// Who took part: node id, role, address, process id, machine.
    pub members: Vec<fabric::cluster::Member>,
    /// Render nodes lost during the render, whose work others took over.
    pub lost_nodes: Vec<LostNode>,
}

/// A node the host lost during a render.
#[derive(Clone, Debug, Serialize)]
pub struct LostNode {
    pub node: NodeId,
    pub role: String,
    pub advertise: String,
    pub pid: u32,
    pub hostname: String,
    /// How the host noticed (the connection's end, or its silence).
    pub reason: String,
    /// Seconds since the host started the render.
    pub after_s: f64,
    /// Subscreens it held with rows still missing, handed to other nodes.
    pub subscreens_reassigned: u32,
}

impl LostNode {
    /// Who it was, as the log, the error and the summary name it: "render node 6 at ADDR
    /// (pid P on HOST)".
    pub fn who(&self) -> String {
        format!(
            "{} {} at {} (pid {} on {})",
            self.role, self.node, self.advertise, self.pid, self.hostname
        )
    }
}

/// Cuts the image into about `n` rectangles of similar shape, row by row.
pub fn subscreens(width: u32, height: u32, n: u32) -> Vec<Rect> {
    let n = n.max(1) as f64;
    let nx = ((n * width as f64 / height as f64).sqrt().round() as u32).clamp(1, width);
    let ny = ((n / nx as f64).round() as u32).clamp(1, height);
    let mut out = Vec::new();
    for j in 0..ny {
        let (y0, y1) = (j * height / ny, (j + 1) * height / ny);
        for i in 0..nx {
            let (x0, x1) = (i * width / nx, (i + 1) * width / nx);
            if x1 > x0 && y1 > y0 {
                out.push(Rect {
                    x: x0,
                    y: y0,
                    width: x1 - x0,
                    height: y1 - y0,
                });
            }
        }
    }
    out
}

struct Sub {
    rect: Rect,
    node: Option<NodeId>,
    /// Whether pixels of it have arrived since it was last handed out.
    pixels_seen: bool,
    giving_back: bool,
    /// When its node said it had sent every row.
    finished_at: Option<Instant>,
}

impl Sub {
    fn new(rect: Rect) -> Sub {
        Sub {
            rect,
            node: None,
            pixels_seen: false,
            giving_back: false,
            finished_at: None,
        }
    }
}

/// After a node is lost, rows of a finished subscreen that have not arrived this long after
/// its node finished it are taken as lost on the way (in the dead node) and rendered again.
const LOST_ROWS_GRACE: Duration = Duration::from_secs(2);

/// The frame buffer and which pixels have arrived.
struct FrameBuffer {
    image: Image,
    have: Vec<bool>,
    missing: u64,
}

impl FrameBuffer {
    fn put(&mut self, x: u32, y: u32, width: u32, data: &[u32]) -> u64 {
        let w = self.image.width;
        if y >= self.image.height || x >= w || width > w - x || data.len() != width as usize * 3 {
            return 0;
        }
        let px: &[[f32; 3]] = bytemuck::cast_slice(data);
        let mut new = 0;
        for (i, p) in px.iter().enumerate() {
            let at = (y * w + x + i as u32) as usize;
            if !self.have[at] {
                self.have[at] = true;
                self.image.pixels[at] = *p;
                new += 1;
            }
        }
        self.missing -= new;
        new
    }

    fn row_missing(&self, r: Rect, y: u32) -> bool {
        (r.x..r.x + r.width).any(|x| !self.have[(y * self.image.width + x) as usize])
    }

    fn rows_missing(&self, r: Rect) -> u32 {
        (r.y..r.y + r.height)
            .filter(|&y| self.row_missing(r, y))
            .count() as u32
    }

    /// The runs of rows of `r` that still miss pixels, as rectangles.
    fn missing_runs(&self, r: Rect) -> Vec<Rect> {
        let mut runs = Vec::new();
        let mut start = None;
        for y in r.y..=r.y + r.height {
            let missing = y < r.y + r.height && self.row_missing(r, y);
            match (missing, start) {
                (true, None) => start = Some(y),
                (false, Some(y0)) => {
                    runs.push(Rect {
                        x: r.x,
                        y: y0,
                        width: r.width,
                        height: y - y0,
                    });
                    start = None;
                }
                _ => {}
            }
        }
        runs
    }
}

/// Renders on a cluster; returns the statistics written to `--stats`.
pub async fn render_on_cluster(
    config: &ClusterRenderConfig,
    cancel: &AtomicBool,
) -> Result<ClusterStats, ClusterRenderError> {
    let rc = &config.render;
    check_settings(rc)?;
    let t0 = Instant::now();

    // The host reads the scene from disk.
    let (desc, warnings) =
        crate::scene_source::read_scene(&rc.scene, rc.environment).map_err(RenderError::Load)?;
    for w in &warnings {
        tracing::warn!("{}: {w}", rc.scene);
    }
    let t = config.cluster.topology.clone();
    tracing::info!("starting {}", t.summary());
    let mut cluster = start(&config.cluster, &|_, _| {}).await?;
    let result = drive(config, &mut cluster, desc, cancel, t0).await;
    let clean = cluster
        .shutdown(if result.is_ok() {
            "render done"
        } else {
            "render failed"
        })
        .await;
    if !clean {
        tracing::warn!("some nodes did not exit when told; they were killed");
    }
    result
}

/// The next delivery, or `None` after `TICK` without one (so that timed duties run even
/// when nothing arrives).
async fn next(
    cluster: &mut Cluster,
    cancel: &AtomicBool,
) -> Result<Option<Delivery>, ClusterRenderError> {
    if cancel.load(Ordering::Relaxed) {
        return Err(ClusterRenderError::Interrupted);
    }
    match tokio::time::timeout(TICK, cluster.formed.inbox.recv()).await {
        Ok(Some(d @ Delivery::Incoming { .. })) => {
            fabric::cluster::refuse_late_joiner(
                d,
                format!(
                    "the cluster {} is full and rendering; start this node before the next render",
                    cluster.formed.fabric.topology().name
                ),
            );
            Ok(None)
        }
        Ok(Some(d)) => Ok(Some(d)),
        Ok(None) => Err(ClusterRenderError::Failed(
            "the host's fabric stopped".into(),
        )),
        Err(_) => Ok(None),
    }
}

const TICK: Duration = Duration::from_millis(100);

/// What the host knows of lost nodes.
struct Faults {
    started: Instant,
    lost: Vec<LostNode>,
}

impl Faults {
    /// A connection to `peer` ended. A lost fork node ends the render (its share of the scene
    /// is gone); a lost render node is declared dead to everyone, who route around it. Returns
    /// whether a render node was newly lost.
    fn on_lost(
        &mut self,
        cluster: &Cluster,
        peer: NodeId,
        reason: &str,
    ) -> Result<bool, ClusterRenderError> {
        let f = &cluster.formed.fabric;
        let topo = f.topology();
        if peer == 0 || peer as usize >= topo.len() || !f.is_alive(peer) {
            return Ok(false);
        }
        let member = cluster.formed.members.iter().find(|m| m.node == peer);
        let (advertise, pid, hostname) = member.map_or((String::new(), 0, String::new()), |m| {
            (m.advertise.clone(), m.pid, m.hostname.clone())
        });
        let role = topo.role(peer);
        let lost = LostNode {
            node: peer,
            role: role.to_string(),
            advertise,
            pid,
            hostname,
            reason: reason.to_string(),
            after_s: self.started.elapsed().as_secs_f64(),
            subscreens_reassigned: 0,
        };
        if role != Role::Render {
            return Err(ClusterRenderError::Failed(format!(
                "lost {}: {reason}; the render cannot go on without its share of the scene, so the cluster is stopped and no image is written",
                lost.who()
            )));
        }
        tracing::warn!(
            "lost {}: {reason}; its unfinished subscreens go to other nodes, and routes go around it",
            lost.who()
        );
        f.mark_dead(peer);
        for m in &cluster.formed.members {
            if m.node != peer && f.is_alive(m.node) {
                let _ = f.send_control(m.node, &Message::NodeDown { node: peer });
            }
        }
        self.lost.push(lost);
        if !topo.render_nodes().into_iter().any(|n| f.is_alive(n)) {
            return Err(ClusterRenderError::Failed(
                "every render node is lost; no image is written".into(),
            ));
        }
        Ok(true)
    }
}

async fn drive(
    config: &ClusterRenderConfig,
    cluster: &mut Cluster,
    desc: renderer::SceneDesc,
    cancel: &AtomicBool,
    t0: Instant,
) -> Result<ClusterStats, ClusterRenderError> {
    let rc = &config.render;
    let f = cluster.formed.fabric.clone();
    let topo = f.topology().clone();
    let master = topo.master_fork();
    let mut faults = Faults {
        started: t0,
        lost: Vec::new(),
    };

    // The scene to the first fork node, in parts that fit a frame.
    let bytes = encode_value(&desc);
    drop(desc);
    const PART: usize = 16 << 20;
    let parts = bytes.len().div_ceil(PART).max(1) as u32;
    for (i, part) in bytes.chunks(PART).enumerate() {
        let msg = Message::ScenePart {
            part: i as u32,
            parts,
            total: bytes.len() as u64,
            len: part.len() as u32,
            chunk_triangles: rc.prepare.chunk_triangles as u32,
        };
        f.send_direct(master, &msg, bytes_to_words(part), 0, 0)
            .map_err(|e| ClusterRenderError::Failed(e.to_string()))?;
    }
    drop(bytes);

    // The prepared header comes back.
    let scene: Scene = loop {
        let Some(delivery) = next(cluster, cancel).await? else {
            continue;
        };
        match delivery {
            Delivery::Frame {
                frame,
                via: Via::Direct(_),
            } => match frame.message() {
                Ok(Message::Header { len, .. }) => {
                    let b = words_to_bytes(&frame.data, len as usize)
                        .ok_or_else(|| ClusterRenderError::Failed("short scene header".into()))?;
                    let s: Scene = decode_value(b)
                        .map_err(|e| ClusterRenderError::Failed(format!("scene header: {e}")))?;
                    s.validate()
                        .map_err(|e| ClusterRenderError::Failed(e.to_string()))?;
                    break s;
                }
                _ => continue,
            },
            Delivery::Frame {
                frame,
                via: Via::Control(_),
            } => {
                if let Ok(Message::Failed { node, message }) = frame.message() {
                    return Err(ClusterRenderError::Failed(format!(
                        "node {node}: {message}"
                    )));
                }
            }
            Delivery::Lost { peer, reason, .. } => {
                faults.on_lost(cluster, peer, &reason)?;
            }
            _ => {}
        }
    };
    let load_s = t0.elapsed().as_secs_f64();

    // Camera and settings exactly as in one process.
    let mut settings = rc.settings.clone();
    let aspect = settings.width as f32 / settings.height as f32;
    let camera = scene
        .camera(rc.camera.as_deref(), aspect)
        .map_err(|e| RenderError::Settings(e.to_string()))?;
    if !rc.height_given
        && let Some(a) = camera.aspect_ratio
    {
        settings.height = ((settings.width as f32 / a).round() as u32).clamp(1, 32768);
    }
    let data_bytes =
        scene.shape_bytes + scene.tile_count as u64 * renderer::texture::TILE_TEXELS as u64 * 4;
    let cache_bytes = (config.cache_percent / 100.0 * data_bytes as f64).ceil() as u64;
    let largest = scene
        .chunks
        .iter()
        .map(|c| c.byte_len as u64)
        .max()
        .unwrap_or(0);
    if config.transfer == TransferMode::Demand && cache_bytes < largest {
        return Err(ClusterRenderError::Failed(format!(
            "a cache of {}% ({cache_bytes} bytes) cannot hold the largest chunk ({largest} bytes); use a larger --cache",
            config.cache_percent
        )));
    }
    let render_nodes = topo.render_nodes();
    let rects = subscreens(
        settings.width,
        settings.height,
        config.subscreens.unwrap_or(8 * render_nodes.len() as u32),
    );
    tracing::info!(
        "{}: {} triangles in {} chunks; {}x{} at {} spp ({}), {} subscreens on {} render nodes, {:?} transfer, cache {cache_bytes} bytes",
        rc.scene,
        scene.triangle_count(),
        scene.chunks.len(),
        settings.width,
        settings.height,
        settings.spp,
        settings.integrator,
        rects.len(),
        render_nodes.len(),
        config.transfer
    );
    let job = JobSpec {
        settings: settings.clone(),
        camera,
        transfer: config.transfer,
        demand_via: config.demand_via,
        cache_bytes,
        render_threads: config.render_threads,
    };
    for n in 1..topo.len() as NodeId {
        if f.is_alive(n) {
            f.send_control(n, &Message::Job(Box::new(job.clone())))
                .map_err(|e| ClusterRenderError::Failed(e.to_string()))?;
        }
    }

    // Hand out subscreens and collect pixels.
    let t1 = Instant::now();
    let total = settings.width as u64 * settings.height as u64;
    let progress = Progress::new(total, rc.progress);
    let mut fb = FrameBuffer {
        image: Image::new(settings.width, settings.height),
        have: vec![false; total as usize],
        missing: total,
    };
    let mut subs: Vec<Sub> = rects.iter().map(|&rect| Sub::new(rect)).collect();
    let mut work = Work {
        queue: (0..subs.len() as u32).collect(),
        parked: VecDeque::new(),
        answered: HashMap::new(),
    };
    let mut split = 0u32;
    let original = subs.len() as u32;
    let mut last_sweep = Instant::now();
    let (mut last_missing, mut last_progress) = (fb.missing, Instant::now());
    while fb.missing > 0 {
        // `None`: nothing arrived for a tick; only the timed duties after the match run.
        match next(cluster, cancel).await? {
            Some(Delivery::Frame { frame, via }) => {
                let Ok(msg) = frame.message() else { continue };
                let sender = frame.header.sender;
                // A lost node's late words change nothing (its pixels still count).
                if !f.is_alive(sender) && !matches!(msg, Message::Pixels { .. }) {
                    continue;
                }
                match msg {
                    Message::SubscreenRequest { finished } => {
                        let key = (sender, frame.header.tag);
                        if let Some(answer) = work.answered.get(&key) {
                            // Sent again after a node was lost: the answer may have been too.
                            let _ = f.reply(&frame, answer, Box::new([]), fabric::Route::Mesh, 0);
                            continue;
                        }
                        if work
                            .parked
                            .iter()
                            .any(|p| (p.header.sender, p.header.tag) == key)
                        {
                            continue;
                        }
                        if let Some(s) = finished.and_then(|id| subs.get_mut(id as usize))
                            && s.node == Some(sender)
                        {
                            s.finished_at = Some(Instant::now());
                            s.giving_back = false;
                        }
                        work.parked.push_back(frame);
                        work.hand_out(&f, &mut subs);
                        if config.adaptive && !work.parked.is_empty() {
                            ask_give_back(&f, &mut subs, &fb);
                        }
                    }
                    Message::Returned {
                        subscreen,
                        from_row,
                    } => {
                        let Some(s) = subs.get_mut(subscreen as usize) else {
                            continue;
                        };
                        if s.node != Some(sender) {
                            continue;
                        }
                        s.giving_back = false;
                        if from_row < s.rect.height {
                            let r = s.rect;
                            s.rect.height = from_row;
                            subs.push(Sub::new(Rect {
                                x: r.x,
                                y: r.y + from_row,
                                width: r.width,
                                height: r.height - from_row,
                            }));
                            split += 1;
                            work.queue.push_back(subs.len() as u32 - 1);
                        }
                        work.hand_out(&f, &mut subs);
                        if !work.parked.is_empty() {
                            ask_give_back(&f, &mut subs, &fb);
                        }
                    }
                    Message::Pixels {
                        subscreen,
                        x,
                        y,
                        width,
                    } if matches!(via, Via::Direct(_)) && fb.put(x, y, width, &frame.data) > 0 => {
                        progress.update(total - fb.missing, total);
                        if let Some(s) = subs.get_mut(subscreen as usize)
                            && !s.pixels_seen
                        {
                            s.pixels_seen = true;
                            if let Some(node) = s.node {
                                event_first_pixels(node, subscreen);
                            }
                        }
                    }
                    Message::Failed { node, message } => {
                        return Err(ClusterRenderError::Failed(format!(
                            "node {node}: {message}"
                        )));
                    }
                    _ => {}
                }
            }
            Some(Delivery::Lost { peer, reason, .. }) => {
                if faults.on_lost(cluster, peer, &reason)? {
                    work.parked.retain(|p| p.header.sender != peer);
                    let mut reassigned = 0;
                    for id in 0..subs.len() {
                        if subs[id].node == Some(peer) && fb.rows_missing(subs[id].rect) > 0 {
                            reassigned += 1;
                            requeue_missing(&mut subs, id, &fb, &mut work.queue);
                        }
                    }
                    if let Some(l) = faults.lost.iter_mut().find(|l| l.node == peer) {
                        l.subscreens_reassigned = reassigned;
                    }
                }
                work.hand_out(&f, &mut subs);
            }
            _ => {}
        }
        if fb.missing != last_missing {
            last_missing = fb.missing;
            last_progress = Instant::now();
        } else if last_progress.elapsed() > STALL_REPORT {
            last_progress = Instant::now();
            let busy: Vec<String> = subs
                .iter()
                .enumerate()
                .filter(|(_, s)| fb.rows_missing(s.rect) > 0)
                .map(|(i, s)| match (s.node, s.finished_at) {
                    (Some(n), None) => format!("{i}@{n}"),
                    (Some(n), Some(_)) => format!("{i}@{n}(finished)"),
                    (None, _) => format!("{i}(queued)"),
                })
                .collect();
            let waiting: Vec<NodeId> = work.parked.iter().map(|p| p.header.sender).collect();
            tracing::info!(
                "no pixels for {:?}: {} missing; subscreens not done: {}; nodes waiting for work: {waiting:?}",
                STALL_REPORT,
                fb.missing,
                busy.join(" ")
            );
        }
        // Once a node was lost, rows may have been lost with it on their way to the frame
        // buffer (or a give-back with its answer): finished subscreens still missing rows
        // are rendered again.
        if !faults.lost.is_empty() && last_sweep.elapsed() > Duration::from_millis(250) {
            last_sweep = Instant::now();
            for id in 0..subs.len() {
                let s = &subs[id];
                if s.finished_at.is_some_and(|t| t.elapsed() > LOST_ROWS_GRACE)
                    && fb.rows_missing(s.rect) > 0
                {
                    tracing::info!("rows of subscreen {id} never arrived; rendering them again");
                    requeue_missing(&mut subs, id, &fb, &mut work.queue);
                }
            }
            work.hand_out(&f, &mut subs);
        }
    }
    progress.finish();
    let render_s = t1.elapsed().as_secs_f64();
    // Everyone still asking gets told there is nothing more.
    for req in work.parked.drain(..) {
        let _ = f.reply(
            &req,
            &Message::NoMoreWork,
            Box::new([]),
            fabric::Route::Mesh,
            0,
        );
    }
    drain_requests(cluster, &f).await;

    let t2 = Instant::now();
    scene_io::write_image(&rc.output, &fb.image).map_err(RenderError::Output)?;
    let write_s = t2.elapsed().as_secs_f64();

    // Every live node's statistics.
    let mut alive: Vec<NodeId> = (1..topo.len() as NodeId)
        .filter(|&n| f.is_alive(n))
        .collect();
    for &n in &alive {
        let _ = f.send_control(n, &Message::StatsRequest);
    }
    let mut nodes: HashMap<NodeId, NodeStats> = HashMap::new();
    let until = Instant::now() + Duration::from_secs(10);
    while nodes.len() < alive.len() && Instant::now() < until {
        match tokio::time::timeout(Duration::from_millis(200), cluster.formed.inbox.recv()).await {
            Ok(Some(Delivery::Frame { frame, .. })) => match frame.message() {
                Ok(Message::NodeStats(s)) => {
                    nodes.insert(s.node, *s);
                }
                Ok(Message::SubscreenRequest { .. }) => {
                    let _ = f.reply(
                        &frame,
                        &Message::NoMoreWork,
                        Box::new([]),
                        fabric::Route::Mesh,
                        0,
                    );
                }
                _ => {}
            },
            // A node lost now cannot answer; the image is already written.
            Ok(Some(Delivery::Lost { peer, reason, .. })) if alive.contains(&peer) => {
                tracing::warn!(
                    "lost node {peer} after the render: {reason}; its figures are missing"
                );
                alive.retain(|&n| n != peer);
            }
            Ok(None) => break,
            _ => {}
        }
    }
    let mut nodes: Vec<NodeStats> = nodes.into_values().collect();
    nodes.sort_by_key(|n| n.node);
    let mut totals = NodeStats::default();
    for n in &nodes {
        totals.subscreens += n.subscreens;
        totals.rows += n.rows;
        totals.pixels += n.pixels;
        totals.samples += n.samples;
        totals.rays += n.rays;
        totals.camera_rays += n.camera_rays;
        totals.secondary_rays += n.secondary_rays;
        totals.shadow_rays += n.shadow_rays;
        totals.bad_samples += n.bad_samples;
        totals.cache_peak_bytes += n.cache_peak_bytes;
        totals.cache_hits += n.cache_hits;
        totals.cache_misses += n.cache_misses;
        totals.cache_evictions += n.cache_evictions;
        totals.bytes_fetched_dma += n.bytes_fetched_dma;
        totals.bytes_fetched_serial += n.bytes_fetched_serial;
        totals.bytes_served += n.bytes_served;
        totals.bytes_gbus += n.bytes_gbus;
        totals.frames_forwarded += n.frames_forwarded;
        totals.frames_around_mesh += n.frames_around_mesh;
        totals.bytes_forwarded += n.bytes_forwarded;
        totals.busy_s += n.busy_s;
        totals.waiting_s += n.waiting_s;
        totals.idle_s += n.idle_s;
        totals.peak_rss_bytes += n.peak_rss_bytes;
    }
    let host_rss = fabric::peak_rss_bytes();
    let mut render = RenderStats {
        scene: rc.scene.to_string(),
        output: rc.output.display().to_string(),
        mode: "cluster".into(),
        width: settings.width,
        height: settings.height,
        spp: settings.spp,
        seed: settings.seed,
        integrator: settings.integrator.to_string(),
        threads: config.render_threads as usize * render_nodes.len(),
        triangles: scene.triangle_count(),
        chunks: scene.chunks.len(),
        shape_bytes: scene.shape_bytes,
        texture_tiles: scene.tile_count,
        ..Default::default()
    };
    render.seconds.load = load_s;
    render.seconds.render = render_s;
    render.seconds.write = write_s;
    render.seconds.total = t0.elapsed().as_secs_f64();
    render.samples = totals.samples;
    render.bad_samples = totals.bad_samples;
    render.peak_rss_bytes = host_rss;
    render.rays = crate::stats::Rays {
        camera: totals.camera_rays,
        secondary: totals.secondary_rays,
        shadow: totals.shadow_rays,
        total: totals.rays,
    };
    if totals.bad_samples > 0 {
        tracing::warn!(
            "{} samples were NaN or infinite and counted as black",
            totals.bad_samples
        );
    }
    if render_s > 0.0 {
        render.samples_per_second = totals.samples as f64 / render_s;
        render.rays_per_second = totals.rays as f64 / render_s;
    }
    let stats = ClusterStats {
        render,
        topology: topo.name.clone(),
        processes: topo.len(),
        transfer: format!("{:?}", config.transfer),
        cache_percent: config.cache_percent,
        cache_bytes,
        subscreens: original,
        subscreens_split: split,
        adaptive: config.adaptive,
        link_model: format!("{:?}", topo.model.link),
        time_scale: topo.model.time_scale,
        cluster_peak_rss_bytes: totals.peak_rss_bytes + host_rss,
        host_peak_rss_bytes: host_rss,
        totals,
        nodes,
        members: cluster.formed.members.clone(),
        lost_nodes: faults.lost,
    };
    if let Some(p) = &rc.stats {
        let json = serde_json::to_vec_pretty(&stats).unwrap_or_default();
        scene_io::image_io::write_atomic(p, &json).map_err(RenderError::Output)?;
    }
    Ok(stats)
}

/// The log target of machine-readable events (`MAGG_EVENT ...` lines at debug level), which
/// tests and scripts wait for instead of guessing with sleeps: `--log info,magg::event=debug`.
pub const EVENT_TARGET: &str = "magg::event";

/// A node's first pixels of a subscreen reached the frame buffer: it is rendering.
fn event_first_pixels(node: NodeId, subscreen: u32) {
    tracing::debug!(target: EVENT_TARGET, "MAGG_EVENT pixels node={node} subscreen={subscreen}");
}

/// Subscreens waiting for a node, and nodes waiting for a subscreen.
/// How long the render may go without a pixel before the host says what it waits for.
const STALL_REPORT: Duration = Duration::from_secs(10);

struct Work {
    queue: VecDeque<u32>,
    /// Requests for work not answered yet.
    parked: VecDeque<Frame>,
    /// Answers given, by (node, request tag), to repeat if the request comes again.
    answered: HashMap<(NodeId, u32), Message>,
}

impl Work {
    /// Pairs waiting requests with waiting subscreens.
    fn hand_out(&mut self, f: &fabric::Fabric, subs: &mut [Sub]) {
        while !self.queue.is_empty() {
            let Some(request) = self.parked.pop_front() else {
                break;
            };
            let id = self.queue.pop_front().expect("not empty");
            let s = &mut subs[id as usize];
            s.node = Some(request.header.sender);
            s.pixels_seen = false;
            s.finished_at = None;
            s.giving_back = false;
            let answer = Message::Subscreen { id, rect: s.rect };
            let _ = f.reply(&request, &answer, Box::new([]), fabric::Route::Mesh, 0);
            self.answered
                .insert((request.header.sender, request.header.tag), answer);
        }
    }
}

/// Puts the rows of subscreen `id` that still miss pixels back in the queue, first in line:
/// the first run of them under the same id, any further runs as new subscreens.
fn requeue_missing(subs: &mut Vec<Sub>, id: usize, fb: &FrameBuffer, queue: &mut VecDeque<u32>) {
    let runs = fb.missing_runs(subs[id].rect);
    let Some((first, rest)) = runs.split_first() else {
        return;
    };
    subs[id] = Sub::new(*first);
    queue.retain(|&q| q as usize != id);
    queue.push_front(id as u32);
    for r in rest {
        subs.push(Sub::new(*r));
        queue.push_front(subs.len() as u32 - 1);
    }
}

/// Asks the node with the most rows still to render to give half of them back.
fn ask_give_back(f: &fabric::Fabric, subs: &mut [Sub], fb: &FrameBuffer) {
    if subs.iter().any(|s| s.giving_back) {
        return;
    }
    let best = subs
        .iter()
        .enumerate()
        .filter(|(_, s)| s.node.is_some())
        .map(|(i, s)| (fb.rows_missing(s.rect), i))
        .filter(|&(rows, _)| rows >= 2)
        .max();
    if let Some((_, i)) = best {
        let s = &mut subs[i];
        s.giving_back = true;
        if let Some(node) = s.node {
            let _ = f.send(
                node,
                &Message::GiveBack {
                    subscreen: i as u32,
                },
                Box::new([]),
                0,
            );
        }
    }
}

/// Answers the last requests for work, which arrive as render nodes finish.
async fn drain_requests(cluster: &mut Cluster, f: &fabric::Fabric) {
    let until = Instant::now() + Duration::from_millis(300);
    while Instant::now() < until {
        if let Ok(Some(Delivery::Frame { frame, .. })) =
            tokio::time::timeout(Duration::from_millis(50), cluster.formed.inbox.recv()).await
            && let Ok(Message::SubscreenRequest { .. }) = frame.message()
        {
            let _ = f.reply(
                &frame,
                &Message::NoMoreWork,
                Box::new([]),
                fabric::Route::Mesh,
                0,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subscreens_tile_the_image() {
        for (w, h, n) in [(640, 480, 640), (256, 256, 16), (7, 3, 100), (1, 1, 5)] {
            let r = subscreens(w, h, n);
            let area: u32 = r.iter().map(|r| r.width * r.height).sum();
            assert_eq!(area, w * h);
            assert!(
                r.len() as f64 >= (n.min(w * h) as f64) * 0.5,
                "{w}x{h} into {n}: {}",
                r.len()
            );
        }
    }
}
