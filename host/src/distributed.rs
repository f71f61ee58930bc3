//! Rendering on the cluster: the host's part of the paper's section 1.3.2.
//!
//! The host reads the scene and sends it to the first fork node, which prepares and places
//! it and returns the header. The host then fixes the camera and settings exactly as an
//! in-process render would, sends every node the job, and hands out subscreens as render
//! nodes ask. Pixel rows reach the host's frame buffer through the fork nodes; when every
//! pixel is in, the host writes the image, collects every node's statistics and stops the
//! cluster. This module does the talking; who gets which subscreen, and when, is decided by
//! [`crate::schedule`], which does none, so that those rules can be tested without processes.

use std::{
    collections::{HashMap, HashSet},
    sync::atomic::{AtomicBool, Ordering},
    time::{Duration, Instant},
};

use fabric::{Delivery, Via};
use protocol::{
    DmaTransport, Frame, JobSpec, Message, NodeId, NodeStats, Rect, Role, Transfer, TransferMode,
    bytes_to_words, decode_value, encode_value, words_to_bytes,
};
use renderer::SceneHeader;
use serde::Serialize;

use crate::{
    checkpoint::{self, Checkpoint, CheckpointKey},
    cluster::{Cluster, ClusterConfig, StartError, start},
    inprocess::{RenderConfig, RenderError, check_settings},
    progress::Progress,
    recovery::HostCopy,
    schedule::{self, Action, Answer, Request, Scheduler},
    stats::{FetchedVia, RenderStats, SubscreenRecord},
};

#[derive(Clone, Debug)]
pub struct ClusterRenderConfig {
    pub render: RenderConfig,
    pub cluster: ClusterConfig,
    pub transfer: TransferMode,
    pub demand_via: Transfer,
    /// How render nodes' DMA reads really travel: shared memory where it can (auto) or TCP.
    pub dma_transport: DmaTransport,
    /// Cache budget per render node, as a percentage of the scene's chunk and tile bytes.
    pub cache_percent: f64,
    pub subscreens: Option<u32>,
    pub adaptive: bool,
    /// Which subscreen a render node asking for work gets.
    pub order: schedule::Order,
    pub render_threads: u32,
    /// Render nodes trace memory-coherent rays (see [`JobSpec::coherent_rays`]).
    pub coherent_rays: protocol::CoherentRays,
    /// Render nodes ask for their next subscreen as they begin one ([`JobSpec::ask_ahead`]).
    pub ask_ahead: bool,
    /// How render nodes' requests for work travel ([`JobSpec::ask_via`]); `None`: over their
    /// own connection to the host when the links have no delay model, else through the mesh,
    /// whose hops the model charges as the paper's.
    pub ask_via: Option<protocol::AskVia>,
    /// How many render nodes of one machine may work at once.
    pub at_work: schedule::AtWork,
}

/// Why a cluster render stopped without an image.
#[derive(Debug, thiserror::Error)]
pub enum ClusterRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Start(#[from] crate::cluster::StartError),
    #[error("the scene could not be sent to fork node {node}")]
    SendScene {
        node: NodeId,
        #[source]
        source: fabric::SendError,
    },
    #[error("fork node {node} could not prepare the scene: {reason}")]
    SceneRefused { node: NodeId, reason: String },
    #[error("the scene header from fork node {node} is shorter than the {len} bytes it announces")]
    ShortHeader { node: NodeId, len: u64 },
    #[error("the scene header from fork node {node} could not be decoded")]
    HeaderDecode {
        node: NodeId,
        #[source]
        source: protocol::DecodeError,
    },
    #[error("the scene header from fork node {node} failed its checks")]
    HeaderInvalid {
        node: NodeId,
        #[source]
        source: renderer::scene::SceneError,
    },
    #[error(
        "a cache of {percent}% ({cache_bytes} bytes) cannot hold the largest chunk ({largest} bytes); use a larger --cache"
    )]
    CacheTooSmall {
        percent: f64,
        cache_bytes: u64,
        largest: u64,
    },
    #[error("the job could not be sent to node {node}")]
    SendJob {
        node: NodeId,
        #[source]
        source: fabric::SendError,
    },
    #[error("node {node} failed: {message}")]
    NodeFailed { node: NodeId, message: String },
    #[error(
        "lost {}: {}; {why}, so the cluster is stopped and no image is written",
        .node.who(), .node.reason
    )]
    ForkNodeLost { node: Box<LostNode>, why: String },
    #[error("every render node is lost; no image is written")]
    NoRenderNodeLeft,
    #[error("the host's fabric stopped, so no message can reach it")]
    FabricStopped,
    #[error("interrupted")]
    Interrupted,
}

/// The `--stats` report of a cluster render: the in-process fields plus every node's.
#[derive(Clone, Debug, Serialize)]
pub struct ClusterStats {
    #[serde(flatten)]
    pub render: RenderStats,
    pub topology: String,
    /// The topology itself, as a topology file, where its name is not a preset's (a file's
    /// topology): what `simulate` replays the render on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub topology_file: Option<String>,
    pub processes: usize,
    pub transfer: String,
    /// The DMA transport asked for (`auto` or `tcp`).
    pub dma_transport: String,
    /// Render nodes whose DMA reads went through shared memory (at least one card's
    /// segment mapped), of all render nodes that reported.
    pub shared_memory_nodes: usize,
    pub cache_percent: f64,
    pub cache_bytes: u64,
    /// How demand fetches travel (`Dma` or `Serial`); batch transfers do not fetch.
    pub demand_via: String,
    /// Rendering threads on each render node.
    pub render_threads: u32,
    /// Subscreens planned (the records in `subscreens` also count the pieces split off).
    pub subscreen_count: u32,
    pub subscreens_split: u32,
    pub adaptive: bool,
    pub order: schedule::Order,
    /// Whether render nodes traced memory-coherent rays: `on` or `auto` as asked for, with a
    /// demand cache smaller than the scene, else `off` (the totals count the paths put
    /// aside; with `auto`, none on nodes that read every card's memory in place).
    pub coherent_rays: String,
    /// Whether render nodes asked for their next subscreen as they began one.
    pub ask_ahead: bool,
    /// How their requests for work travelled: `mesh` or `control`, as asked for ...
    pub ask_via: String,
    /// ... and as they came in (repeats of a request included): through the mesh of fork
    /// nodes, or over the render node's own connection to the host.
    pub requests_via: RequestsVia,
    /// How many render nodes of one machine were let work at once, as asked (`auto`,
    /// `cpus`, `all` or a number) ...
    pub at_work: String,
    /// ... and as it came out: the machines whose render nodes were limited, each with its
    /// nodes and how many of them worked at once (none: every node could work).
    pub machine_limits: Vec<schedule::Machine>,
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
    /// Subscreens it held with rows still missing, handed to other nodes; for a fork node,
    /// those of the render nodes it served, whose rows on their way were lost with it.
    pub subscreens_reassigned: u32,
    /// For a fork node: chunks and tiles of its share rebuilt on live cards.
    pub items_moved: u32,
    /// Seconds from noticing the loss until rendering went on: for a fork node, its share
    /// placed on the live cards, its render nodes served by another, their unfinished work
    /// queued again; 0 for a render node (its work is queued again at once).
    pub recovered_after_s: f64,
    /// For a fork node: seconds from noticing the loss until the first pixels of a render
    /// node it served reached the frame buffer through another fork node (none if the
    /// render ended first).
    pub served_rows_after_s: Option<f64>,
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

/// Renders on a cluster; returns the statistics written to `--stats`.
pub async fn render_on_cluster(
    config: &ClusterRenderConfig,
    cancel: &AtomicBool,
) -> Result<ClusterStats, ClusterRenderError> {
    let rc = &config.render;
    check_settings(rc)?;
    let t0 = Instant::now();

    // The host reads the scene from disk while the cluster starts (both take a good part of
    // a second on a scene of a million triangles). A file that cannot be opened is reported
    // before any process starts.
    if let crate::scene_source::SceneSource::File(path) = &rc.scene
        && let Err(e) = std::fs::File::open(path)
    {
        let e = scene_io::LoadError::Io {
            path: path.clone(),
            source: e,
        };
        return Err(RenderError::Load(e).into());
    }
    // Encoded for the first fork node (and hashed for the checkpoint) in the same task, so
    // that the encoding does not wait for the cluster to form.
    let reading = {
        let (scene, environment) = (rc.scene.clone(), rc.environment);
        tokio::task::spawn_blocking(move || {
            crate::scene_source::read_scene(&scene, environment)
                .map(|(desc, warnings)| (EncodedScene::new(desc), warnings))
        })
    };
    let t = config.cluster.topology.clone();
    // Said once the scene is read, so that a scene that cannot be read is still one line
    // of error, as when nothing was started.
    let read = async {
        // A panic while reading is the reader's bug: it goes on as a panic here.
        let read = reading
            .await
            .unwrap_or_else(|e| std::panic::resume_unwind(e.into_panic()));
        if let Ok((_, warnings)) = &read {
            for w in warnings {
                tracing::warn!("{}: {w}", rc.scene);
            }
            tracing::info!("scene read; the render runs on {}", t.summary());
        }
        read.map_err(|e| ClusterRenderError::from(RenderError::Load(e)))
    };
    let starting = async {
        start(&config.cluster, &|_, _| {}, cancel)
            .await
            .map_err(|e| match e {
                StartError::Stopped => ClusterRenderError::Interrupted,
                e => e.into(),
            })
    };
    tokio::pin!(starting, read);
    let (mut cluster, scene) = tokio::select! {
        // A scene that cannot be read ends the start at once (nodes started by hand may be
        // long in joining); spawned nodes are killed with the half-formed cluster.
        read = &mut read => {
            let (scene, _) = read?;
            (starting.await?, scene)
        }
        started = &mut starting => {
            let cluster = started?;
            match read.await {
                Ok((scene, _)) => (cluster, scene),
                Err(e) => {
                    cluster.shutdown("the scene could not be read").await;
                    return Err(e);
                }
            }
        }
    };
    let result = drive(config, &mut cluster, scene, cancel, t0).await;
    let clean = cluster
        .shutdown(match &result {
            Ok(_) => "render done",
            Err(ClusterRenderError::Interrupted) => "the host was stopped",
            Err(_) => "render failed",
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
                    "the cluster {} is full and rendering; a node joins a cluster before its render begins",
                    cluster.formed.fabric.topology().name
                ),
            );
            Ok(None)
        }
        Ok(Some(d)) => Ok(Some(d)),
        Ok(None) => Err(ClusterRenderError::FabricStopped),
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
    /// A connection to `peer` ended. A lost node is declared dead to everyone, who route
    /// around it; returns what the loss asks of the render, if `peer` was newly lost. A lost
    /// fork node ends the render when no fork node is left to hold its share of the scene,
    /// or while the scene is being placed (not `recoverable`).
    fn on_lost(
        &mut self,
        cluster: &Cluster,
        peer: NodeId,
        reason: &str,
        recoverable: bool,
    ) -> Result<Option<Loss>, ClusterRenderError> {
        let f = &cluster.formed.fabric;
        let topo = f.topology();
        if peer == 0 || peer as usize >= topo.len() || !f.is_alive(peer) {
            return Ok(None);
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
            items_moved: 0,
            recovered_after_s: 0.0,
            served_rows_after_s: None,
        };
        if role != Role::Render {
            let live_forks = topo
                .fork_nodes()
                .into_iter()
                .filter(|&n| n != peer && f.is_alive(n))
                .count();
            let why = match (live_forks, recoverable) {
                (0, _) => Some("no fork node is left to hold its share of the scene"),
                (_, false) => Some("the scene was still being placed"),
                _ => None,
            };
            if let Some(why) = why {
                return Err(ClusterRenderError::ForkNodeLost {
                    node: Box::new(lost),
                    why: why.into(),
                });
            }
        }
        // The render nodes it served, before the loss changes who serves them.
        let served: Vec<NodeId> = topo
            .render_nodes()
            .into_iter()
            .filter(|&r| f.is_alive(r) && f.serving_fork(r) == Some(peer))
            .collect();
        if role == Role::Render {
            tracing::warn!(
                "lost {}: {reason}; its unfinished subscreens go to other nodes, and routes go around it",
                lost.who()
            );
        } else {
            tracing::warn!(
                "lost {}: {reason}; its share of the scene is rebuilt on the live fork nodes from the host's copy, and its {} render nodes go to another",
                lost.who(),
                served.len()
            );
        }
        f.mark_dead(peer);
        for m in &cluster.formed.members {
            if m.node != peer && f.is_alive(m.node) {
                let _ = f.send_control(m.node, &Message::NodeDown { node: peer });
            }
        }
        self.lost.push(lost);
        if !topo.render_nodes().into_iter().any(|n| f.is_alive(n)) {
            return Err(ClusterRenderError::NoRenderNodeLeft);
        }
        Ok(Some(match role {
            Role::Render => Loss::Render,
            _ => Loss::Fork { served },
        }))
    }
}

/// What a loss asks of the render going on.
enum Loss {
    /// A render node: its work goes to others.
    Render,
    /// A fork node: its share of the scene is to be rebuilt, and the rows its render nodes
    /// (`served`) sent through it may be lost.
    Fork { served: Vec<NodeId> },
}

async fn drive(
    config: &ClusterRenderConfig,
    cluster: &mut Cluster,
    scene: EncodedScene,
    cancel: &AtomicBool,
    t0: Instant,
) -> Result<ClusterStats, ClusterRenderError> {
    let rc = &config.render;
    let f = cluster.formed.fabric.clone();
    let mut faults = Faults {
        started: t0,
        lost: Vec::new(),
    };
    let chunk_triangles = rc.prepare.chunk_triangles as u32;
    let EncodedScene {
        desc,
        encoded,
        digest: scene_sha256,
    } = scene;
    upload_scene(&f, &encoded, chunk_triangles)?;
    // The denoiser's guides are traced here, from the host's own copy of the scene; without
    // them the copy goes now.
    let for_guides = rc.denoise.then_some(desc);
    let placed = await_header(cluster, cancel, &mut faults).await?;
    let scene = placed.scene;
    let copy = HostCopy {
        encoded,
        chunk_triangles,
        header: placed.header,
        chunk_owner: placed.chunk_owner,
        tile_owner: placed.tile_owner,
    };
    let load_s = t0.elapsed().as_secs_f64();
    let plan = plan_job(
        config,
        &scene,
        f.topology().render_nodes(),
        &cluster.formed.members,
    )?;
    let (width, height) = (plan.job.settings.width, plan.job.settings.height);
    let key = CheckpointKey::new(
        scene_sha256,
        &rc.prepare,
        &plan.job.settings,
        &plan.job.camera,
    );
    let kept = checkpoint::start(
        &checkpoint::path_for(&rc.output),
        rc.resume,
        key,
        width,
        height,
    )
    .map_err(RenderError::from)?;
    send_job(&f, &plan.job)?;
    // Traced while the cluster renders.
    let guides = for_guides.map(|desc| {
        let (camera, prepare, threads) = (plan.job.camera.clone(), rc.prepare, rc.threads);
        tokio::task::spawn_blocking(move || {
            let (scene, data) = renderer::prepare(desc, &prepare);
            renderer::denoise::guides(&scene, &data, &camera, width, height, threads)
        })
    });

    let t1 = Instant::now();
    let mut frame = Rendering::new(config, &plan, &faults, f.clone(), kept, copy, t1);
    if let Err(e) = frame.run(cluster, cancel, &mut faults).await {
        // What is finished outlives the render: `--resume` continues from it.
        frame.save();
        return Err(e);
    }
    let render_s = t1.elapsed().as_secs_f64();
    let answered = frame.finish(&mut faults);
    let owed = f
        .topology()
        .render_nodes()
        .into_iter()
        .filter(|&n| f.is_alive(n) && !answered.contains(&n))
        .collect();
    drain_requests(cluster, &f, owed).await;

    let t_denoise = Instant::now();
    let denoised = match guides {
        Some(task) => {
            let guides = task
                .await
                .expect("the denoiser's guide tracing panicked")
                .map_err(RenderError::Render)?;
            Some(renderer::denoise::denoise(
                &frame.kept.image,
                &guides,
                rc.threads,
            ))
        }
        None => None,
    };
    let denoise_s = t_denoise.elapsed().as_secs_f64();

    let t2 = Instant::now();
    scene_io::write_image(&rc.output, denoised.as_ref().unwrap_or(&frame.kept.image))
        .map_err(RenderError::Output)?;
    // The image is whole: its checkpoint, if one was written, has served.
    let _ = std::fs::remove_file(&frame.checkpoint_path);
    let write_s = t2.elapsed().as_secs_f64();

    let nodes = collect_node_stats(cluster).await;
    let seconds = crate::stats::Seconds {
        load: load_s,
        render: render_s,
        denoise: denoise_s,
        write: write_s,
        total: t0.elapsed().as_secs_f64(),
    };
    let stats = cluster_stats(
        config,
        cluster,
        Finished {
            scene: &scene,
            plan: &plan,
            subscreens: frame.scheduler.planned(),
            subscreens_split: frame.scheduler.split(),
            requests_via: frame.requests_via,
            times: std::mem::take(&mut frame.times),
            nodes,
            lost_nodes: faults.lost,
            seconds,
        },
    );
    if let Some(p) = &rc.stats {
        let json = serde_json::to_vec_pretty(&stats).unwrap_or_default();
        scene_io::image_io::write_atomic(p, &json).map_err(RenderError::Output)?;
    }
    Ok(stats)
}

/// The scene description, encoded as it travels to the first fork node (and kept to rebuild
/// a lost fork node's share from), and the encoding's digest (the scene's hash in a
/// checkpoint).
struct EncodedScene {
    desc: renderer::SceneDesc,
    encoded: Vec<u8>,
    digest: String,
}

impl EncodedScene {
    fn new(desc: renderer::SceneDesc) -> EncodedScene {
        let encoded = encode_value(&desc);
        let digest = checkpoint::digest_of_encoded(&encoded);
        EncodedScene {
            desc,
            encoded,
            digest,
        }
    }
}

/// Sends the encoded scene to the first fork node, in parts that fit a frame.
fn upload_scene(
    f: &fabric::Fabric,
    bytes: &[u8],
    chunk_triangles: u32,
) -> Result<(), ClusterRenderError> {
    let master = f.topology().master_fork();
    const PART: usize = 16 << 20;
    let parts = bytes.len().div_ceil(PART).max(1) as u32;
    for (i, part) in bytes.chunks(PART).enumerate() {
        let msg = Message::ScenePart {
            part: i as u32,
            parts,
            total: bytes.len() as u64,
            len: part.len() as u32,
            chunk_triangles,
        };
        f.send_direct(master, &msg, bytes_to_words(part), 0, 0)
            .map_err(|source| ClusterRenderError::SendScene {
                node: master,
                source,
            })?;
    }
    Ok(())
}

/// The prepared scene as the first fork node placed it.
struct Placed {
    scene: SceneHeader,
    /// The header as it travelled.
    header: Vec<u8>,
    chunk_owner: Vec<NodeId>,
    tile_owner: Vec<NodeId>,
}

/// Waits for the prepared scene's header and address table from the first fork node.
async fn await_header(
    cluster: &mut Cluster,
    cancel: &AtomicBool,
    faults: &mut Faults,
) -> Result<Placed, ClusterRenderError> {
    let master = cluster.formed.fabric.topology().master_fork();
    loop {
        let Some(delivery) = next(cluster, cancel).await? else {
            continue;
        };
        match delivery {
            Delivery::Frame {
                frame,
                via: Via::Direct(_),
            } => {
                if let Ok(Message::Header {
                    len,
                    chunk_owner,
                    tile_owner,
                }) = frame.message()
                {
                    let (scene, header) = read_header(&frame, len)?;
                    return Ok(Placed {
                        scene,
                        header,
                        chunk_owner,
                        tile_owner,
                    });
                }
            }
            Delivery::Frame {
                frame,
                via: Via::Control(_),
            } => match frame.message() {
                Ok(Message::Failed { node, message }) if node == master => {
                    return Err(ClusterRenderError::SceneRefused {
                        node,
                        reason: message,
                    });
                }
                Ok(Message::Failed { node, message }) => {
                    return Err(ClusterRenderError::NodeFailed { node, message });
                }
                _ => {}
            },
            Delivery::Lost { peer, reason, .. } => {
                faults.on_lost(cluster, peer, &reason, false)?;
            }
            _ => {}
        }
    }
}

/// The scene of a header frame, checked as the render nodes check it, and its bytes.
fn read_header(frame: &Frame, len: u64) -> Result<(SceneHeader, Vec<u8>), ClusterRenderError> {
    let node = frame.header.sender;
    let bytes = words_to_bytes(&frame.data, len as usize)
        .ok_or(ClusterRenderError::ShortHeader { node, len })?;
    let scene: SceneHeader =
        decode_value(bytes).map_err(|source| ClusterRenderError::HeaderDecode { node, source })?;
    scene
        .validate()
        .map_err(|source| ClusterRenderError::HeaderInvalid { node, source })?;
    Ok((scene, bytes.to_vec()))
}

/// What every node is told to do, and how the image is cut.
struct JobPlan {
    job: JobSpec,
    subscreens: Vec<Rect>,
    render_nodes: Vec<NodeId>,
    /// Machines on which fewer render nodes work at once than run.
    machines: Vec<schedule::Machine>,
}

/// Fixes the camera and settings exactly as a render in one process would, the cache of
/// each render node, and the subscreens.
fn plan_job(
    config: &ClusterRenderConfig,
    scene: &SceneHeader,
    render_nodes: Vec<NodeId>,
    members: &[fabric::cluster::Member],
) -> Result<JobPlan, ClusterRenderError> {
    let rc = &config.render;
    let (settings, camera) = crate::inprocess::camera_and_settings(rc, scene)?;
    // A cache holds chunks ready to walk, so its percentages are of what the scene takes in
    // that form (words and walking forms), not of the bytes that cross the links.
    let data_bytes = scene.memory_bytes();
    let cache_bytes = (config.cache_percent / 100.0 * data_bytes as f64).ceil() as u64;
    let largest = scene.largest_chunk_memory();
    if config.transfer == TransferMode::Demand && cache_bytes < largest {
        return Err(ClusterRenderError::CacheTooSmall {
            percent: config.cache_percent,
            cache_bytes,
            largest,
        });
    }
    let subscreens = subscreens(
        settings.width,
        settings.height,
        config.subscreens.unwrap_or(8 * render_nodes.len() as u32),
    );
    tracing::info!(
        "{}: {} triangles in {} chunks; {}x{} at {} spp ({}), {} subscreens on {} render nodes, {} transfer, cache {cache_bytes} bytes",
        rc.scene,
        scene.triangle_count(),
        scene.chunks.len(),
        settings.width,
        settings.height,
        settings.spp,
        settings.integrator,
        subscreens.len(),
        render_nodes.len(),
        format!("{:?}", config.transfer).to_lowercase()
    );
    let no_link_model = config.cluster.topology.model.link == fabric::model::LinkModelKind::None;
    // Only a cache smaller than the scene misses while rendering (and can make a path wait).
    let misses = config.transfer == TransferMode::Demand && cache_bytes < data_bytes;
    let job = JobSpec {
        settings,
        camera,
        transfer: config.transfer,
        demand_via: config.demand_via,
        dma_transport: config.dma_transport,
        cache_bytes,
        render_threads: config.render_threads,
        coherent_rays: if misses {
            config.coherent_rays
        } else {
            protocol::CoherentRays::Off
        },
        ask_ahead: config.ask_ahead,
        ask_via: config.ask_via.unwrap_or(if no_link_model {
            protocol::AskVia::Control
        } else {
            protocol::AskVia::Mesh
        }),
    };
    // Nodes that wait for fetches over sockets while rendering leave their CPUs idle: more
    // of them at work fill those waits (the spheres at cache 5% over TCP, 320x240 at 16 spp:
    // 29 to 64 s with two at work, 25 s with 16 or all). Where every miss is a read in place,
    // or the cache holds the whole scene, nothing waits long. A card is read in place only
    // where its fork node's shared memory is seen (its machine, and there not from a
    // container with a /dev/shm of its own), and a render node reads every card.
    let cards_and_nodes = members
        .iter()
        .filter(|m| matches!(m.role, Role::Render | Role::Fork))
        .map(|m| m.shm_domain.as_str());
    let misses_cross_sockets = misses
        && (config.dma_transport == protocol::DmaTransport::Tcp
            || config.demand_via == Transfer::Serial
            || schedule::spans_shared_memories(cards_and_nodes));
    let at_work = schedule::resolve_at_work(config.at_work, !no_link_model, misses_cross_sockets);
    let on_machines: Vec<schedule::NodeMachine<'_>> = members
        .iter()
        .filter(|m| render_nodes.contains(&m.node))
        .map(|m| schedule::NodeMachine {
            node: m.node,
            machine: &m.boot_id,
            cpus: m.cpus,
            machine_cpus: m.machine_cpus,
        })
        .collect();
    let machines = schedule::machines(&on_machines, at_work, config.render_threads);
    for m in &machines {
        tracing::info!(
            "{} render nodes share a machine: {} of them work at once (--at-work {})",
            m.nodes.len(),
            m.at_work,
            config.at_work
        );
    }
    Ok(JobPlan {
        job,
        subscreens,
        render_nodes,
        machines,
    })
}

/// Sends the job to every live node.
fn send_job(f: &fabric::Fabric, job: &JobSpec) -> Result<(), ClusterRenderError> {
    for node in 1..f.topology().len() as NodeId {
        if f.is_alive(node) {
            f.send_control(node, &Message::Job(Box::new(job.clone())))
                .map_err(|source| ClusterRenderError::SendJob { node, source })?;
        }
    }
    Ok(())
}

/// A run of pixels as it arrived, for [`Action::Store`] to copy from.
struct Run<'a> {
    x: u32,
    y: u32,
    data: &'a [u32],
}

/// One frame being rendered: the messages in and out around the [`Scheduler`]'s decisions,
/// and the image they fill.
struct Rendering {
    scheduler: Scheduler,
    /// The image, and which of its lines are finished: what `OUT.partial` keeps.
    kept: Checkpoint,
    /// Per line, pixels not yet in.
    pending: Vec<u32>,
    checkpoint_path: std::path::PathBuf,
    checkpoint_interval: Duration,
    last_checkpoint: Instant,
    /// Whether writing the checkpoint failed already (said once, the render goes on).
    checkpoint_failed: bool,
    /// The frames of requests for work not answered yet, to answer them by.
    requests: HashMap<Request, (Frame, Via)>,
    requests_via: RequestsVia,
    times: SubscreenTimes,
    progress: Progress,
    /// The scene as the host sent it and where its items are: a lost fork node's share is
    /// rebuilt from it.
    copy: HostCopy,
    /// Lost fork nodes whose render nodes have not yet had pixels arrive since: the fork
    /// node, the render nodes it served, when the loss was noticed.
    resuming: Vec<(NodeId, Vec<NodeId>, Instant)>,
    f: fabric::Fabric,
}

impl Rendering {
    fn new(
        config: &ClusterRenderConfig,
        plan: &JobPlan,
        faults: &Faults,
        f: fabric::Fabric,
        kept: Checkpoint,
        copy: HostCopy,
        now: Instant,
    ) -> Rendering {
        let (width, height) = (plan.job.settings.width, plan.job.settings.height);
        let finished: Vec<Rect> = (0..height)
            .filter(|&y| kept.rows_done[y as usize])
            .map(|y| Rect {
                x: 0,
                y,
                width,
                height: 1,
            })
            .collect();
        let mut scheduler = Scheduler::resume(
            schedule::Plan {
                width,
                height,
                subscreens: plan.subscreens.clone(),
                render_nodes: plan.render_nodes.clone(),
                adaptive: config.adaptive,
                order: config.order,
                machines: plan.machines.clone(),
            },
            &finished,
            now,
        );
        // Render nodes lost while the scene was placed held no work, yet their loss still
        // makes finished subscreens suspect.
        for lost in &faults.lost {
            scheduler.node_lost(lost.node);
        }
        let total = width as u64 * height as u64;
        Rendering {
            scheduler,
            pending: kept.pending(),
            kept,
            checkpoint_path: checkpoint::path_for(&config.render.output),
            checkpoint_interval: config.render.checkpoint_interval,
            last_checkpoint: now,
            checkpoint_failed: false,
            requests: HashMap::new(),
            requests_via: RequestsVia::default(),
            times: SubscreenTimes {
                began: Some(now),
                ..SubscreenTimes::default()
            },
            progress: Progress::new(total, config.render.progress),
            copy,
            resuming: Vec::new(),
            f,
        }
    }

    /// Hands out subscreens and collects pixels until the image is complete.
    async fn run(
        &mut self,
        cluster: &mut Cluster,
        cancel: &AtomicBool,
        faults: &mut Faults,
    ) -> Result<(), ClusterRenderError> {
        while !self.scheduler.is_complete() {
            // `None`: nothing arrived for a tick; only the timed duties run.
            match next(cluster, cancel).await? {
                Some(Delivery::Frame { frame, via }) => self.on_frame(frame, via, faults)?,
                Some(Delivery::Lost { peer, reason, .. }) => {
                    self.on_lost(cluster, peer, &reason, faults).await?;
                }
                _ => {}
            }
            let actions = self.scheduler.tick(Instant::now());
            self.perform(actions, None, faults);
            if self.last_checkpoint.elapsed() >= self.checkpoint_interval {
                self.save();
            }
        }
        self.progress.finish();
        Ok(())
    }

    /// Replaces the checkpoint with the lines finished so far.
    fn save(&mut self) {
        self.last_checkpoint = Instant::now();
        let k = &self.kept;
        if let Err(e) = checkpoint::write(&self.checkpoint_path, &k.key, &k.image, &k.rows_done)
            && !self.checkpoint_failed
        {
            self.checkpoint_failed = true;
            tracing::warn!("cannot keep a checkpoint: {e}");
        }
    }

    /// The connection to `peer` ended: a render node's work goes to others; a fork node's
    /// share of the scene is rebuilt on the live cards, and the work of the render nodes it
    /// served is queued again (their rows on the way went with it), while they go on,
    /// served by another fork node.
    async fn on_lost(
        &mut self,
        cluster: &Cluster,
        peer: NodeId,
        reason: &str,
        faults: &mut Faults,
    ) -> Result<(), ClusterRenderError> {
        let detected = Instant::now();
        match faults.on_lost(cluster, peer, reason, true)? {
            None => {}
            Some(Loss::Render) => {
                self.requests.retain(|r, _| r.node != peer);
                let actions = self.scheduler.node_lost(peer);
                self.perform(actions, None, faults);
            }
            Some(Loss::Fork { served }) => {
                let moved = match self.copy.rebuild(&self.f, peer).await {
                    Ok(moved) => moved,
                    Err(e) => {
                        let lost = faults.lost.pop().map(Box::new);
                        return Err(match lost {
                            Some(node) => ClusterRenderError::ForkNodeLost {
                                node,
                                why: format!("its share of the scene could not be rebuilt: {e}"),
                            },
                            None => ClusterRenderError::FabricStopped,
                        });
                    }
                };
                let mut reassigned = 0;
                self.resuming.push((peer, served.clone(), detected));
                for r in served {
                    let actions = self.scheduler.take_back(r);
                    for a in &actions {
                        if let Action::Reassigned { subscreens, .. } = a {
                            reassigned += subscreens;
                        }
                    }
                    self.perform(actions, None, faults);
                }
                let recovered_after_s = detected.elapsed().as_secs_f64();
                if let Some(l) = faults.lost.iter_mut().find(|l| l.node == peer) {
                    l.items_moved = moved;
                    l.subscreens_reassigned = reassigned;
                    l.recovered_after_s = recovered_after_s;
                }
                tracing::info!(
                    "fork node {peer}'s share ({moved} chunks and tiles) rebuilt on the live fork nodes and {reassigned} subscreens queued again; rendering goes on {recovered_after_s:.2} s after the loss"
                );
                event_recovered(peer);
            }
        }
        Ok(())
    }

    fn on_frame(
        &mut self,
        frame: Frame,
        via: Via,
        faults: &mut Faults,
    ) -> Result<(), ClusterRenderError> {
        let Ok(msg) = frame.message() else {
            return Ok(());
        };
        let sender = frame.header.sender;
        // A lost node's late words change nothing (its pixels still count).
        if !self.f.is_alive(sender) && !matches!(msg, Message::Pixels { .. }) {
            return Ok(());
        }
        match msg {
            Message::SubscreenRequest { finished, ahead } => {
                let request = Request {
                    node: sender,
                    tag: frame.header.tag,
                };
                match via {
                    Via::Control(_) => self.requests_via.control += 1,
                    Via::Mesh(_) | Via::Direct(_) => self.requests_via.mesh += 1,
                }
                // A repeat of a waiting request is answered by the first one's frame, the way
                // it came.
                self.requests.entry(request).or_insert((frame, via));
                let actions = self
                    .scheduler
                    .request(request, finished, ahead, Instant::now());
                self.perform(actions, None, faults);
                if !self.scheduler.is_waiting(request) {
                    self.requests.remove(&request);
                }
            }
            Message::Returned {
                subscreen,
                from_row,
            } => {
                let actions = self.scheduler.returned(sender, subscreen, from_row);
                self.perform(actions, None, faults);
            }
            Message::Pixels {
                subscreen,
                x,
                y,
                width,
            } if matches!(via, Via::Direct(_))
                && width > 0
                && !frame.data.is_empty()
                && frame.data.len().is_multiple_of(width as usize * 3) =>
            {
                self.times.pixels_in(subscreen);
                for (row, data) in frame.data.chunks_exact(width as usize * 3).enumerate() {
                    let y = y.saturating_add(row as u32);
                    let actions = self.scheduler.pixels(subscreen, x, y, width);
                    self.perform(actions, Some(Run { x, y, data }), faults);
                }
            }
            Message::Failed { node, message } => {
                return Err(ClusterRenderError::NodeFailed { node, message });
            }
            _ => {}
        }
        Ok(())
    }

    /// Carries out the scheduler's decisions; `run` is the run of pixels that led to them.
    fn perform(&mut self, actions: Vec<Action>, run: Option<Run<'_>>, faults: &mut Faults) {
        let mut stored = false;
        for action in actions {
            match action {
                Action::Answer { request, answer } => self.answer(request, answer),
                Action::GiveBack { node, subscreen } => {
                    let _ = self
                        .f
                        .send(node, &Message::GiveBack { subscreen }, Box::new([]), 0);
                }
                Action::Store { x, y, width } => {
                    if let Some(run) = &run {
                        self.store(run, x, y, width);
                        stored = true;
                    }
                }
                Action::FirstPixels { node, subscreen } => {
                    event_first_pixels(node, subscreen);
                    self.resumed(node, faults);
                }
                Action::Reassigned { node, subscreens } => {
                    if let Some(l) = faults.lost.iter_mut().find(|l| l.node == node) {
                        l.subscreens_reassigned = subscreens;
                    }
                }
                Action::RowsNeverArrived { subscreen } => {
                    tracing::info!(
                        "rows of subscreen {subscreen} never arrived; rendering them again"
                    );
                }
                Action::Stalled(report) => tracing::info!("{report}"),
                // The loop in `run` sees it.
                Action::Complete => {}
            }
        }
        if stored {
            let total = self.kept.image.pixels.len() as u64;
            self.progress
                .update(total - self.scheduler.missing(), total);
        }
    }

    /// Pixels of `node` arrived: if it was served by a lost fork node, they came through
    /// another, and the lost card renders again.
    fn resumed(&mut self, node: NodeId, faults: &mut Faults) {
        self.resuming.retain(|(fork, served, detected)| {
            if !served.contains(&node) {
                return true;
            }
            let after = detected.elapsed().as_secs_f64();
            if let Some(l) = faults.lost.iter_mut().find(|l| l.node == *fork) {
                l.served_rows_after_s = Some(after);
            }
            tracing::info!(
                "render node {node}, served by lost fork node {fork}, renders again: its pixels arrive {after:.2} s after the loss"
            );
            false
        });
    }

    fn answer(&mut self, request: Request, answer: Answer) {
        let Some((frame, via)) = self.requests.remove(&request) else {
            return;
        };
        let message = match answer {
            Answer::Subscreen { id, rect } => {
                self.times.handed_out(request.node, id);
                Message::Subscreen { id, rect }
            }
            Answer::NoMoreWork => Message::NoMoreWork,
            Answer::NothingAhead => Message::NothingAhead,
        };
        let _ = self
            .f
            .reply(&frame, &message, Box::new([]), fabric::Route::back(via), 0);
    }

    /// Copies `width` pixels at (x, y) from the run that brought them into the image.
    fn store(&mut self, run: &Run<'_>, x: u32, y: u32, width: u32) {
        let pixels: &[[f32; 3]] = bytemuck::cast_slice(run.data);
        let from = (x - run.x) as usize;
        debug_assert_eq!(y, run.y);
        // The scheduler stores each pixel once, so a line's count of pixels left is exact.
        let rect = Rect {
            x,
            y,
            width,
            height: 1,
        };
        self.kept.put_rect(
            rect,
            &pixels[from..from + width as usize],
            &mut self.pending,
        );
    }

    /// The frame is complete: everyone still asking is told there is nothing more.
    /// Answers the requests held until the end; returns the render nodes answered.
    fn finish(&mut self, faults: &mut Faults) -> Vec<NodeId> {
        let actions = self.scheduler.finish();
        let answered = actions
            .iter()
            .filter_map(|a| match a {
                Action::Answer { request, .. } => Some(request.node),
                _ => None,
            })
            .collect();
        self.perform(actions, None, faults);
        answered
    }
}

/// When, by the host's clock, each subscreen went out and its pixels came in: the times of
/// the per-subscreen records, whose costs the render nodes report at the end.
#[derive(Default)]
struct SubscreenTimes {
    began: Option<Instant>,
    /// Seconds since `began` each (render node, subscreen) was first handed out.
    out: HashMap<(NodeId, u32), f64>,
    /// Seconds since `began` the last pixels of each subscreen arrived.
    last_in: HashMap<u32, f64>,
}

impl SubscreenTimes {
    fn now(&self) -> f64 {
        self.began.map_or(0.0, |b| b.elapsed().as_secs_f64())
    }

    fn handed_out(&mut self, node: NodeId, subscreen: u32) {
        let now = self.now();
        // A request sent twice is answered twice with the same subscreen: the first counts.
        self.out.entry((node, subscreen)).or_insert(now);
    }

    fn pixels_in(&mut self, subscreen: u32) {
        let now = self.now();
        self.last_in.insert(subscreen, now);
    }

    /// Every render node's subscreens, with their times, ordered by when they ended.
    fn records(&self, nodes: &[NodeStats], job: &JobSpec) -> Vec<SubscreenRecord> {
        let mut records: Vec<SubscreenRecord> = nodes
            .iter()
            .flat_map(|n| n.records.iter().map(move |w| (n.node, w)))
            .map(|(node, w)| {
                let start_s = self.out.get(&(node, w.subscreen)).copied().unwrap_or(0.0);
                SubscreenRecord {
                    node: node as u32,
                    x: w.rect.x,
                    y: w.rect.y,
                    width: w.rect.width,
                    height: w.rect.height,
                    start_s,
                    end_s: self
                        .last_in
                        .get(&w.subscreen)
                        .copied()
                        .unwrap_or(start_s)
                        .max(start_s),
                    cpu_s: w.cpu_s,
                    pixels: w.pixels,
                    samples: w.samples,
                    rays: w.rays,
                    chunks: w.chunks.clone(),
                    tiles: w.tiles.clone(),
                    fetched_bytes: w.fetched_bytes,
                    fetches: w.fetches,
                    fetched_via: match (job.transfer, job.demand_via) {
                        (TransferMode::Batch, _) => FetchedVia::Batch,
                        _ if w.fetches == 0 => FetchedVia::None,
                        (TransferMode::Demand, Transfer::Dma) => FetchedVia::Dma,
                        (TransferMode::Demand, Transfer::Serial) => FetchedVia::Mesh,
                    },
                }
            })
            .collect();
        records.sort_by(|a, b| a.end_s.total_cmp(&b.end_s).then(a.node.cmp(&b.node)));
        records
    }
}

/// Answers a request for work that came `via` this way, after the frame, with "no more work".
fn refuse_request(f: &fabric::Fabric, request: &Frame, via: Via) {
    let _ = f.reply(
        request,
        &Message::NoMoreWork,
        Box::new([]),
        fabric::Route::back(via),
        0,
    );
}

/// Every live node's statistics, as many as arrive within 10 s.
async fn collect_node_stats(cluster: &mut Cluster) -> Vec<NodeStats> {
    let f = cluster.formed.fabric.clone();
    let mut alive: Vec<NodeId> = (1..f.topology().len() as NodeId)
        .filter(|&n| f.is_alive(n))
        .collect();
    for &n in &alive {
        let _ = f.send_control(n, &Message::StatsRequest);
    }
    let mut nodes: HashMap<NodeId, NodeStats> = HashMap::new();
    let until = Instant::now() + Duration::from_secs(10);
    while nodes.len() < alive.len() && Instant::now() < until {
        match tokio::time::timeout(Duration::from_millis(200), cluster.formed.inbox.recv()).await {
            Ok(Some(Delivery::Frame { frame, via })) => match frame.message() {
                Ok(Message::NodeStats(s)) => {
                    nodes.insert(s.node, *s);
                }
                Ok(Message::SubscreenRequest { .. }) => refuse_request(&f, &frame, via),
                _ => {}
            },
            // A node lost now cannot answer; the image is already written. Marked dead so
            // that the shutdown does not wait for it either.
            Ok(Some(Delivery::Lost { peer, reason, .. })) if alive.contains(&peer) => {
                tracing::warn!(
                    "lost node {peer} after the render: {reason}; its figures are missing"
                );
                f.mark_dead(peer);
                alive.retain(|&n| n != peer);
            }
            Ok(None) => break,
            _ => {}
        }
    }
    let mut nodes: Vec<NodeStats> = nodes.into_values().collect();
    nodes.sort_by_key(|n| n.node);
    nodes
}

/// The sums of every node's figures. Every field is named (none left to `..`), so a figure
/// added to [`NodeStats`] cannot be left out of the totals unnoticed.
fn sum_node_stats(nodes: &[NodeStats]) -> NodeStats {
    let mut t = NodeStats::default();
    for n in nodes {
        let NodeStats {
            node: _,
            role: _,
            subscreens,
            rows,
            pixels,
            samples,
            rays,
            camera_rays,
            secondary_rays,
            shadow_rays,
            bad_samples,
            cache_hits,
            cache_misses,
            cache_evictions,
            cache_peak_bytes,
            bytes_fetched_dma,
            bytes_fetched_serial,
            bytes_fetched_shared,
            shared_segments,
            bytes_served,
            bytes_gbus,
            frames_forwarded,
            frames_around_mesh,
            bytes_forwarded,
            busy_s,
            waiting_s,
            idle_s,
            peak_rss_bytes,
            peak_private_bytes,
            chunks_in_place,
            paths_deferred,
            deferred_fetches,
            share_items_in_segment,
            records: _,
        } = n;
        t.subscreens += subscreens;
        t.rows += rows;
        t.pixels += pixels;
        t.samples += samples;
        t.rays += rays;
        t.camera_rays += camera_rays;
        t.secondary_rays += secondary_rays;
        t.shadow_rays += shadow_rays;
        t.bad_samples += bad_samples;
        t.cache_hits += cache_hits;
        t.cache_misses += cache_misses;
        t.cache_evictions += cache_evictions;
        t.cache_peak_bytes += cache_peak_bytes;
        t.bytes_fetched_dma += bytes_fetched_dma;
        t.bytes_fetched_serial += bytes_fetched_serial;
        t.bytes_fetched_shared += bytes_fetched_shared;
        t.shared_segments += shared_segments;
        t.bytes_served += bytes_served;
        t.bytes_gbus += bytes_gbus;
        t.frames_forwarded += frames_forwarded;
        t.frames_around_mesh += frames_around_mesh;
        t.bytes_forwarded += bytes_forwarded;
        t.busy_s += busy_s;
        t.waiting_s += waiting_s;
        t.idle_s += idle_s;
        t.peak_rss_bytes += peak_rss_bytes;
        t.peak_private_bytes += peak_private_bytes;
        t.chunks_in_place += chunks_in_place;
        t.paths_deferred += paths_deferred;
        t.deferred_fetches += deferred_fetches;
        t.share_items_in_segment += share_items_in_segment;
    }
    t
}

/// Render nodes' requests for work, by the way they reached the host.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RequestsVia {
    pub mesh: u64,
    pub control: u64,
}

/// What a finished render leaves for its statistics.
struct Finished<'a> {
    scene: &'a SceneHeader,
    plan: &'a JobPlan,
    subscreens: u32,
    subscreens_split: u32,
    requests_via: RequestsVia,
    times: SubscreenTimes,
    nodes: Vec<NodeStats>,
    lost_nodes: Vec<LostNode>,
    seconds: crate::stats::Seconds,
}

fn cluster_stats(
    config: &ClusterRenderConfig,
    cluster: &Cluster,
    done: Finished<'_>,
) -> ClusterStats {
    let rc = &config.render;
    let settings = &done.plan.job.settings;
    let topo = cluster.formed.fabric.topology();
    let totals = sum_node_stats(&done.nodes);
    let host_rss = fabric::peak_rss_bytes();
    let render_s = done.seconds.render;
    let mut render = RenderStats {
        scene: rc.scene.to_string(),
        output: rc.output.display().to_string(),
        mode: "cluster".into(),
        width: settings.width,
        height: settings.height,
        spp: settings.spp,
        seed: settings.seed,
        integrator: settings.integrator.to_string(),
        threads: config.render_threads as usize * done.plan.render_nodes.len(),
        triangles: done.scene.triangle_count(),
        chunks: done.scene.chunks.len(),
        shape_bytes: done.scene.shape_bytes,
        texture_tiles: done.scene.tile_count,
        seconds: done.seconds,
        subscreens: done.times.records(&done.nodes, &done.plan.job),
        chunk_bytes: crate::stats::chunk_bytes(done.scene),
        tile_bytes: crate::stats::tile_bytes(done.scene),
        ..Default::default()
    };
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
    ClusterStats {
        render,
        topology: topo.name.clone(),
        topology_file: (!topo.is_preset()).then(|| topo.to_toml()),
        processes: topo.len(),
        transfer: format!("{:?}", config.transfer),
        dma_transport: config.dma_transport.as_str().into(),
        shared_memory_nodes: done
            .nodes
            .iter()
            .filter(|n| n.role == Some(Role::Render) && n.shared_segments > 0)
            .count(),
        cache_percent: config.cache_percent,
        cache_bytes: done.plan.job.cache_bytes,
        demand_via: format!("{:?}", config.demand_via),
        render_threads: config.render_threads,
        subscreen_count: done.subscreens,
        subscreens_split: done.subscreens_split,
        adaptive: config.adaptive,
        order: config.order,
        coherent_rays: done.plan.job.coherent_rays.as_str().into(),
        ask_ahead: done.plan.job.ask_ahead,
        ask_via: done.plan.job.ask_via.as_str().into(),
        requests_via: done.requests_via,
        at_work: config.at_work.to_string(),
        machine_limits: done.plan.machines.clone(),
        link_model: format!("{:?}", topo.model.link),
        time_scale: topo.model.time_scale,
        cluster_peak_rss_bytes: totals.peak_rss_bytes + host_rss,
        host_peak_rss_bytes: host_rss,
        totals,
        nodes: done.nodes,
        members: cluster.formed.members.clone(),
        lost_nodes: done.lost_nodes,
    }
}

/// The log target of machine-readable events (`MAGG_EVENT ...` lines at debug level), which
/// tests and scripts wait for instead of guessing with sleeps: `--log info,magg::event=debug`.
pub const EVENT_TARGET: &str = "magg::event";

/// A lost fork node's share of the scene is rebuilt and its render nodes' work queued again.
fn event_recovered(node: NodeId) {
    tracing::debug!(target: EVENT_TARGET, "MAGG_EVENT recovered node={node}");
}

/// A node's first pixels of a subscreen reached the frame buffer: it is rendering.
fn event_first_pixels(node: NodeId, subscreen: u32) {
    tracing::debug!(target: EVENT_TARGET, "MAGG_EVENT pixels node={node} subscreen={subscreen}");
}

/// Answers the last requests for work, which arrive as render nodes finish: one from each
/// render node in `owed` (live, and not answered when the image was complete). Each node
/// asks once its last subscreen's figures are recorded, so the figures collected next are
/// whole; waiting for exactly those requests, instead of a fixed time, keeps the host from
/// idling after the last node has asked (a fixed 300 ms was most of a small render's
/// overhead). A node the machine's load started late may ask only now, after the image is
/// complete (its figures are then whole too); one that never asks (its rendering thread
/// hung) is waited for 2 s.
async fn drain_requests(cluster: &mut Cluster, f: &fabric::Fabric, mut owed: HashSet<NodeId>) {
    let until = Instant::now() + Duration::from_secs(2);
    while !owed.is_empty() {
        let left = until.saturating_duration_since(Instant::now());
        if left.is_zero() {
            tracing::debug!(
                "{} render nodes did not ask for work again after the image was complete",
                owed.len()
            );
            return;
        }
        match tokio::time::timeout(left, cluster.formed.inbox.recv()).await {
            Ok(Some(Delivery::Frame { frame, via })) => {
                if let Ok(Message::SubscreenRequest { .. }) = frame.message() {
                    owed.remove(&frame.header.sender);
                    refuse_request(f, &frame, via);
                }
            }
            Ok(Some(Delivery::Lost { peer, .. })) => {
                // Gone after the image was complete: nothing of it is needed but its figures,
                // which it can no longer give.
                f.mark_dead(peer);
                owed.remove(&peer);
            }
            Ok(None) | Err(_) => return,
            Ok(Some(_)) => {}
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

    /// Every figure of the totals is the sum of the nodes' (the stats file's `totals` once
    /// showed no chunk walked in place while every render node had walked some).
    #[test]
    fn totals_sum_every_figure() {
        let node = |k: u64| NodeStats {
            node: k as u16,
            subscreens: k as u32,
            rows: k,
            pixels: k,
            samples: k,
            rays: k,
            camera_rays: k,
            secondary_rays: k,
            shadow_rays: k,
            bad_samples: k,
            cache_hits: k,
            cache_misses: k,
            cache_evictions: k,
            cache_peak_bytes: k,
            bytes_fetched_dma: k,
            bytes_fetched_serial: k,
            bytes_fetched_shared: k,
            shared_segments: k as u32,
            bytes_served: k,
            bytes_gbus: k,
            frames_forwarded: k,
            frames_around_mesh: k,
            bytes_forwarded: k,
            busy_s: k as f64,
            waiting_s: k as f64,
            idle_s: k as f64,
            peak_rss_bytes: k,
            peak_private_bytes: k,
            chunks_in_place: k,
            paths_deferred: k,
            deferred_fetches: k,
            share_items_in_segment: k,
            ..NodeStats::default()
        };
        let t = sum_node_stats(&[node(1), node(2)]);
        let mut expected = node(3);
        expected.node = 0;
        assert_eq!(t, expected);
    }
}
