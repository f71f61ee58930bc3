//! `magg-host`: renders scenes (in this process, or on a cluster) and runs the benchmarks.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use renderer::{IntegratorKind, PrepareOptions, RenderSettings};

magg::check_cpu_at_start!();

#[derive(Parser)]
#[command(
    name = "magg-host",
    version = magg::BUILD_ID,
    about = "magg: a distributed ray tracer (the host role)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log level filter (error, warn, info, debug, trace), or RUST_LOG syntax.
    #[arg(long, global = true, env = "MAGG_LOG", default_value = "info")]
    log: String,
}

#[derive(Subcommand)]
enum Command {
    /// Render a glTF scene (or the built-in demo scene) to an image.
    Render(RenderArgs),
    /// Measure the renderer core: BVH build, rays per second, samples per second.
    Bench(BenchArgs),
    /// Rerun the paper's experiments on real processes.
    #[command(subcommand)]
    Experiment(ExperimentCmd),
    /// Render every scene of a folder small, on one contact sheet with their names.
    Gallery(GalleryArgs),
    /// Compare an image with a reference: relative MSE and channel means.
    Compare {
        /// The image measured (.png, .exr or .pfm).
        image: PathBuf,
        /// The image it is measured against, of the same size.
        reference: PathBuf,
    },
    /// Predict a render with the simulator from a cluster render's --stats records: by
    /// default the same render (its time beside the measured one), or changed by the flags.
    Simulate(SimulateArgs),
    /// Draw a render's timeline (a row per render node, a bar per subscreen, darker the
    /// more it fetched) and its image tinted by who rendered each subscreen, from its
    /// `--stats` file: STATS.timeline.png and STATS.nodes.png.
    Plot {
        /// The `--stats` file of a render (in one process or on a cluster).
        stats: PathBuf,
        /// Folder for the PNG files (default: the stats file's folder).
        #[arg(short, long)]
        output: Option<PathBuf>,
    },
    /// Run as a fork node (what a spawning host starts; the flags of magg-fork-node).
    #[command(hide = true)]
    ForkNode(magg::NodeArgs),
    /// Run as a render node (what a spawning host starts; the flags of magg-render-node).
    #[command(hide = true)]
    RenderNode(magg::NodeArgs),
}

#[derive(Subcommand)]
enum ExperimentCmd {
    /// Figures 1.5 and 1.6: transfer times by serial link and DMA, and the one-packet formula.
    Links(LinksArgs),
    /// The cluster's cost: the same image in one process and on a cluster (no delay model).
    Overhead(RunArgs),
    /// Bytes fetched, hit rate and time for several shape-cache sizes (paper link model).
    Cache(CacheArgs),
    /// Figure 1.10: busy, waiting and idle time per render node with one subscreen per node
    /// (static), many handed out on request (dynamic), and with adaptive redivision.
    LoadBalance(BalanceArgs),
    /// Run time against error: relMSE against a reference at 1, 2, 4 ... spp, with the peer
    /// renderers' curves from bench/peers when they were run.
    #[command(name = "error")]
    Convergence(ErrorArgs),
    /// The simulator's predictions against real renders: 1 and 2 render nodes of one thread,
    /// and the 86 processes with the paper's link model at its real time scale.
    Validate(ValidateArgs),
    /// Figure 1.11: rendering time of 80 render nodes against the number of subscreens, one
    /// curve per cache size (simulated from a recorded render, with measured points).
    Subscreens(ScalingArgs),
    /// Figures 1.12 to 1.15: T(1)/T(n) against the number of render nodes, batch and demand
    /// transfer (simulated to 1000 render nodes, with measured points).
    Speedup(ScalingArgs),
    /// Every experiment at its default size and one report.md linking them (about 4 to 5
    /// minutes on 2 cores).
    All(AllArgs),
}

#[derive(Args)]
struct AllArgs {
    /// Folder for every experiment's folder and the report [default: out/all].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Only these experiments (comma-separated names).
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
}

#[derive(Args)]
struct ScalingArgs {
    /// Folder for the recording, measured renders, CSV, plots and report.
    #[arg(long)]
    out: Option<PathBuf>,
    /// The scene every run renders.
    #[arg(long, default_value = lab::scaling::DEFAULT_SCENE)]
    scene: PathBuf,
    /// Image width of every run.
    #[arg(long, default_value_t = 480)]
    width: u32,
    /// Image height of every run.
    #[arg(long, default_value_t = 270)]
    height: u32,
    /// Time scale of the measured points (the paper's link times at 1).
    #[arg(long, default_value_t = 1.0)]
    measured_time_scale: f64,
    /// More measured points and simulated points (subscreens: about 2.5 minutes on 2 cores,
    /// speedup: about 5; the defaults take about 1.5 and 2).
    #[arg(long)]
    full: bool,
    /// Render flags of every run besides the scene and size.
    #[arg(last = true)]
    render: Vec<String>,
}

#[derive(Args)]
struct ValidateArgs {
    /// Folder for the images, stats, CSV and report.
    #[arg(long)]
    out: Option<PathBuf>,
    /// The scene of the compute-bound cases (1 and 2 render nodes).
    #[arg(long, default_value = "tests/data/scenes/cornell/cornell.gltf")]
    scene: PathBuf,
    /// Image width of the compute-bound cases.
    #[arg(long, default_value_t = 192)]
    width: u32,
    /// Image height of the compute-bound cases.
    #[arg(long, default_value_t = 192)]
    height: u32,
    /// Samples per pixel of the compute-bound cases.
    #[arg(long, default_value_t = 32)]
    spp: u32,
}

#[derive(Args)]
struct ErrorArgs {
    /// Folder for the images, stats, CSV, plot and report.
    #[arg(long)]
    out: Option<PathBuf>,
    /// The scene the sweep renders.
    #[arg(long, default_value = "tests/data/scenes/cornell/cornell.gltf")]
    scene: PathBuf,
    /// The converged image errors are measured against (same size as the renders).
    #[arg(long, default_value = "tests/data/references/cornell/cornell_ref.exr")]
    reference: PathBuf,
    /// Image width of the sweep's renders.
    #[arg(long, default_value_t = 256)]
    width: u32,
    /// Image height of the sweep's renders.
    #[arg(long, default_value_t = 256)]
    height: u32,
    /// Largest sample count of the sweep (doubling from 1; 1 to 2^30).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=1 << 30))]
    max_spp: u32,
    /// The full sweep, to 4096 spp (about 8 minutes on 2 cores).
    #[arg(long)]
    full: bool,
    /// Results of bench/peers/mitsuba.py to plot beside magg's, when the file exists; the
    /// results of bench/peers/cycles.py are read from the same folder.
    #[arg(long, default_value = "bench/peers/out/mitsuba-results.json")]
    peers: PathBuf,
    /// Further render flags for magg's runs.
    #[arg(last = true)]
    render: Vec<String>,
}

#[derive(Args)]
struct BalanceArgs {
    #[command(flatten)]
    run: RunArgs,
    /// Subscreens of the dynamic and adaptive runs.
    #[arg(long, default_value_t = 640, value_parser = subscreen_count)]
    subscreens: u32,
    /// The full size (when no render flags are given): 480x270 at 16 spp and 2000
    /// subscreens (about 11 s on 2 cores; the default takes about 2 s).
    #[arg(long)]
    full: bool,
}

/// Render arguments passed through to every run, e.g. `-- SCENE --spp 16`.
#[derive(Args)]
struct RunArgs {
    /// Folder for the images, stats and tables.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Cluster flags for the cluster run (default: --spawn magg).
    #[arg(long, allow_hyphen_values = true, default_value = "--spawn magg")]
    cluster: String,
    /// Scene and render flags, as for `magg-host render`.
    #[arg(last = true)]
    render: Vec<String>,
}

#[derive(Args)]
struct CacheArgs {
    #[command(flatten)]
    run: RunArgs,
    /// Cache sizes in percent, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "5,10,20,40,100")]
    caches: Vec<f64>,
}

/// Where a host listening for nodes started by hand, given no secret, keeps the one it
/// generates, for the nodes to read.
const GENERATED_SECRET: &str = "magg-secret";

/// The help heading of the flags only a cluster reads; `render --in-process` says which of
/// them it was given ([`cluster_flags_given`]).
const CLUSTER_HEADING: &str = "Cluster options (not read by --in-process)";

/// Where the cluster comes from: spawned here, or nodes joining from elsewhere.
#[derive(Args, Clone)]
struct ClusterArgs {
    /// Topology to spawn as local processes: magg, magg1000, tiny, grid:CARDSxROWSxCOLS or a TOML file.
    #[arg(long, default_value = "magg")]
    spawn: String,
    /// Instead of spawning, listen here for nodes started by hand (with --topology).
    // Given with --spawn, one of the two was silently ignored (the spawn).
    #[arg(long, conflicts_with = "spawn")]
    listen: Option<String>,
    /// The topology the joining nodes fill (with --listen).
    // Without --listen it was silently ignored: `--topology tiny` spawned 86 processes.
    #[arg(long, requires = "listen")]
    topology: Option<String>,
    #[command(flatten)]
    secret: magg::SecretArgs,
    /// The cluster's name, which every node gives: nodes of another are refused, so two
    /// clusters can share a network [default: the topology file's `cluster_id`, else magg].
    // A default here replaced the file's id, which nodes then had to give: an Option tells
    // a given id from none.
    #[arg(long, env = "MAGG_CLUSTER_ID")]
    cluster_id: Option<String>,
    /// Seconds to wait for the cluster to form.
    #[arg(long, default_value_t = 120, value_parser = magg::wait_seconds)]
    join_timeout: u64,
    /// Log level of spawned nodes.
    #[arg(long, default_value = "warn")]
    node_log: String,
}

impl ClusterArgs {
    fn config(&self) -> Result<host::cluster::ClusterConfig> {
        let (mode, spec) = match &self.listen {
            Some(addr) => (
                host::cluster::ClusterMode::Listen(addr.clone()),
                self.topology.clone().unwrap_or_else(|| "magg".into()),
            ),
            None => (host::cluster::ClusterMode::Spawn, self.spawn.clone()),
        };
        let mut topology = fabric::Topology::resolve(&spec).map_err(anyhow::Error::msg)?;
        if let Some(id) = &self.cluster_id {
            if *id != topology.cluster_id {
                tracing::info!(
                    "cluster id {id:?} (--cluster-id or MAGG_CLUSTER_ID) instead of the topology's {:?}",
                    topology.cluster_id
                );
            }
            topology.cluster_id = id.clone();
        }
        // A secret generated for nodes started by hand goes to a file they can read, once
        // the host listens (`host::cluster::bind`). A file of that name already there is
        // used, not replaced: it is an earlier run's secret, which nodes may hold (or a file
        // of the user's, which the generated secret overwrote).
        let listening = matches!(mode, host::cluster::ClusterMode::Listen(_));
        let earlier = std::path::Path::new(GENERATED_SECRET);
        let (secret, write_secret) = match self.secret.resolve()? {
            Some(s) => (s, None),
            None if listening && earlier.exists() => {
                let s = std::fs::read_to_string(earlier)
                    .map_err(anyhow::Error::from)
                    .and_then(|text| protocol::Secret::new(&text).map_err(anyhow::Error::msg))
                    .with_context(|| {
                        format!(
                            "the cluster secret in {GENERATED_SECRET}, left by an earlier run \
                             (remove the file to have a new one generated)"
                        )
                    })?;
                // Generated, it is readable only by its owner; one that others can read
                // (copied without its mode, or written by hand) gives the cluster away.
                use std::os::unix::fs::PermissionsExt;
                if let Ok(m) = std::fs::metadata(earlier)
                    && m.permissions().mode() & 0o077 != 0
                {
                    tracing::warn!(
                        "{GENERATED_SECRET} can be read by others than you (mode {:o}): \
                         chmod 600 {GENERATED_SECRET}",
                        m.permissions().mode() & 0o777
                    );
                }
                tracing::info!(
                    "using the cluster secret in {GENERATED_SECRET}, left by an earlier run: give nodes --secret-file {GENERATED_SECRET}"
                );
                (s, None)
            }
            None => (
                protocol::Secret::generate(),
                listening.then(|| std::path::PathBuf::from(GENERATED_SECRET)),
            ),
        };
        Ok(host::cluster::ClusterConfig {
            mode,
            topology,
            secret,
            join_timeout: std::time::Duration::from_secs(self.join_timeout),
            node_log: self.node_log.clone(),
            node_program: own_program()?,
            write_secret,
        })
    }
}

#[derive(Args)]
struct LinksArgs {
    #[command(flatten)]
    cluster: ClusterArgs,
    /// Data sizes in bytes, comma-separated (each at most what a frame carries, 64 MiB).
    #[arg(long, value_delimiter = ',', default_value = "640,2560,10240,40960", value_parser = transfer_size)]
    sizes: Vec<u32>,
    /// Transfers per node per size (1 to 10,000).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    count: u32,
    /// Packets per distance for the one-packet formula (1 to 10,000).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    probes: u32,
    /// Multiplies every modelled delay (above 0, at most a million) [default: the topology
    /// file's `[model] time_scale`, else 1].
    #[arg(long, value_parser = time_scale)]
    time_scale: Option<f64>,
    /// Folder for the CSV files and the plot.
    #[arg(long, default_value = "out/links")]
    out: PathBuf,
    /// The full size: sizes 640 B to 80 KiB, 20 transfers per node and size, 100 probes
    /// (about 3 minutes on 2 cores; the default takes about 20 s).
    #[arg(long)]
    full: bool,
}

#[derive(Args)]
struct GalleryArgs {
    /// Folder searched (recursively) for .gltf and .glb files.
    dir: PathBuf,
    /// The contact sheet (PNG).
    #[arg(short, long, default_value = "gallery.png")]
    output: PathBuf,
    /// Side of each picture in pixels, 16 to 1024.
    #[arg(long, default_value_t = 160, value_parser = clap::value_parser!(u32).range(16..=1024))]
    size: u32,
    /// Samples per pixel, 1 to 65536.
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=65536))]
    spp: u32,
    /// path (unbiased path tracing) or whitted (the paper's ray tracer).
    #[arg(long, default_value = "path")]
    integrator: IntegratorKind,
    /// Pictures a row, at least 1 (more than there are pictures make one row).
    #[arg(long, default_value_t = 7, value_parser = clap::value_parser!(u32).range(1..))]
    columns: u32,
}

/// Parses the most triangles of a chunk, 1 to 2^32 - 1: the cluster sends the number to the
/// first fork node in 32 bits, so a larger one would chunk the scene otherwise there than in
/// one process.
fn chunk_size(s: &str) -> Result<usize, String> {
    magg::number_in(s, "triangles", 1, u32::MAX as usize, "")
}

/// A number of subscreens, 1 to a million (the paper's experiments go to 10,000; a count in
/// the billions took the memory of a rectangle each).
fn subscreen_count(s: &str) -> Result<u32, String> {
    magg::number_in(s, "subscreens", 1, 1_000_000, "")
}

/// A data size for `experiment links`: 1 byte to what one frame carries.
fn transfer_size(s: &str) -> Result<u32, String> {
    magg::number_in(s, "bytes", 1, protocol::MAX_DATA, "")
}

/// A multiplier of the modelled delays, above 0 and at most a million (beyond, the delays
/// overflow the clock and vanish).
fn time_scale(s: &str) -> Result<f64, String> {
    let v = magg::number_in(
        s,
        "as a time scale",
        0.0,
        fabric::model::MOST_TIME_SCALE,
        "",
    )?;
    if v == 0.0 {
        return Err("a time scale of 0: give a number above 0".into());
    }
    Ok(v)
}

/// A side of an image a benchmark renders, 1 to a render's limit.
fn image_side(s: &str) -> Result<u32, String> {
    magg::number_in(s, "pixels", 1, renderer::MAX_IMAGE_SIDE, "")
}

/// How often a benchmark measures, 1 to 10,000 (its times are kept for the median).
fn repeats(s: &str) -> Result<usize, String> {
    magg::number_in(s, "repeats", 1, 10_000, "")
}

/// A benchmark's size at most: far larger ones take more memory than a machine has, and
/// aborted on allocation.
const MOST_BENCH_ITEMS: usize = 100_000_000;

fn triangles_to_bench(s: &str) -> Result<usize, String> {
    magg::number_in(s, "triangles", 1, MOST_BENCH_ITEMS, "")
}

fn rays_to_bench(s: &str) -> Result<usize, String> {
    magg::number_in(s, "rays", 1, MOST_BENCH_ITEMS, "")
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Cast the rays of a file into a mesh on one thread, as render does: rays per second
    /// and each ray's hit (formats in the README; bench/peers/embree.py uses it).
    Rays(RaysArgs),
    /// Render every glTF scene under a folder with the path and the Whitted integrator: times,
    /// specular rays per camera ray, and what Whitted's pruning costs on glass scenes.
    Whitted(WhittedArgs),
}

#[derive(Args)]
struct WhittedArgs {
    /// The folder of scenes (searched recursively for .gltf and .glb files); the full sweep
    /// is `../shared/scenes/khronos`.
    #[arg(default_value = "tests/data/scenes/khronos")]
    scenes: PathBuf,
    /// Image width of each scene's render.
    #[arg(long, default_value_t = 320, value_parser = image_side)]
    width: u32,
    /// Image height of each scene's render.
    #[arg(long, default_value_t = 240, value_parser = image_side)]
    height: u32,
    /// Samples per pixel of each scene's render.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..))]
    spp: u32,
    /// Rendering threads (default: one per CPU the process may use).
    #[arg(long, value_parser = magg::thread_count)]
    threads: Option<usize>,
    /// Also write the figures as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Args)]
struct RaysArgs {
    /// A glTF or GLB file (its triangles; materials and cameras do not matter).
    mesh: PathBuf,
    /// Rays: per ray six little-endian f32, origin then unit direction.
    rays: PathBuf,
    /// Write each ray's hit distance here (little-endian f32, +inf on a miss).
    #[arg(long)]
    hits: Option<PathBuf>,
    /// Measurements of each kind (the best and the median are printed), 1 to 10,000.
    #[arg(long, default_value_t = 5, value_parser = repeats)]
    repeat: usize,
    /// Any hit instead of the closest (shadow rays: stop at the first opaque surface).
    #[arg(long)]
    any_hit: bool,
    /// Triangles per chunk of the mesh (the unit render nodes fetch).
    #[arg(long, default_value_t = 4096, value_parser = chunk_size)]
    chunk_triangles: usize,
    /// Also write the figures as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// Without a subcommand: the renderer core's figures (build, rays, samples per second).
#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
struct BenchArgs {
    #[command(subcommand)]
    what: Option<BenchCmd>,
    /// A glTF file to use as the big mesh (default: a procedural mesh).
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Triangles in the procedural mesh (at most 100 million).
    #[arg(long, default_value_t = 1_100_000, value_parser = triangles_to_bench)]
    triangles: usize,
    /// The Cornell box scene, for samples per second [default: the repository's,
    /// tests/data/scenes/cornell/cornell.gltf, skipped where it is not].
    #[arg(long)]
    cornell: Option<PathBuf>,
    /// A textured scene, rendered with and without its textures [default: the repository's
    /// DamagedHelmet, skipped where it is not].
    #[arg(long)]
    textured: Option<PathBuf>,
    /// Rays per measurement (at most 100 million).
    #[arg(long, default_value_t = 1_000_000, value_parser = rays_to_bench)]
    rays: usize,
    /// Rendering threads (default: one per CPU the process may use).
    #[arg(long, value_parser = magg::thread_count)]
    threads: Option<usize>,
    /// Triangles per chunk (the unit render nodes fetch).
    #[arg(long, default_value_t = 4096, value_parser = chunk_size)]
    chunk_triangles: usize,
    /// Also write the figures as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Args)]
struct RenderArgs {
    /// A .gltf or .glb file; the built-in demo scene when absent.
    scene: Option<PathBuf>,
    /// Output image: .png (sRGB, 8-bit), .exr or .pfm (linear float).
    #[arg(short, long, default_value = "magg.png")]
    output: PathBuf,
    /// Render in this one process on all cores (instead of on a cluster).
    #[arg(long, conflicts_with_all = ["spawn", "listen"])]
    in_process: bool,
    /// Continue an interrupted render from its checkpoint `OUTPUT.partial` (on any
    /// cluster, or in one process); the image is the same bytes as an uninterrupted render.
    #[arg(long)]
    resume: bool,
    /// Seconds between checkpoints of a render in progress (`OUTPUT.partial`).
    #[arg(long, default_value_t = 10.0, value_name = "SECONDS", value_parser = magg::fractional_seconds)]
    checkpoint_every: f64,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height; by default from the camera's aspect ratio, else 3/4 of the width (480
    /// for the default 640).
    #[arg(long)]
    height: Option<u32>,
    /// Resolution preset: hdtv (1920x1035, the paper's display), 1080p, 720p, vga (not with
    /// --width or --height, which it would override).
    #[arg(long, conflicts_with_all = ["width", "height"])]
    preset: Option<String>,
    /// Samples per pixel [default: 64; 24 for the built-in demo scene when it is denoised].
    #[arg(long)]
    spp: Option<u32>,
    /// Seed of every pixel's random numbers: the same seed renders the same bytes.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// path (unbiased path tracing) or whitted (the paper's ray tracer).
    #[arg(long, default_value = "path")]
    integrator: IntegratorKind,
    /// Longest path, in bounces [default: 64 for path, 16 for whitted].
    #[arg(long)]
    max_depth: Option<u32>,
    /// Adaptive sampling: stop a pixel once its relative standard error is below this (0: off).
    #[arg(long, default_value_t = 0.0)]
    noise_threshold: f32,
    /// Biased: limit light found by a caustic path (a rough bounce, then mirrors or glass,
    /// then the light) to this value per sample (largest channel), which removes fireflies
    /// along with some caustic light. 0: off, the default for scene files; the built-in demo
    /// scene uses 8 when denoised, else 4.
    #[arg(long)]
    clamp_indirect: Option<f32>,
    /// Biased: filter the finished image with an edge-aware denoiser guided by the albedo,
    /// normals and depth the camera sees (traced by the host). Off by default for scene
    /// files; on for the built-in demo scene unless told otherwise.
    #[arg(long, value_parser = parse_on_off, action = clap::ArgAction::Set)]
    denoise: Option<bool>,
    /// The scene camera to use, by name (default: the first, or an automatic one).
    #[arg(long)]
    camera: Option<String>,
    /// Rendering threads in one process; on a cluster, the host's threads for the
    /// denoiser's guides (default: all cores).
    #[arg(long, value_parser = magg::thread_count)]
    threads: Option<usize>,
    /// Write render statistics as JSON.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Most triangles in one chunk (the unit of shape data moved and cached).
    #[arg(long, default_value_t = 4096, value_parser = chunk_size)]
    chunk_triangles: usize,
    /// Radiance of the world around the scene, the same from every direction: one number
    /// (grey) or R,G,B. By default a sky (1 above, 0.25 below) when the scene has no lights,
    /// else black.
    #[arg(long, value_parser = parse_rgb)]
    environment: Option<glam::Vec3>,
    /// No progress bar or progress lines.
    #[arg(long)]
    quiet: bool,
    // The cluster's flags come last: the heading of a flattened group goes on to every
    // field after it.
    #[command(flatten, next_help_heading = CLUSTER_HEADING)]
    cluster: ClusterArgs,
    /// How render nodes get shape data: demand (fetched into a bounded cache) or batch.
    #[arg(long, default_value = "demand", value_parser = parse_transfer_mode)]
    transfer: protocol::TransferMode,
    /// Cache budget of each render node, in percent of the scene's shape and texture bytes.
    #[arg(long, default_value_t = 100.0)]
    cache: f64,
    /// How demand fetches travel: dma (the direct connection) or serial (through the mesh).
    #[arg(long, default_value = "dma", value_parser = parse_transfer)]
    demand_via: protocol::Transfer,
    /// How DMA reads really travel: auto (through a shared-memory segment when a render node
    /// shares the machine with the fork node, else TCP) or tcp (always a socket, as between
    /// machines). The delay model's timing is the same either way.
    #[arg(long, default_value = "auto", value_parser = parse_dma_transport)]
    dma_transport: protocol::DmaTransport,
    /// About how many subscreens the image is cut into: a grid of rectangles of similar
    /// shape whose count is nearest this (7 gives 6 on a 4:3 image; default: 8 per render
    /// node; at most a million).
    #[arg(long, value_parser = subscreen_count)]
    subscreens: Option<u32>,
    /// Adaptive redivision: idle nodes get the unbegun half of a busy node's subscreen.
    #[arg(long)]
    adaptive: bool,
    /// Which subscreen a render node asking for work gets: plain (the paper's: next in line)
    /// or local (near its last one, so its cache holds what it needs).
    #[arg(long, default_value = "plain")]
    order: host::schedule::Order,
    /// Delay model of the links: none, or paper (the transputer's measured timings)
    /// [default: the topology file's `[model] link`, else none].
    // Defaults here replaced a topology file's own values: an Option tells a given flag
    // from none.
    #[arg(long)]
    link_model: Option<fabric::model::LinkModelKind>,
    /// Multiplies every modelled delay [default: the topology file's `[model] time_scale`,
    /// else 1].
    #[arg(long, allow_negative_numbers = true)]
    time_scale: Option<f64>,
    /// Rendering threads per render node.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=magg::MOST_THREADS as i64))]
    render_threads: u32,
    /// Memory-coherent rays on render nodes: on (a path whose data the cache lacks waits
    /// while others go on; each fetch then serves every path waiting for that item), off
    /// (each miss is fetched at once while the thread waits, as in the paper), or auto (on,
    /// except on a node that reads every card's memory in place through shared memory with
    /// links of no delay model: a miss there copies nothing).
    #[arg(long, default_value = "auto", value_parser = parse_coherent_rays)]
    coherent_rays: protocol::CoherentRays,
    /// Render nodes ask for their next subscreen as they begin one, so that it is there when
    /// they finish (on), or only once they have finished (off, as in the paper).
    #[arg(long, default_value = "on", value_parser = parse_on_off, action = clap::ArgAction::Set)]
    ask_ahead: bool,
    /// How render nodes' requests for work reach the host: auto (over each node's own
    /// connection to the host when --link-model is none, else mesh), mesh (hop by hop through
    /// the render nodes' mesh and the fork nodes, as in the paper) or control (one hop)
    #[arg(long, default_value = "auto", value_parser = parse_ask_via)]
    ask_via: AskViaArg,
    /// How many render nodes of one machine work at once: cpus (as many as the CPUs they
    /// report between them, over --render-threads; the others wait and stand in for a lost
    /// one), all (every node, as in the paper), a number, or auto (cpus, except all with a
    /// link model or with a cache smaller than the scene fetched over sockets, as between
    /// machines, where nodes wait rather than compute).
    #[arg(long, default_value = "auto")]
    at_work: host::schedule::AtWork,
}

/// After a render that ended early: where its finished lines are, if any were kept.
fn resume_hint(output: &std::path::Path) {
    let partial = host::checkpoint::path_for(output);
    if partial.exists() {
        magg::say!(
            "the finished scan lines are kept in {}; the same command with --resume continues the render",
            partial.display()
        );
    }
}

/// This executable: spawned nodes and the lab's whole-render runs start it again.
/// `experiment subscreens` or `speedup`: `run` into `--out` (default `out/NAME`), its findings
/// and measured points printed (`x` names the measured points' axis).
fn scaling(
    a: ScalingArgs,
    name: &str,
    x: &str,
    run: fn(
        &std::path::Path,
        &lab::scaling::ScalingConfig,
        &std::path::Path,
    ) -> Result<lab::scaling::ScalingReport, lab::LabError>,
) -> Result<()> {
    let dir = a.out.clone().unwrap_or_else(|| lab::runs::out_dir(name));
    let r = run(&own_program()?, &scaling_config(a), &dir)?;
    magg::put!("{}", lab::scaling::findings_table(&r));
    magg::put!("{}", lab::scaling::measured_table(&r, x));
    magg::put!("wrote {}/report.md", dir.display());
    Ok(())
}

fn scaling_config(a: ScalingArgs) -> lab::scaling::ScalingConfig {
    let mut c = lab::scaling::ScalingConfig::small(a.scene);
    c.width = a.width;
    c.height = a.height;
    c.measured_time_scale = a.measured_time_scale;
    c.full = a.full;
    if !a.render.is_empty() {
        c.render_args = a.render;
    }
    c.record_subscreens = c.record_subscreens.min(a.width * a.height / 2).max(1);
    c
}

fn own_program() -> Result<PathBuf> {
    std::env::current_exe()
        .context("finding this executable, which spawned nodes and lab runs start")
}

fn parse_rgb(s: &str) -> Result<glam::Vec3, String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("{s:?} is not a number or R,G,B"))?;
    let c = match v[..] {
        [g] => glam::Vec3::splat(g),
        [r, g, b] => glam::Vec3::new(r, g, b),
        _ => return Err(format!("{s:?}: give one number or three (R,G,B)")),
    };
    if !c.is_finite() || c.min_element() < 0.0 {
        return Err(format!("{s:?}: radiance must be finite and not negative"));
    }
    Ok(c)
}

#[derive(Args)]
struct SimulateArgs {
    /// The --stats JSON of a cluster render (with per-subscreen records).
    stats: PathBuf,
    /// Another machine: a preset (magg, magg1000, tiny, grid:CARDSxROWSxCOLS) or a file.
    #[arg(long)]
    topology: Option<String>,
    /// Link delay model: none or paper.
    #[arg(long)]
    link_model: Option<fabric::model::LinkModelKind>,
    /// Multiplies every modelled delay.
    #[arg(long)]
    time_scale: Option<f64>,
    /// demand or batch.
    #[arg(long, value_parser = parse_transfer_mode)]
    transfer: Option<protocol::TransferMode>,
    /// Cache budget of each render node, in percent of the scene's bytes.
    #[arg(long)]
    cache: Option<f64>,
    /// How demand fetches travel: dma or serial.
    #[arg(long, value_parser = parse_transfer)]
    demand_via: Option<protocol::Transfer>,
    /// About this many subscreens, cut as the host cuts them (costs carried over by area; at
    /// most a million).
    #[arg(long, conflicts_with = "static_division", value_parser = subscreen_count)]
    subscreens: Option<u32>,
    /// One subscreen per render node.
    #[arg(long = "static")]
    static_division: bool,
    /// Adaptive redivision on or off.
    #[arg(long)]
    adaptive: Option<bool>,
    /// Multiplies every recorded CPU time (a slower or faster processor).
    #[arg(long)]
    cpu_scale: Option<f64>,
    /// How many render nodes work at once: all, or a number of them [default: as the
    /// recorded render let them, on its own machine; all on another].
    #[arg(long)]
    at_work: Option<host::schedule::AtWork>,
    /// Adds the real costs beyond the models (per message, before the start) read off this
    /// recorded cluster render's stats (the same file, or another render on this machine).
    #[arg(long)]
    overheads_from: Option<PathBuf>,
    /// Also write the whole prediction as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

fn simulate(a: SimulateArgs) -> Result<()> {
    use host::inprocess::{FileUse::*, refuse_same_files};
    refuse_same_files(&[
        ("the recorded statistics", Some(&a.stats), Read),
        ("--overheads-from", a.overheads_from.as_deref(), Read),
        ("the prediction (--json)", a.json.as_deref(), Written),
    ])
    .map_err(anyhow::Error::msg)?;
    let text = std::fs::read_to_string(&a.stats)
        .with_context(|| format!("reading {}", a.stats.display()))?;
    let overrides = lab::simulate::Overrides {
        topology: a.topology,
        link: a.link_model,
        time_scale: a.time_scale,
        transfer: a.transfer,
        cache_percent: a.cache,
        via: a.demand_via,
        subscreens: a.subscreens,
        static_division: a.static_division,
        adaptive: a.adaptive,
        cpu_scale: a.cpu_scale,
        at_work: a.at_work,
        overheads: match &a.overheads_from {
            Some(path) => {
                let from = std::fs::read_to_string(path)
                    .with_context(|| format!("reading {}", path.display()))?;
                let m = lab::simulate::measure_overheads(&from)
                    .with_context(|| format!("measuring overheads in {}", path.display()))?;
                magg::put!(
                    "overheads from {}: {:.1} us a hop, {:.1} ms before the start, {:.1} us between the nodes' starts",
                    path.display(),
                    m.overheads.hop_ns as f64 / 1e3,
                    m.overheads.start_ns as f64 / 1e6,
                    m.overheads.job_stagger_ns as f64 / 1e3
                );
                Some(m.overheads)
            }
            None => None,
        },
    };
    let p = lab::simulate::predict(&text, &overrides)
        .with_context(|| format!("simulating {}", a.stats.display()))?;
    magg::put_raw!("{}", lab::simulate::summary(&p));
    if let Some(path) = a.json {
        let json = serde_json::to_vec_pretty(&p).context("encoding the prediction")?;
        scene_io::image_io::write_atomic(&path, &json)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

fn parse_transfer_mode(s: &str) -> Result<protocol::TransferMode, String> {
    match s {
        "demand" => Ok(protocol::TransferMode::Demand),
        "batch" => Ok(protocol::TransferMode::Batch),
        o => Err(format!("unknown transfer {o:?} (demand or batch)")),
    }
}

fn parse_transfer(s: &str) -> Result<protocol::Transfer, String> {
    match s {
        "dma" => Ok(protocol::Transfer::Dma),
        "serial" => Ok(protocol::Transfer::Serial),
        o => Err(format!("unknown demand transfer {o:?} (dma or serial)")),
    }
}

fn parse_dma_transport(s: &str) -> Result<protocol::DmaTransport, String> {
    match s {
        "auto" => Ok(protocol::DmaTransport::Auto),
        "tcp" => Ok(protocol::DmaTransport::Tcp),
        o => Err(format!("unknown DMA transport {o:?} (auto or tcp)")),
    }
}

/// `--ask-via`: a way, or `auto` (`None`: the host picks by the link model).
#[derive(Clone, Copy, Debug)]
struct AskViaArg(Option<protocol::AskVia>);

fn parse_ask_via(s: &str) -> Result<AskViaArg, String> {
    match s {
        "auto" => Ok(AskViaArg(None)),
        "mesh" => Ok(AskViaArg(Some(protocol::AskVia::Mesh))),
        "control" => Ok(AskViaArg(Some(protocol::AskVia::Control))),
        o => Err(format!(
            "unknown way to ask for work {o:?} (auto, mesh or control)"
        )),
    }
}

fn parse_coherent_rays(s: &str) -> Result<protocol::CoherentRays, String> {
    match s {
        "auto" => Ok(protocol::CoherentRays::Auto),
        "on" => Ok(protocol::CoherentRays::On),
        "off" => Ok(protocol::CoherentRays::Off),
        o => Err(format!("expected auto, on or off, not {o:?}")),
    }
}

fn parse_on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" => Ok(true),
        "off" => Ok(false),
        o => Err(format!("expected on or off, not {o:?}")),
    }
}

/// The built-in demo scene's first picture: denoised, so that 24 samples a pixel do (its
/// relMSE against a 4096-spp unbiased render is about 4.0e-3, against 9.6e-3 for 64 samples
/// as sampled; `bench/first_command.py`).
const DEMO_DENOISED_SPP: u32 = 24;
/// The demo's indirect clamp: its caustics (through the glass sphere and off the mirror onto
/// the walls) are fireflies that unbiased sampling takes minutes to average out. Denoised,
/// a looser clamp is better: the filter takes the noise a tighter one would, and the tighter
/// one's bias (lost caustic light) is what would remain.
const DEMO_CLAMP_INDIRECT: f32 = 4.0;
const DEMO_DENOISED_CLAMP_INDIRECT: f32 = 8.0;
/// Samples per pixel unless told.
const DEFAULT_SPP: u32 = 64;

/// Samples, indirect clamp and denoising as asked, else the defaults: a scene file is
/// rendered as sampled and unbiased; the built-in demo scene's biased defaults are announced.
struct Sampling {
    spp: u32,
    clamp_indirect: f32,
    denoise: bool,
}

fn sampling(args: &RenderArgs) -> Result<Sampling> {
    let demo = args.scene.is_none();
    let denoise = args.denoise.unwrap_or(demo);
    let spp = args.spp.unwrap_or(if demo && denoise {
        DEMO_DENOISED_SPP
    } else {
        DEFAULT_SPP
    });
    let clamp = match args.clamp_indirect {
        Some(c) => c,
        None if !demo => 0.0,
        None if denoise => DEMO_DENOISED_CLAMP_INDIRECT,
        None => DEMO_CLAMP_INDIRECT,
    };
    anyhow::ensure!(
        clamp.is_finite() && clamp >= 0.0,
        "--clamp-indirect must be a number >= 0 (0 turns it off), not {clamp}"
    );
    if demo {
        let mut biased = Vec::new();
        if args.clamp_indirect.is_none() && clamp > 0.0 {
            biased.push(format!(
                "caustic light clamped at {clamp} (hides its fireflies; \
                 --clamp-indirect 0 renders it unbiased)"
            ));
        }
        if args.denoise.is_none() && denoise {
            biased.push(format!(
                "denoised{} (--denoise off renders it as sampled)",
                if args.spp.is_none() {
                    format!(", so {spp} samples a pixel do")
                } else {
                    String::new()
                }
            ));
        }
        if !biased.is_empty() {
            tracing::info!(
                "demo scene, biased for a quick picture: {}",
                biased.join("; ")
            );
        }
    }
    Ok(Sampling {
        spp,
        clamp_indirect: clamp,
        denoise,
    })
}

/// The flags under [`CLUSTER_HEADING`] that this command line gave `render` itself (not
/// through the environment), as typed. A cluster's flags beside `--in-process` did nothing
/// without a word; they are said, not refused: the same command with and without
/// `--in-process` is how a cluster's image is checked against one process's.
fn cluster_flags_given() -> Vec<String> {
    use clap::{CommandFactory, parser::ValueSource};
    let cli = Cli::command();
    let Ok(matches) = cli.clone().try_get_matches_from(std::env::args_os()) else {
        return Vec::new();
    };
    let (Some(("render", given)), Some(render)) =
        (matches.subcommand(), cli.find_subcommand("render"))
    else {
        return Vec::new();
    };
    render
        .get_arguments()
        .filter(|a| a.get_help_heading() == Some(CLUSTER_HEADING))
        .filter(|a| given.value_source(a.get_id().as_str()) == Some(ValueSource::CommandLine))
        .filter_map(|a| Some(format!("--{}", a.get_long()?)))
        .collect()
}

fn render(args: RenderArgs) -> Result<()> {
    if args.in_process {
        let given = cluster_flags_given();
        if !given.is_empty() {
            tracing::warn!(
                "{} only a cluster reads: in one process {} nothing",
                given.join(", "),
                if given.len() == 1 {
                    "it does"
                } else {
                    "they do"
                }
            );
        }
    }
    let (mut width, mut height) = (args.width, args.height);
    if let Some(p) = &args.preset {
        let (w, h) = match p.as_str() {
            "hdtv" => (1920, 1035),
            "1080p" => (1920, 1080),
            "720p" => (1280, 720),
            "vga" => (640, 480),
            other => anyhow::bail!("unknown preset {other:?} (hdtv, 1080p, 720p, vga)"),
        };
        width = w;
        height = Some(h);
    }
    let sampling = sampling(&args)?;
    let settings = RenderSettings {
        width,
        // 4:3, the default size's shape: a fixed 480 made `--width 160` a tall strip.
        height: height.unwrap_or_else(|| ((width as u64 * 3).div_ceil(4) as u32).max(1)),
        spp: sampling.spp,
        seed: args.seed,
        integrator: args.integrator,
        max_depth: args
            .max_depth
            .unwrap_or(args.integrator.default_max_depth()),
        noise_threshold: args.noise_threshold,
        min_spp: 16,
        clamp_indirect: sampling.clamp_indirect,
        ..RenderSettings::default()
    };
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let config = host::RenderConfig {
        scene: match &args.scene {
            Some(p) => host::SceneSource::File(p.clone()),
            None => host::SceneSource::Demo,
        },
        output: args.output.clone(),
        settings,
        height_given: height.is_some(),
        camera: args.camera.clone(),
        threads,
        stats: args.stats.clone(),
        environment: args.environment.map(renderer::light::Environment::uniform),
        prepare: PrepareOptions {
            chunk_triangles: args.chunk_triangles.max(1),
        },
        progress: !args.quiet,
        resume: args.resume,
        checkpoint_interval: std::time::Duration::from_secs_f64(args.checkpoint_every.max(0.0)),
        denoise: sampling.denoise,
    };
    if !args.in_process {
        if !(args.cache > 0.0 && args.cache <= 100.0) {
            anyhow::bail!(
                "--cache must be a percentage above 0 and at most 100, not {}",
                args.cache
            );
        }
        if let Some(scale) = args.time_scale
            && !(scale > 0.0 && scale <= fabric::model::MOST_TIME_SCALE)
        {
            anyhow::bail!(
                "--time-scale must be a number above 0 and at most {}, not {scale:?}",
                fabric::model::MOST_TIME_SCALE,
            );
        }
        let cluster = args
            .cluster
            .config()?
            .with_model(args.link_model, args.time_scale);
        let cfg = host::distributed::ClusterRenderConfig {
            render: config,
            cluster,
            transfer: args.transfer,
            demand_via: args.demand_via,
            dma_transport: args.dma_transport,
            cache_percent: args.cache,
            subscreens: args.subscreens,
            adaptive: args.adaptive,
            order: args.order,
            render_threads: args.render_threads.max(1),
            coherent_rays: args.coherent_rays,
            ask_ahead: args.ask_ahead,
            ask_via: args.ask_via.0,
            at_work: args.at_work,
        };
        let cancel = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        // One thread for the host's networking, as for the nodes': its work is small and
        // comes in bursts from many connections, and a second worker only adds wake-ups on
        // cores the render nodes use (heavy work goes to the blocking pool).
        let rt = magg::node_runtime()?;
        let c = cancel.clone();
        rt.spawn(async move {
            let signal = magg::stop_signal().await;
            tracing::warn!("{signal}: stopping the cluster");
            c.store(true, std::sync::atomic::Ordering::SeqCst);
        });
        let stats = match rt.block_on(host::distributed::render_on_cluster(&cfg, &cancel)) {
            Err(host::distributed::ClusterRenderError::Interrupted) => {
                magg::say!("interrupted; the cluster was stopped and no image was written");
                resume_hint(&args.output);
                std::process::exit(magg::stopped_exit_code());
            }
            Err(e) => {
                let e = anyhow::Error::from(e);
                magg::say!("error: {}", magg::report(&e));
                resume_hint(&args.output);
                std::process::exit(1);
            }
            Ok(stats) => stats,
        };
        print_cluster_summary(&stats);
        return Ok(());
    }
    let stop = std::sync::Arc::new(host::inprocess::Stop::default());
    let s = stop.clone();
    // Ctrl-C or SIGTERM stops the render with its finished lines kept for --resume, or
    // before the first line at once.
    std::thread::spawn(move || {
        if let Ok(rt) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        {
            let signal = rt.block_on(magg::stop_signal());
            if s.request() {
                magg::say!("{signal}: stopped before rendering began; nothing was written");
                std::process::exit(magg::stopped_exit_code());
            }
            tracing::warn!("{signal}: stopping the render");
        }
    });
    let stats = match host::inprocess::render_in_process_until(&config, &stop) {
        Err(e @ host::RenderError::Interrupted { .. }) => {
            magg::say!("{e}");
            std::process::exit(magg::stopped_exit_code());
        }
        r => r?,
    };
    magg::say!(
        "wrote {} ({}x{}, {} spp) in {:.2} s: {:.2} M rays/s, {:.0} samples/s",
        stats.output,
        stats.width,
        stats.height,
        stats.spp,
        stats.seconds.total,
        stats.rays_per_second / 1e6,
        stats.samples_per_second
    );
    Ok(())
}

fn bench_rays(a: RaysArgs) -> Result<()> {
    use host::inprocess::{FileUse::*, refuse_same_files};
    refuse_same_files(&[
        ("the mesh", Some(&a.mesh), Read),
        ("the rays", Some(&a.rays), Read),
        ("the hits (--hits)", a.hits.as_deref(), Written),
        ("the figures (--json)", a.json.as_deref(), Written),
    ])
    .map_err(anyhow::Error::msg)?;
    let cfg = lab::raybench::RaysConfig {
        mesh: a.mesh,
        rays: a.rays,
        hits: a.hits,
        repeat: a.repeat,
        any_hit: a.any_hit,
        chunk_triangles: a.chunk_triangles,
    };
    let r = lab::raybench::run(&cfg, &|m| magg::say!("{m}"))?;
    let kind = if r.any_hit { "any hit" } else { "closest hit" };
    magg::put!(
        "{} triangles, {} chunks: build best {:.3} s, median {:.3} s",
        r.triangles,
        r.chunks,
        r.build_seconds,
        r.build_seconds_median
    );
    magg::put!(
        "{} rays ({kind}), {} hit ({:.2}%)",
        r.rays,
        r.hits,
        100.0 * r.hits as f64 / r.rays.max(1) as f64
    );
    for (name, rate) in [
        ("in-process", &r.in_process),
        ("render node cache", &r.cache),
    ] {
        magg::put!(
            "{name}: best {:.2} M rays/s, median {:.2} M rays/s (of {} repeats)",
            rate.best_mrays,
            rate.median_mrays,
            rate.repeats
        );
    }
    if let Some(p) = a.json {
        scene_io::image_io::write_atomic(&p, &serde_json::to_vec_pretty(&r)?)?;
    }
    Ok(())
}

fn bench_whitted(a: WhittedArgs) -> Result<()> {
    let cfg = lab::whittedbench::WhittedConfig {
        scenes: a.scenes,
        width: a.width,
        height: a.height,
        spp: a.spp,
        threads: a
            .threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())),
    };
    let r = lab::whittedbench::run(&cfg, &|m| magg::say!("{m}"))?;
    magg::put!(
        "{}x{}, {} spp, {} threads",
        cfg.width,
        cfg.height,
        cfg.spp,
        cfg.threads
    );
    magg::put!(
        "| scene | triangles | path (s) | whitted (s) | whitted/path | specular rays a camera ray | pruning relMSE |"
    );
    magg::put!("|---|---:|---:|---:|---:|---:|---:|");
    for row in &r.rows {
        magg::put!(
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.1} | {} |",
            row.scene,
            row.triangles,
            row.path_seconds,
            row.whitted_seconds,
            row.ratio,
            row.specular_rays_per_camera_ray,
            row.pruning_rel_mse
                .map(|e| format!("{e:.2e}"))
                .unwrap_or_else(|| "no glass".into())
        );
    }
    if let Some(worst) = r.rows.iter().max_by(|a, b| a.ratio.total_cmp(&b.ratio)) {
        magg::put!(
            "slowest against the path tracer: {} at {:.2}x ({:.2} s against {:.2} s)",
            worst.scene,
            worst.ratio,
            worst.whitted_seconds,
            worst.path_seconds
        );
    }
    if let Some(worst) = r
        .rows
        .iter()
        .filter_map(|row| row.pruning_rel_mse.map(|e| (row, e)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
    {
        magg::put!(
            "largest pruning error: {} at relMSE {:.2e}",
            worst.0.scene,
            worst.1
        );
    }
    for (name, reason) in &r.refused {
        magg::put!("refused by the loader: {name}: {reason}");
    }
    let h = &r.hostile;
    magg::put!(
        "{} nested glass shells, {}x{}, 1 spp: {:.2} s, {:.1} specular rays a camera ray",
        h.shells,
        h.width,
        h.height,
        h.seconds,
        h.specular_rays_per_camera_ray
    );
    if let Some(p) = a.json {
        scene_io::image_io::write_atomic(&p, &serde_json::to_vec_pretty(&r)?)?;
    }
    Ok(())
}

fn bench(args: BenchArgs) -> Result<()> {
    match args.what {
        Some(BenchCmd::Rays(a)) => return bench_rays(a),
        Some(BenchCmd::Whitted(a)) => return bench_whitted(a),
        None => {}
    }
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    // A scene the user names must be there (one that was not was skipped without a word);
    // the repository's own, the defaults, are skipped where the command runs elsewhere.
    let scene = |given: Option<PathBuf>, default: &str| -> Result<PathBuf> {
        match given {
            Some(p) if !p.is_file() => anyhow::bail!("{}: no such scene file", p.display()),
            Some(p) => Ok(p),
            None => Ok(PathBuf::from(default)),
        }
    };
    let cornell = scene(args.cornell, "tests/data/scenes/cornell/cornell.gltf")?;
    let textured = scene(
        args.textured,
        "tests/data/scenes/khronos/DamagedHelmet/glTF-Binary/DamagedHelmet.glb",
    )?;
    let config = lab::bench::BenchConfig {
        mesh: args.mesh,
        triangles: args.triangles,
        cornell: Some(cornell.clone()),
        textured: Some(textured.clone()),
        rays: args.rays,
        threads,
        chunk_triangles: args.chunk_triangles,
    };
    let r = lab::bench::run(&config).map_err(anyhow::Error::msg)?;
    magg::put!(
        "mesh: {} ({} triangles, {} chunks)",
        r.mesh,
        r.triangles,
        r.chunks
    );
    magg::put!("| figure | value |");
    magg::put!("|---|---|");
    magg::put!(
        "| BVH build (chunks + both levels) | {:.2} s per million triangles |",
        r.build_seconds_per_million
    );
    magg::put!(
        "| primary rays, 1 core | {:.2} M rays/s ({:.0}% hit) |",
        r.primary_rays_per_second / 1e6,
        r.primary_hit_fraction * 100.0
    );
    magg::put!(
        "| incoherent rays, 1 core | {:.2} M rays/s ({:.0}% hit) |",
        r.incoherent_rays_per_second / 1e6,
        r.incoherent_hit_fraction * 100.0
    );
    match r.cornell_samples_per_second {
        Some(s) => magg::put!(
            "| Cornell box path tracing, {} threads | {:.0} samples/s |",
            r.cornell_threads,
            s
        ),
        None => magg::put!(
            "| Cornell box path tracing | skipped: no {} here (give --cornell) |",
            cornell.display()
        ),
    }
    if let (Some(t), Some(u)) = (
        r.textured_samples_per_second,
        r.untextured_samples_per_second,
    ) {
        magg::put!(
            "| textured scene, {} threads: with textures / with constant factors | {:.0} / {:.0} samples/s ({:.2}x) |",
            r.cornell_threads,
            t,
            u,
            u / t
        );
    } else {
        magg::put!(
            "| textured scene | skipped: no {} here (give --textured) |",
            textured.display()
        );
    }
    if let Some(p) = args.json {
        scene_io::image_io::write_atomic(&p, &serde_json::to_vec_pretty(&r)?)?;
    }
    Ok(())
}

fn print_cluster_summary(s: &host::distributed::ClusterStats) {
    let r = &s.render;
    magg::say!(
        "wrote {} ({}x{}, {} spp) on {} processes ({}) in {:.2} s (render {:.2} s): {:.0} samples/s",
        r.output,
        r.width,
        r.height,
        r.spp,
        s.processes,
        s.topology,
        r.seconds.total,
        r.seconds.render,
        r.samples_per_second
    );
    magg::say!(
        "{} subscreens ({} split off), {} transfer, cache {}% ({} bytes a node), link model {} x{}",
        s.subscreen_count,
        s.subscreens_split,
        // As the flags spell them (the stats keep the names they always had).
        s.transfer.to_lowercase(),
        s.cache_percent,
        s.cache_bytes,
        s.link_model.to_lowercase(),
        s.time_scale
    );
    let render: Vec<&protocol::NodeStats> = s
        .nodes
        .iter()
        .filter(|n| n.role == Some(protocol::Role::Render))
        .collect();
    let forks: Vec<&protocol::NodeStats> = s
        .nodes
        .iter()
        .filter(|n| n.role == Some(protocol::Role::Fork))
        .collect();
    let range = |v: Vec<f64>| -> String {
        if v.is_empty() {
            return "-".into();
        }
        let min = v.iter().cloned().fold(f64::INFINITY, f64::min);
        let max = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        format!("{min:.1}/{mean:.1}/{max:.1}")
    };
    magg::say!(
        "{:<13} {:>5} {:>16} {:>16} {:>14} {:>14} {:>22}",
        "",
        "nodes",
        "subscreens",
        "busy s",
        "waiting s",
        "idle s",
        "cache hit/miss/evict"
    );
    magg::say!(
        "{:<13} {:>5} {:>16} {:>16} {:>14} {:>14} {:>22}",
        "render nodes",
        render.len(),
        range(render.iter().map(|n| n.subscreens as f64).collect()),
        range(render.iter().map(|n| n.busy_s).collect()),
        range(render.iter().map(|n| n.waiting_s).collect()),
        range(render.iter().map(|n| n.idle_s).collect()),
        format!(
            "{}/{}/{}",
            s.totals.cache_hits, s.totals.cache_misses, s.totals.cache_evictions
        )
    );
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    magg::say!(
        "{:<13} {:>5} served {:.1} MiB to render nodes, read {:.1} MiB over the G-bus; {} took their share as a segment the first fork node wrote",
        "fork nodes",
        forks.len(),
        mib(forks.iter().map(|n| n.bytes_served).sum()),
        mib(forks.iter().map(|n| n.bytes_gbus).sum()),
        forks
            .iter()
            .filter(|n| n.share_items_in_segment > 0)
            .count()
    );
    magg::say!(
        "render nodes fetched {:.1} MiB (DMA {:.1}, of which {:.1} through shared memory; serial {:.1}); DMA transport {} ({} of {} render nodes on shared memory); {} frames forwarded; peak memory {:.1} MiB in all (per-node figures: --stats)",
        mib(s.totals.bytes_fetched_dma + s.totals.bytes_fetched_serial),
        mib(s.totals.bytes_fetched_dma),
        mib(s.totals.bytes_fetched_shared),
        mib(s.totals.bytes_fetched_serial),
        s.dma_transport,
        s.shared_memory_nodes,
        render.len(),
        s.totals.frames_forwarded,
        mib(s.cluster_peak_rss_bytes)
    );
    let median = |mut v: Vec<u64>| -> u64 {
        v.sort_unstable();
        v.get(v.len() / 2).copied().unwrap_or(0)
    };
    let private: Vec<u64> = render.iter().map(|n| n.peak_private_bytes).collect();
    magg::say!(
        "render nodes' own memory (not shared segments) median {:.1} / max {:.1} MiB for a cache budget of {:.1} MiB; fork nodes' max {:.1} MiB; {} chunks walked in place in shared memory",
        mib(median(private.clone())),
        mib(private.iter().copied().max().unwrap_or(0)),
        mib(s.cache_bytes),
        mib(forks
            .iter()
            .map(|n| n.peak_private_bytes)
            .max()
            .unwrap_or(0)),
        render.iter().map(|n| n.chunks_in_place).sum::<u64>()
    );
    for l in &s.lost_nodes {
        magg::say!(
            "lost {} after {:.1} s: {}; {} subscreens handed on",
            l.who(),
            l.after_s,
            l.reason,
            l.subscreens_reassigned
        );
        if l.role == "fork node" {
            let rows = l.served_rows_after_s.map_or(
                "none of its render nodes sent pixels through another fork node before the end"
                    .into(),
                |s| {
                    format!(
                        "first pixels of its render nodes through another fork node after {s:.3} s"
                    )
                },
            );
            magg::say!(
                "  its share ({} chunks and tiles) rebuilt on the live fork nodes and rendering went on {:.3} s after the loss; {rows}",
                l.items_moved,
                l.recovered_after_s
            );
        }
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

fn experiment(cmd: ExperimentCmd) -> Result<()> {
    match cmd {
        ExperimentCmd::Overhead(a) => {
            let dir = a.out.unwrap_or_else(|| lab::runs::out_dir("overhead"));
            let cluster: Vec<String> = a.cluster.split_whitespace().map(String::from).collect();
            // The small default: the Cornell box (in the repository), about a minute.
            let render = if a.render.is_empty() {
                [
                    "tests/data/scenes/cornell/cornell.gltf",
                    "--width",
                    "256",
                    "--height",
                    "256",
                    "--spp",
                    "64",
                ]
                .map(String::from)
                .to_vec()
            } else {
                a.render
            };
            let r = lab::runs::overhead(&own_program()?, &render, &cluster, &dir)?;
            magg::put!("{}", lab::runs::overhead_table(&r));
            scene_io::image_io::write_atomic(
                &dir.join("overhead.json"),
                &serde_json::to_vec_pretty(&r)?,
            )?;
            Ok(())
        }
        ExperimentCmd::Cache(a) => {
            let dir = a.run.out.unwrap_or_else(|| lab::runs::out_dir("cache"));
            let cluster: Vec<String> = a.run.cluster.split_whitespace().map(String::from).collect();
            // The small default: DamagedHelmet (in the repository) in small chunks, the
            // paper's integrator and link model; every size holds its largest item.
            let render = if a.run.render.is_empty() {
                [
                    &[
                        lab::scaling::DEFAULT_SCENE,
                        "--width",
                        "160",
                        "--height",
                        "120",
                    ][..],
                    &lab::scaling::PAPER_FLAGS,
                    &["--link-model", "paper", "--time-scale", "0.1"],
                ]
                .concat()
                .into_iter()
                .map(String::from)
                .collect()
            } else {
                a.run.render
            };
            let rows = lab::runs::cache_sweep(
                &own_program()?,
                &[render, cluster].concat(),
                &a.caches,
                &dir,
            )?;
            magg::put!("{}", lab::runs::cache_table(&rows));
            magg::put!("wrote {}/cache.csv", dir.display());
            Ok(())
        }
        ExperimentCmd::LoadBalance(a) => {
            let dir = a
                .run
                .out
                .unwrap_or_else(|| lab::runs::out_dir("load-balance"));
            let cluster: Vec<String> = a.run.cluster.split_whitespace().map(String::from).collect();
            // The small default: the demo scene, small enough for a few minutes on 2 cores.
            let (render, subscreens) = match (a.run.render.is_empty(), a.full) {
                (true, false) => (
                    ["--width", "160", "--height", "120", "--spp", "16"]
                        .map(String::from)
                        .to_vec(),
                    a.subscreens,
                ),
                (true, true) => (
                    ["--width", "480", "--height", "270", "--spp", "16"]
                        .map(String::from)
                        .to_vec(),
                    2000,
                ),
                (false, _) => (a.run.render, a.subscreens),
            };
            let r =
                lab::balance::load_balance(&own_program()?, &render, &cluster, subscreens, &dir)?;
            magg::put!("{}", lab::balance::table(&r));
            magg::put!("wrote {}/report.md", dir.display());
            Ok(())
        }
        ExperimentCmd::Convergence(a) => {
            let dir = a.out.unwrap_or_else(|| lab::runs::out_dir("error"));
            let config = lab::convergence::ErrorConfig {
                scene: a.scene,
                reference: a.reference,
                width: a.width,
                height: a.height,
                max_spp: if a.full { 4096 } else { a.max_spp },
                render_args: a.render,
                peers: Some(a.peers),
            };
            let r = lab::convergence::error_sweep(&own_program()?, &config, &dir)?;
            magg::put!("{}", lab::convergence::table(&r));
            magg::put!("wrote {}/report.md", dir.display());
            Ok(())
        }
        ExperimentCmd::Subscreens(a) | ExperimentCmd::Speedup(a) if !a.scene.is_file() => {
            anyhow::bail!("{}: no such scene file", a.scene.display())
        }
        ExperimentCmd::Subscreens(a) => {
            scaling(a, "subscreens", "subscreens", lab::scaling::subscreens)
        }
        ExperimentCmd::Speedup(a) => scaling(a, "speedup", "render nodes", lab::scaling::speedup),
        ExperimentCmd::All(a) => {
            let dir = a.out.unwrap_or_else(lab::all::default_dir);
            let results = lab::all::all(&own_program()?, &dir, &a.only)?;
            for r in &results {
                magg::put!(
                    "{:<14} {:>6.0} s  {}",
                    r.name,
                    r.seconds,
                    if r.ok { "ok" } else { "FAILED" }
                );
            }
            magg::put!("wrote {}/report.md", dir.display());
            if results.iter().any(|r| !r.ok) {
                anyhow::bail!("some experiments failed; their output is in the report");
            }
            Ok(())
        }
        ExperimentCmd::Validate(a) => {
            let dir = a.out.unwrap_or_else(|| lab::runs::out_dir("validate"));
            let rows = lab::validate::validate(
                &own_program()?,
                &a.scene,
                (a.width, a.height, a.spp),
                &dir,
            )?;
            magg::put!("{}", lab::validate::table(&rows));
            magg::put!("wrote {}/report.md", dir.display());
            Ok(())
        }
        ExperimentCmd::Links(args) => {
            let cluster = args.cluster.config()?.with_model(None, args.time_scale);
            let (sizes, count, probes) = if args.full {
                ((0..8).map(|i| 640u32 << i).collect(), 20, 100)
            } else {
                (args.sizes, args.count, args.probes)
            };
            let config = lab::experiment::LinksConfig {
                cluster,
                sizes,
                count,
                probes,
                out_dir: args.out.clone(),
            };
            let report =
                runtime()?.block_on(lab::experiment::links(&config, &|m| tracing::info!("{m}")))?;
            let tables = lab::experiment::tables(&report);
            magg::put!("{tables}");
            lab::all::write_links_report(&args.out, &tables)?;
            magg::put!(
                "wrote {0}/one_way.csv, {0}/transfers.csv, {0}/links.json, {0}/fig1.5-one-node.png, {0}/fig1.6-many-nodes.png and {0}/report.md",
                args.out.display()
            );
            Ok(())
        }
    }
}

fn main() {
    let cli = magg::parse_args::<Cli>();
    magg::init_logging(&cli.log);
    let result = match cli.command {
        Command::Render(args) => render(args),
        Command::Bench(args) => bench(args),
        Command::Gallery(a) => (|| {
            host::inprocess::check_output(&a.output)?;
            let c = lab::gallery::GalleryConfig {
                dir: a.dir,
                output: a.output.clone(),
                size: a.size,
                spp: a.spp,
                integrator: a.integrator,
                columns: a.columns,
                threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            };
            let entries = lab::gallery::gallery(&c, &|f| tracing::info!("{f}"))
                .map_err(anyhow::Error::msg)?;
            let failed = entries.iter().filter(|e| e.pixels.is_none()).count();
            let bad: u64 = entries.iter().map(|e| e.bad_samples).sum();
            magg::say!(
                "wrote {} ({} scenes, {failed} not rendered, {bad} NaN or infinite samples)",
                a.output.display(),
                entries.len()
            );
            for e in entries.iter().filter(|e| e.pixels.is_none()) {
                magg::say!("  {}: {}", e.name, e.note);
            }
            Ok(())
        })(),
        Command::Experiment(cmd) => experiment(cmd),
        Command::Simulate(args) => simulate(args),
        Command::ForkNode(node) => magg::node_main(protocol::Role::Fork, &node),
        Command::RenderNode(node) => magg::node_main(protocol::Role::Render, &node),
        Command::Plot { stats, output } => (|| {
            let plots = lab::timeline::plot(&stats, output.as_deref())?;
            magg::put!("{}", plots.timeline.display());
            magg::put!("{}", plots.tinted.display());
            Ok(())
        })(),
        Command::Compare { image, reference } => (|| {
            // Its errors name the file already.
            let a = scene_io::read_image(&image)?;
            let b = scene_io::read_image(&reference)?;
            // A NaN or infinite value makes every figure NaN or infinite, which read as
            // figures (relMSE NaN, exit 0): say which image holds them instead.
            for (path, img) in [(&image, &a), (&reference, &b)] {
                let bad = img
                    .pixels
                    .iter()
                    .flatten()
                    .filter(|v| !v.is_finite())
                    .count();
                if bad > 0 {
                    anyhow::bail!(
                        "{}: {bad} pixel values are not finite numbers (NaN or infinite): \
                         no error can be measured",
                        path.display()
                    );
                }
            }
            let c = lab::compare::compare(&a, &b).map_err(anyhow::Error::msg)?;
            let mut text = format!("relMSE {:.6e}\n", c.rel_mse);
            for (i, ch) in ["R", "G", "B"].iter().enumerate() {
                // Against a reference mean of 0 no relative difference exists (it said
                // +0.000% for 0.5 against 0).
                let diff = if c.mean_b[i] == 0.0 && c.mean_a[i] != 0.0 {
                    "the reference's mean is 0".to_string()
                } else {
                    format!("{:+.3}%", c.mean_rel_diff[i] * 100.0)
                };
                text += &format!(
                    "mean {ch}: {:.5} vs {:.5} ({diff})\n",
                    c.mean_a[i], c.mean_b[i]
                );
            }
            magg::put_raw!("{text}");
            Ok(())
        })(),
    };
    if let Err(e) = result {
        magg::say!("error: {}", magg::report(&e));
        std::process::exit(1);
    }
    if magg::stdout_failed() {
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// Every argument of every subcommand, with the command path it belongs to and whether
    /// a user sees it (neither it nor a command above it hidden).
    fn every_argument() -> Vec<(String, clap::Arg, bool)> {
        fn walk(
            cmd: &clap::Command,
            path: &str,
            shown: bool,
            out: &mut Vec<(String, clap::Arg, bool)>,
        ) {
            for arg in cmd.get_arguments() {
                out.push((path.to_string(), arg.clone(), shown && !arg.is_hide_set()));
            }
            for sub in cmd.get_subcommands() {
                let path = format!("{path} {}", sub.get_name());
                walk(sub, &path, shown && !sub.is_hide_set(), out);
            }
        }
        let mut out = Vec::new();
        walk(&Cli::command(), "magg-host", true, &mut out);
        out
    }

    /// Every flag and argument says in its help what it is (a dozen said nothing but their
    /// name).
    #[test]
    fn every_argument_has_help() {
        let missing: Vec<String> = every_argument()
            .into_iter()
            .filter(|(_, arg, shown)| {
                let builtin = matches!(arg.get_id().as_str(), "help" | "version");
                *shown && !builtin && arg.get_help().is_none()
            })
            .map(|(path, arg, _)| format!("{path} {}", arg.get_id()))
            .collect();
        assert!(missing.is_empty(), "without help: {missing:?}");
    }

    /// A list flag's default is shown in its help as it is typed: given as several values
    /// it showed `[default: 5 10 20 40 100]`, which the flag (comma-separated) refused.
    #[test]
    fn list_defaults_are_shown_as_they_are_typed() {
        let mut seen = 0;
        for (path, arg, _) in every_argument() {
            if arg.get_value_delimiter().is_some() && !arg.get_default_values().is_empty() {
                seen += 1;
                assert_eq!(
                    arg.get_default_values().len(),
                    1,
                    "{path} --{}: give the default as one comma-separated string",
                    arg.get_id()
                );
            }
        }
        Cli::command().debug_assert();
        assert!(
            seen >= 2,
            "the list flags with defaults were found ({seen})"
        );
        let typed = |extra: &[&str]| {
            let args = [&["magg-host", "experiment", "cache"][..], extra].concat();
            match Cli::try_parse_from(args).unwrap().command {
                Command::Experiment(ExperimentCmd::Cache(a)) => a.caches,
                _ => unreachable!(),
            }
        };
        assert_eq!(typed(&[]), typed(&["--caches", "5,10,20,40,100"]));
    }
}
