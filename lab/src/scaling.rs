//! `experiment subscreens` (the paper's figure 1.11) and `experiment speedup` (figures 1.12
//! to 1.15): how the rendering time of 80 render nodes depends on the number of subscreens
//! and the cache size, and how `T(1)/T(n)` grows with the number of render nodes.
//!
//! A 2-core machine cannot time 80 processors computing at once, so each figure is made of
//! two kinds of result, labelled as which:
//!
//! * **simulated curves**: one real cluster render is recorded (per subscreen: CPU time and
//!   the chunks and tiles its rays touched), and the simulator (`sim`) replays those costs
//!   on the paper's machine for every point of the figure, at two time scales that bracket
//!   the paper's own ratio of link time to rendering time (see [`paper_time_scales`]), and
//!   beyond the paper to 1000 render nodes;
//! * **measured points**: real renders of the same image on real processes, at a time scale
//!   where the link model's delays dominate computing (so that two cores serving 80 render
//!   nodes do not distort them), each beside the simulator's prediction of the same render
//!   from the recording, with the real per-message costs read off one of them
//!   ([`crate::simulate::measure_overheads`]).
//!
//! Each finding of the paper is checked on the simulated curves at both scales and reported
//! as reproduced or not, with the numbers that decide it.

use std::{
    io::Write,
    path::{Path, PathBuf},
};

use fabric::{Topology, model::LinkModelKind};
use serde::Serialize;
use sim::{Balance, Overheads, SimConfig, Transfer, Workload};

use crate::runs::render_run;

/// The default scene of the scaling and cache experiments: in the repository, with texture
/// tiles and 46k triangles.
pub const DEFAULT_SCENE: &str =
    "tests/data/scenes/khronos/DamagedHelmet/glTF-Binary/DamagedHelmet.glb";

/// The paper's integrator at one sample, in chunks small enough that cache sizes can matter.
pub const PAPER_FLAGS: [&str; 6] = [
    "--spp",
    "1",
    "--integrator",
    "whitted",
    "--chunk-triangles",
    "256",
];

/// What both experiments render and how large they are.
#[derive(Clone, Debug)]
pub struct ScalingConfig {
    pub scene: PathBuf,
    pub width: u32,
    pub height: u32,
    /// Render flags besides the scene, size and cluster (integrator, spp, chunk size).
    pub render_args: Vec<String>,
    /// Subscreens of the recording: at least as many as any simulated division.
    pub record_subscreens: u32,
    /// The time scale of the measured points.
    pub measured_time_scale: f64,
    /// Larger figures: more measured points and every simulated point.
    pub full: bool,
}

impl ScalingConfig {
    /// The small default: DamagedHelmet (in the repository) with the paper's own integrator,
    /// cut into small chunks so that cache sizes matter.
    pub fn small(scene: PathBuf) -> ScalingConfig {
        ScalingConfig {
            scene,
            width: 480,
            height: 270,
            render_args: PAPER_FLAGS.map(String::from).to_vec(),
            record_subscreens: 10000,
            measured_time_scale: 1.0,
            full: false,
        }
    }

    fn image_args(&self) -> Vec<String> {
        [
            vec![
                self.scene.display().to_string(),
                "--width".into(),
                self.width.to_string(),
                "--height".into(),
                self.height.to_string(),
                "--threads".into(),
                "1".into(),
            ],
            self.render_args.clone(),
        ]
        .concat()
    }
}

/// The paper gives no rendering time per pixel. Its processors were T800-20 transputers
/// (INMOS: 10 MIPS, 1.5 MFLOPS peak), and a Whitted pixel of a scene of some thousand shapes
/// behind a box tree takes some thousands to some tens of thousands of floating-point
/// operations: between 2 and 20 ms per pixel. The link model keeps the paper's own times
/// (610 us for an 84-byte packet over one hop). A time scale `s` makes magg's link times
/// `s` times the paper's while its pixels cost what they cost here, so the paper's ratio of
/// link time to pixel time is kept by `s = (magg's CPU time per pixel) / (the paper's)`.
/// Returns the two scales for 20 ms and 2 ms per paper pixel (slow and fast links).
pub fn paper_time_scales(cpu_s_per_pixel: f64) -> [(f64, &'static str); 2] {
    [
        (cpu_s_per_pixel / 20e-3, "paper pixel 20 ms"),
        (cpu_s_per_pixel / 2e-3, "paper pixel 2 ms"),
    ]
}

/// The recorded render the simulated curves replay.
pub struct Recording {
    pub workload: Workload,
    pub json: String,
    pub cpu_s_per_pixel: f64,
}

/// Renders the image once on the 86-process cluster with no delay model, a cache holding
/// the whole scene and `record_subscreens` subscreens, and keeps its records.
pub fn record(
    program: &Path,
    config: &ScalingConfig,
    dir: &Path,
) -> Result<Recording, crate::LabError> {
    let args = [
        config.image_args(),
        [
            "--spawn",
            "magg",
            "--transfer",
            "demand",
            "--cache",
            "100",
            "--subscreens",
        ]
        .map(String::from)
        .to_vec(),
        vec![config.record_subscreens.to_string()],
    ]
    .concat();
    tracing::info!("recording the costs: {}", args.join(" "));
    let stats_path = dir.join("recording.json");
    render_run(program, &args, &dir.join("recording.pfm"), &stats_path)?;
    let json =
        std::fs::read_to_string(&stats_path).map_err(crate::LabError::folder(&stats_path))?;
    let workload =
        Workload::from_stats_json(&json).map_err(crate::simulate::SimulateError::from)?;
    let pixels = (workload.width as f64 * workload.height as f64).max(1.0);
    Ok(Recording {
        cpu_s_per_pixel: workload.cpu_s() / pixels,
        workload,
        json,
    })
}

/// How data reaches the render nodes in one curve.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum Data {
    Batch,
    /// Demand transfer by DMA with a cache of this percent of the scene.
    Dma(f64),
    /// Demand transfer by serial link (through the mesh).
    Serial(f64),
}

impl Data {
    pub fn label(self) -> String {
        match self {
            Data::Batch => "batch".into(),
            Data::Dma(p) => format!("demand {p}%"),
            Data::Serial(p) => format!("demand {p}% by serial link"),
        }
    }

    /// Whether the cache holds the scene's largest item (the real render refuses otherwise).
    fn fits(self, w: &Workload) -> bool {
        match self.transfer(w) {
            Transfer::Batch => true,
            Transfer::Demand { cache_bytes, .. } => cache_bytes >= w.largest_item(),
        }
    }

    fn transfer(self, w: &Workload) -> Transfer {
        match self {
            Data::Batch => Transfer::Batch,
            Data::Dma(p) => Transfer::demand_percent(w, p, protocol::Transfer::Dma),
            Data::Serial(p) => Transfer::demand_percent(w, p, protocol::Transfer::Serial),
        }
    }

    fn render_args(self) -> Vec<String> {
        match self {
            Data::Batch => vec!["--transfer".into(), "batch".into()],
            Data::Dma(p) => vec![
                "--transfer".into(),
                "demand".into(),
                "--cache".into(),
                p.to_string(),
            ],
            Data::Serial(p) => vec![
                "--transfer".into(),
                "demand".into(),
                "--cache".into(),
                p.to_string(),
                "--demand-via".into(),
                "serial".into(),
            ],
        }
    }
}

/// One simulated render: `T` in seconds.
fn simulate(
    w: &Workload,
    topology: &str,
    data: Data,
    subscreens: u32,
    time_scale: f64,
    overheads: Overheads,
) -> Result<f64, crate::LabError> {
    Ok(simulate_full(w, topology, data, subscreens, time_scale, overheads)?.total_s)
}

/// One simulated render, all of it.
fn simulate_full(
    w: &Workload,
    topology: &str,
    data: Data,
    subscreens: u32,
    time_scale: f64,
    overheads: Overheads,
) -> Result<sim::SimResult, crate::LabError> {
    let topology = Topology::resolve(topology).map_err(crate::simulate::SimulateError::from)?;
    let config = SimConfig {
        link: LinkModelKind::Paper,
        time_scale,
        transfer: data.transfer(w),
        balance: Balance::Dynamic { subscreens },
        overheads,
        ..SimConfig::new(topology)
    };
    Ok(sim::simulate(w, &config).map_err(crate::simulate::SimulateError::from)?)
}

/// Bytes the render nodes fetched (MiB) and the share of their time they waited for data.
fn data_cost(r: &sim::SimResult) -> (f64, f64) {
    let bytes = r.bytes.dma + r.bytes.mesh + r.bytes.batch;
    let (wait, all) = r.nodes.iter().fold((0.0, 0.0), |a, n| {
        (a.0 + n.waiting_s, a.1 + n.busy_s + n.waiting_s + n.idle_s)
    });
    (
        bytes as f64 / 1048576.0,
        if all > 0.0 { wait / all } else { 0.0 },
    )
}

/// One simulated render without overheads, as the findings read it.
struct Run {
    scale: f64,
    data: Data,
    topology: String,
    subscreens: u32,
    total_s: f64,
    /// MiB fetched and waiting share ([`data_cost`]).
    cost: (f64, f64),
}

/// Simulated renders kept so that the findings read the curves' own runs instead of
/// simulating them again.
#[derive(Default)]
struct Runs(Vec<Run>);

impl Runs {
    /// The time and data cost of a render, simulated once.
    fn get(
        &mut self,
        w: &Workload,
        topology: &str,
        data: Data,
        subscreens: u32,
        scale: f64,
    ) -> Result<(f64, (f64, f64)), crate::LabError> {
        let hit = self.0.iter().find(|r| {
            r.scale == scale
                && r.data == data
                && r.topology == topology
                && r.subscreens == subscreens
        });
        if let Some(r) = hit {
            return Ok((r.total_s, r.cost));
        }
        let r = simulate_full(w, topology, data, subscreens, scale, Overheads::default())?;
        let run = Run {
            scale,
            data,
            topology: topology.to_string(),
            subscreens,
            total_s: r.total_s,
            cost: data_cost(&r),
        };
        let out = (run.total_s, run.cost);
        self.0.push(run);
        Ok(out)
    }
}

/// A point of a figure.
#[derive(Clone, Debug, Serialize)]
pub struct Point {
    /// `simulated` or `measured`.
    pub kind: &'static str,
    /// What the curve is (cache or transfer), and at which time scale.
    pub curve: String,
    pub time_scale: f64,
    pub x: f64,
    /// Seconds (figure 1.11) or `T(1)/T(n)` (figures 1.12 to 1.15).
    pub y: f64,
    /// For a measured point, the simulator's prediction of the same render.
    pub predicted: Option<f64>,
}

/// One of the paper's findings, checked.
#[derive(Clone, Debug, Serialize)]
pub struct Finding {
    pub quote: &'static str,
    pub holds: bool,
    pub evidence: String,
}

/// What an experiment produced.
#[derive(Clone, Debug, Serialize)]
pub struct ScalingReport {
    pub points: Vec<Point>,
    pub findings: Vec<Finding>,
    pub time_scales: Vec<(f64, String)>,
    pub cpu_s_per_pixel: f64,
    pub overheads: Overheads,
    /// Curves left out, and why.
    pub notes: Vec<String>,
}

/// The cache sizes of `wanted` that hold the scene's largest item, and a note for the
/// others.
fn fitting(w: &Workload, wanted: &[f64], notes: &mut Vec<String>) -> Vec<f64> {
    let (fit, small): (Vec<f64>, Vec<f64>) = wanted.iter().partition(|&&c| Data::Dma(c).fits(w));
    if !small.is_empty() {
        notes.push(format!(
            "Left out: caches of {} of this scene cannot hold its largest item ({} bytes); the real render refuses them too. Findings that need them read as not reproduced.",
            small
                .iter()
                .map(|c| format!("{c}%"))
                .collect::<Vec<_>>()
                .join(", "),
            w.largest_item()
        ));
    }
    fit
}

fn write_csv(
    path: &Path,
    points: &[Point],
    x_name: &str,
    y_name: &str,
) -> Result<(), crate::LabError> {
    let io = crate::LabError::folder(path);
    let mut f = Vec::new();
    writeln!(f, "kind,curve,time_scale,{x_name},{y_name},predicted").map_err(io)?;
    for p in points {
        writeln!(
            f,
            "{},{},{},{},{:.6},{}",
            p.kind,
            p.curve,
            p.time_scale,
            p.x,
            p.y,
            p.predicted.map(|v| format!("{v:.6}")).unwrap_or_default()
        )
        .map_err(io)?;
    }
    scene_io::image_io::write_atomic(path, &f)?;
    Ok(())
}

/// The curves of `points` of one time scale (or the measured ones) as plot series.
fn series(points: &[Point], kind: &str, scale: f64) -> Vec<(String, Vec<(f64, f64)>)> {
    let mut out: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for p in points
        .iter()
        .filter(|p| p.kind == kind && p.time_scale == scale)
    {
        match out.iter_mut().find(|s| s.0 == p.curve) {
            Some(s) => s.1.push((p.x, p.y)),
            None => out.push((p.curve.clone(), vec![(p.x, p.y)])),
        }
    }
    out
}

fn y_at(points: &[Point], curve: &str, scale: f64, x: f64) -> f64 {
    points
        .iter()
        .find(|p| p.kind == "simulated" && p.curve == curve && p.time_scale == scale && p.x == x)
        .map_or(f64::NAN, |p| p.y)
}

/// The real per-message costs of this machine, read off a measured render; none when the
/// render cannot be read.
fn overheads_of(json: &str) -> Overheads {
    crate::simulate::measure_overheads(json)
        .map(|m| m.overheads)
        .unwrap_or_default()
}

/// Renders one measured point and predicts it from the recording.
fn measured_point(
    program: &Path,
    config: &ScalingConfig,
    recording: &Recording,
    dir: &Path,
    name: &str,
    topology: &str,
    data: Data,
    subscreens: u32,
    overheads: &mut Option<Overheads>,
) -> Result<(f64, f64), crate::LabError> {
    let args = [
        config.image_args(),
        vec![
            "--spawn".into(),
            topology.into(),
            "--link-model".into(),
            "paper".into(),
            "--time-scale".into(),
            config.measured_time_scale.to_string(),
            "--subscreens".into(),
            subscreens.to_string(),
        ],
        data.render_args(),
    ]
    .concat();
    tracing::info!("measured point {name}");
    let stats_path = dir.join(format!("{name}.json"));
    let stats = render_run(
        program,
        &args,
        &dir.join(format!("{name}.pfm")),
        &stats_path,
    )?;
    let measured = stats["seconds"]["render"].as_f64().unwrap_or(f64::NAN);
    // The first measured render gives this machine's per-message costs for every prediction.
    let o = *overheads.get_or_insert_with(|| {
        overheads_of(&std::fs::read_to_string(&stats_path).unwrap_or_default())
    });
    let predicted = simulate(
        &recording.workload,
        topology,
        data,
        subscreens,
        config.measured_time_scale,
        o,
    )?;
    Ok((measured, predicted))
}

/// Figure 1.11: rendering time of 80 render nodes against the number of subscreens, one curve
/// per cache size.
pub fn subscreens(
    program: &Path,
    config: &ScalingConfig,
    dir: &Path,
) -> Result<ScalingReport, crate::LabError> {
    // The smallest subscreen count measured is 80, one a render node: an image must have that
    // many pixels (the findings are read at that count).
    if u64::from(config.width) * u64::from(config.height) < 80 {
        return Err(crate::LabError::Settings(format!(
            "an image of {}x{} has fewer pixels than the 80 subscreens measured first",
            config.width, config.height
        )));
    }
    std::fs::create_dir_all(dir).map_err(crate::LabError::folder(dir))?;
    let recording = record(program, config, dir)?;
    let w = &recording.workload;
    let pixels = w.width * w.height;
    let mut notes = Vec::new();
    let caches = fitting(w, &[5.0, 10.0, 20.0, 40.0, 100.0], &mut notes);
    let counts: Vec<u32> = [80, 160, 320, 640, 1280, 2500, 5000, 10000]
        .into_iter()
        .filter(|&n| n <= pixels)
        .collect();
    let scales = paper_time_scales(recording.cpu_s_per_pixel);
    let mut runs = Runs::default();
    let mut points = Vec::new();
    for &(scale, _) in &scales {
        for &c in &caches {
            for &n in &counts {
                points.push(Point {
                    kind: "simulated",
                    curve: Data::Dma(c).label(),
                    time_scale: scale,
                    x: n as f64,
                    y: runs.get(w, "magg", Data::Dma(c), n, scale)?.0,
                    predicted: None,
                });
            }
        }
    }
    // Measured points, with the simulator's prediction of each at the same scale.
    let measured_counts: &[u32] = if config.full {
        &[80, 320, 1280, 5000]
    } else {
        &[80, 640, 5000]
    };
    // The smallest cache that fits, and the whole scene.
    let mut measured_caches = vec![caches[0]];
    if config.full && caches.contains(&20.0) && caches[0] < 20.0 {
        measured_caches.push(20.0);
    }
    if caches[0] < 100.0 {
        measured_caches.push(100.0);
    }
    let mut overheads = None;
    for &c in &measured_caches {
        for &n in measured_counts.iter().filter(|&&n| n <= pixels) {
            let (measured, predicted) = measured_point(
                program,
                config,
                &recording,
                dir,
                &format!("measured-{c}pct-{n}"),
                "magg",
                Data::Dma(c),
                n,
                &mut overheads,
            )?;
            points.push(Point {
                kind: "measured",
                curve: Data::Dma(c).label(),
                time_scale: config.measured_time_scale,
                x: n as f64,
                y: measured,
                predicted: Some(predicted),
            });
        }
    }
    let overheads = overheads.unwrap_or_default();
    // The simulated curves of the measured scale, with this machine's costs.
    for &c in &measured_caches {
        for &n in &counts {
            points.push(Point {
                kind: "simulated",
                curve: format!("{} (this machine's costs)", Data::Dma(c).label()),
                time_scale: config.measured_time_scale,
                x: n as f64,
                y: simulate(
                    w,
                    "magg",
                    Data::Dma(c),
                    n,
                    config.measured_time_scale,
                    overheads,
                )?,
                predicted: None,
            });
        }
    }

    let mut findings = Vec::new();
    for &(scale, why) in &scales {
        let curve = |c: f64| -> Vec<(u32, f64)> {
            counts
                .iter()
                .map(|&n| (n, y_at(&points, &Data::Dma(c).label(), scale, n as f64)))
                .collect()
        };
        let large = curve(100.0);
        let (best_n, best_t) = large
            .iter()
            .copied()
            .fold((0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
        let first = large.first().map_or(f64::NAN, |p| p.1);
        findings.push(Finding {
            quote: "to increase the number of subscreens improves the rendering time until the number of the subscreens exceed about 5000 when the shape cache becomes large",
            holds: best_t < first && (2500..=5000).contains(&best_n),
            evidence: format!(
                "time scale {scale:.3e} ({why}): with a 100% cache the time falls from {first:.3} s at {} subscreens to its least, {best_t:.3} s, at {best_n}",
                counts[0]
            ),
        });
        let past = |c: f64| {
            let t = curve(c);
            let at = |n: u32| t.iter().find(|p| p.0 == n).map_or(f64::NAN, |p| p.1);
            (at(5000), at(10000))
        };
        let (a5, b5) = past(5.0);
        let (a10, b10) = past(10.0);
        findings.push(Finding {
            quote: "In the case, the shape data cache is small such as 5 or 10%, the rendering time is still decreasing when the number of the subscreens exceed about 5000",
            holds: b5 < a5 && b10 < a10,
            evidence: format!(
                "time scale {scale:.3e} ({why}): 5% cache {a5:.3} s at 5000 subscreens, {b5:.3} s at 10000; 10% cache {a10:.3} s, {b10:.3} s"
            ),
        });
        let worst = counts
            .iter()
            .map(|&n| {
                let a = y_at(&points, &Data::Dma(40.0).label(), scale, n as f64);
                let b = y_at(&points, &Data::Dma(100.0).label(), scale, n as f64);
                (a - b).abs() / b
            })
            .fold(0.0, f64::max);
        let n = 5000.min(pixels);
        let (_, (b5, w5)) = runs.get(w, "magg", Data::Dma(5.0), n, scale)?;
        let (_, (b100, w100)) = runs.get(w, "magg", Data::Dma(100.0), n, scale)?;
        findings.push(Finding {
            quote: "the rendering time is almost same when the size of shape data cache is larger than 40%",
            holds: worst < 0.05,
            evidence: format!(
                "time scale {scale:.3e} ({why}): 40% and 100% caches differ by at most {:.1}% over all subscreen counts. Why the caches matter this much: at {n} subscreens the render nodes fetch {b5:.1} MiB with a 5% cache and {b100:.1} MiB with 100%, and wait for data {:.1}% and {:.1}% of their time",
                100.0 * worst,
                100.0 * w5,
                100.0 * w100
            ),
        });
    }
    let report = ScalingReport {
        points,
        findings,
        time_scales: scales.iter().map(|s| (s.0, s.1.to_string())).collect(),
        cpu_s_per_pixel: recording.cpu_s_per_pixel,
        overheads,
        notes,
    };
    write_figure(
        dir,
        config,
        &report,
        &Figure {
            name: "subscreens",
            what: "80 render nodes",
            x: ("subscreens", "subscreens"),
            y: ("seconds", "rendering time (s)"),
            title: "Rendering time against the number of subscreens (the paper's figure 1.11)",
            quote: "\"The relationships between the rendering time of the image and the number of subscreens with 80 NPs are shown in Figure 1.11.\"",
            ideal: None,
        },
    )?;
    Ok(report)
}

/// The topology of `n` render nodes: cards of 4x4 as the paper's (one card for up to 16, in
/// the largest rectangle), the paper's own 80 as `magg`, and `magg1000` for 1000.
pub fn topology_for(n: u32) -> String {
    match n {
        80 => "magg".into(),
        1000 => "magg1000".into(),
        n if n <= 16 => {
            let rows = (1..=4)
                .rev()
                .find(|r| n % r == 0 && n / r <= 4)
                .unwrap_or(1);
            format!("grid:1x{rows}x{}", n / rows)
        }
        n => format!("grid:{}x4x4", n.div_ceil(16)),
    }
}

/// Figures 1.12 to 1.15: `T(1)/T(n)` against the number of render nodes.
pub fn speedup(
    program: &Path,
    config: &ScalingConfig,
    dir: &Path,
) -> Result<ScalingReport, crate::LabError> {
    std::fs::create_dir_all(dir).map_err(crate::LabError::folder(dir))?;
    let recording = record(program, config, dir)?;
    let w = &recording.workload;
    let pixels = w.width * w.height;
    let nodes: Vec<u32> = if config.full {
        vec![1, 2, 4, 8, 16, 32, 48, 64, 80, 160, 320, 640, 1000]
    } else {
        vec![1, 2, 4, 8, 16, 32, 80, 160, 320, 1000]
    };
    // Subscreens: the paper's optimum for 80 nodes, and ten per node beyond it.
    let subscreens_for = |n: u32| (n * 10).clamp(5000, 10000).min(pixels);
    let curves = [
        Data::Batch,
        Data::Dma(40.0),
        Data::Dma(20.0),
        Data::Dma(10.0),
        Data::Dma(5.0),
        Data::Serial(20.0),
    ];
    let mut notes = Vec::new();
    let fit = fitting(w, &[5.0, 10.0, 20.0, 40.0, 100.0], &mut notes);
    let curves: Vec<Data> = curves.into_iter().filter(|d| d.fits(w)).collect();
    let scales = paper_time_scales(recording.cpu_s_per_pixel);
    let mut points = Vec::new();
    let mut times = Vec::new();
    let mut runs = Runs::default();
    for &(scale, _) in &scales {
        for &data in &curves {
            let t1 = runs
                .get(w, &topology_for(1), data, subscreens_for(1), scale)?
                .0;
            for &n in &nodes {
                let t = runs
                    .get(w, &topology_for(n), data, subscreens_for(n), scale)?
                    .0;
                times.push((scale, data, n, t));
                points.push(Point {
                    kind: "simulated",
                    curve: data.label(),
                    time_scale: scale,
                    x: n as f64,
                    y: t1 / t,
                    predicted: None,
                });
            }
        }
    }
    // Measured speedups at a link-dominated scale, up to 16 render nodes.
    let measured_nodes: &[u32] = if config.full {
        &[1, 2, 4, 8, 16]
    } else {
        &[1, 2, 8]
    };
    let measured_data = [Data::Batch, Data::Dma(fit[0])];
    let measured_subscreens = 640.min(pixels);
    let mut overheads = None;
    let mut measured = Vec::new();
    for &data in &measured_data {
        for &n in measured_nodes {
            let name = format!("measured-{}-{n}", data.label().replace(['%', ' '], ""));
            let (m, p) = measured_point(
                program,
                config,
                &recording,
                dir,
                &name,
                &topology_for(n),
                data,
                measured_subscreens,
                &mut overheads,
            )?;
            measured.push((data, n, m, p));
        }
    }
    let overheads = overheads.unwrap_or_default();
    let scale = config.measured_time_scale;
    for &data in &measured_data {
        let (t1, p1) = measured
            .iter()
            .find(|m| m.0 == data && m.1 == 1)
            .map_or((f64::NAN, f64::NAN), |m| (m.2, m.3));
        for m in measured.iter().filter(|m| m.0 == data) {
            points.push(Point {
                kind: "measured",
                curve: data.label(),
                time_scale: scale,
                x: m.1 as f64,
                y: t1 / m.2,
                predicted: Some(p1 / m.3),
            });
        }
        let s1 = simulate(
            w,
            &topology_for(1),
            data,
            measured_subscreens,
            scale,
            overheads,
        )?;
        for &n in nodes.iter().filter(|&&n| n <= 80) {
            let t = simulate(
                w,
                &topology_for(n),
                data,
                measured_subscreens,
                scale,
                overheads,
            )?;
            points.push(Point {
                kind: "simulated",
                curve: format!("{} (this machine's costs)", data.label()),
                time_scale: scale,
                x: n as f64,
                y: s1 / t,
                predicted: None,
            });
        }
    }

    let mut findings = Vec::new();
    for &(scale, why) in &scales {
        let at = |data: Data, n: u32| {
            times
                .iter()
                .find(|t| t.0 == scale && t.1 == data && t.2 == n)
                .map_or(f64::NAN, |t| t.3)
        };
        let sp = |data: Data| at(data, 1) / at(data, 80);
        let (s5, s10, s20) = (sp(Data::Dma(5.0)), sp(Data::Dma(10.0)), sp(Data::Dma(20.0)));
        let (t5, t20) = (at(Data::Dma(5.0), 80), at(Data::Dma(20.0), 80));
        findings.push(Finding {
            quote: "Even though the rendering time is much longer than the batch transfer when the cache size is small, the parallel processing performance becomes more linear and better",
            holds: s5 > s20 && t5 > t20,
            evidence: format!(
                "time scale {scale:.3e} ({why}): at 80 render nodes T(1)/T(80) is {s5:.1} with a 5% cache, {s10:.1} with 10%, {s20:.1} with 20%; T(80) is {t5:.3} s with 5% and {t20:.3} s with 20%"
            ),
        });
        let (s40, sb) = (sp(Data::Dma(40.0)), sp(Data::Batch));
        let n80 = subscreens_for(80);
        let (_, (bb, wb)) = runs.get(w, &topology_for(80), Data::Batch, n80, scale)?;
        let (_, (b40, w40)) = runs.get(w, &topology_for(80), Data::Dma(40.0), n80, scale)?;
        findings.push(Finding {
            quote: "In the case of the size of shape data cache is larger than 40%, the performance is almost same as that of batch transfer",
            holds: ((s40 - sb) / sb).abs() < 0.10,
            evidence: format!(
                "time scale {scale:.3e} ({why}): T(1)/T(80) is {s40:.1} with a 40% cache and {sb:.1} with batch transfer. At 80 render nodes batch transfer moves {bb:.0} MiB (the whole scene to every node, through each card's one DMA bus, before any starts) and the nodes wait {:.0}% of their time; demand with a 40% cache moves {b40:.0} MiB and they wait {:.0}%",
                100.0 * wb,
                100.0 * w40
            ),
        });
        let ss = sp(Data::Serial(20.0));
        findings.push(Finding {
            quote: "the performance is terribly low in the case of the demand data transfer by serial link",
            holds: ss < 0.5 * s20,
            evidence: format!(
                "time scale {scale:.3e} ({why}): T(1)/T(80) with a 20% cache is {ss:.1} by serial link against {s20:.1} by DMA"
            ),
        });
        let s1000 = at(Data::Dma(5.0), 1) / at(Data::Dma(5.0), 1000);
        findings.push(Finding {
            quote: "we will be able to improve the rendering time by increasing the number of NPs",
            holds: at(Data::Dma(5.0), 1000) < at(Data::Dma(5.0), 80),
            evidence: format!(
                "time scale {scale:.3e} ({why}), beyond the paper: with a 5% cache T(1)/T(1000) is {s1000:.1} against {s5:.1} at 80"
            ),
        });
    }
    let report = ScalingReport {
        points,
        findings,
        time_scales: scales.iter().map(|s| (s.0, s.1.to_string())).collect(),
        cpu_s_per_pixel: recording.cpu_s_per_pixel,
        overheads,
        notes,
    };
    let ideal: Vec<(f64, f64)> = nodes.iter().map(|&n| (n as f64, n as f64)).collect();
    write_figure(
        dir,
        config,
        &report,
        &Figure {
            name: "speedup",
            what: "T(1)/T(n)",
            x: ("render_nodes", "render nodes"),
            y: ("speedup", "T(1)/T(n)"),
            title: "Parallel processing performance T(1)/T(n) (the paper's figures 1.12 to 1.15)",
            quote: "\"This performance is defined by T(1)/T(n), here T(n) is the rendering time of a whole image with n NPs.\"",
            ideal: Some(("ideal T(1)/n", &ideal)),
        },
    )?;
    Ok(report)
}

/// What differs between the two experiments' outputs.
struct Figure<'a> {
    /// The files' stem: NAME.csv, NAME-1.png ...
    name: &'static str,
    /// The plots' titles begin with it.
    what: &'static str,
    /// (CSV column, axis label).
    x: (&'static str, &'static str),
    y: (&'static str, &'static str),
    title: &'static str,
    quote: &'static str,
    /// A reference line drawn on each simulated plot.
    ideal: Option<(&'static str, &'a [(f64, f64)])>,
}

/// The CSV, one plot of simulated curves per time scale, one of measured points over their
/// simulated curves, and `report.md`.
fn write_figure(
    dir: &Path,
    config: &ScalingConfig,
    report: &ScalingReport,
    f: &Figure,
) -> Result<(), crate::LabError> {
    write_csv(
        &dir.join(format!("{}.csv", f.name)),
        &report.points,
        f.x.0,
        f.y.0,
    )?;
    let mut pngs = Vec::new();
    for (i, (scale, why)) in report.time_scales.iter().enumerate() {
        let name = format!("{}-{}.png", f.name, i + 1);
        let mut s = series(&report.points, "simulated", *scale);
        if let Some((label, points)) = f.ideal {
            s.push((label.to_string(), points.to_vec()));
        }
        crate::plot::log_log_png(
            &dir.join(&name),
            &format!("{}, simulated, time scale {scale:.2e} ({why})", f.what),
            f.x.1,
            f.y.1,
            &s,
        )?;
        pngs.push((name, format!("simulated, time scale {scale:.2e} ({why})")));
    }
    let scale = config.measured_time_scale;
    let measured = format!("{}-measured.png", f.name);
    crate::plot::log_log_marked_png(
        &dir.join(&measured),
        &format!(
            "{}, measured (crosses) and simulated, time scale {scale}",
            f.what
        ),
        f.x.1,
        f.y.1,
        &series(&report.points, "simulated", scale),
        &series(&report.points, "measured", scale),
    )?;
    pngs.push((
        measured,
        format!("measured on this machine (crosses) and simulated, time scale {scale}"),
    ));
    let text = report_md(f.title, f.quote, config, report, &pngs, f.x.1);
    scene_io::image_io::write_atomic(&dir.join("report.md"), text.as_bytes())?;
    Ok(())
}

/// The findings as the command prints them.
pub fn findings_table(r: &ScalingReport) -> String {
    let mut s = String::from("| finding | reproduced | evidence |\n|---|---|---|\n");
    for f in &r.findings {
        s += &format!(
            "| \"{}\" | {} | {} |\n",
            f.quote,
            if f.holds { "yes" } else { "no" },
            f.evidence
        );
    }
    s
}

/// Measured points beside their predictions.
pub fn measured_table(r: &ScalingReport, x_name: &str) -> String {
    let mut s =
        format!("| curve | {x_name} | measured | predicted | error |\n|---|---:|---:|---:|---:|\n");
    for p in r.points.iter().filter(|p| p.kind == "measured") {
        let predicted = p.predicted.unwrap_or(f64::NAN);
        s += &format!(
            "| {} | {} | {:.3} | {:.3} | {:+.0}% |\n",
            p.curve,
            p.x,
            p.y,
            predicted,
            100.0 * (predicted - p.y) / p.y
        );
    }
    s
}

fn report_md(
    title: &str,
    quote: &str,
    config: &ScalingConfig,
    r: &ScalingReport,
    pngs: &[(String, String)],
    x_name: &str,
) -> String {
    let mut s = format!("# {title}\n\n> {quote}\n\n");
    s += &format!(
        "Scene: `{}`, {}x{}, `{}`. The simulated curves replay one recorded render of this \
         image on the 86-process cluster ({} subscreens, no delay model; `recording.json`), \
         whose rendering threads took {:.2} us of CPU per pixel. Bulk transfers are modelled \
         as flows booking each link of their route.\n\n",
        config.scene.display(),
        config.width,
        config.height,
        config.render_args.join(" "),
        config.record_subscreens,
        r.cpu_s_per_pixel * 1e6,
    );
    s += "**Time scale.** The paper gives no rendering time per pixel. Its processors were \
          T800-20 transputers (10 MIPS, 1.5 MFLOPS); a Whitted pixel behind a box tree takes \
          some thousands to some tens of thousands of floating-point operations: 2 to 20 ms. \
          The link model keeps the paper's times (610 us for one 84-byte packet over one hop), \
          so the paper's ratio of link time to pixel time is kept at time scale \
          `magg's CPU time per pixel / the paper's`. The two scales bracket it:\n\n";
    for (scale, why) in &r.time_scales {
        s += &format!("- {scale:.3e} ({why})\n");
    }
    for note in &r.notes {
        s += &format!("\n{note}\n");
    }
    s += "\n## Findings\n\n";
    s += &findings_table(r);
    s += "\nThe findings are checked on the simulated curves (80 render nodes as the paper; \
          beyond it, up to 1000).\n\n## Figures\n\n";
    for (png, caption) in pngs {
        s += &format!("![{caption}]({png})\n\n*{caption}*\n\n");
    }
    s += &format!(
        "## Measured points\n\nReal renders on this machine's processes, at time scale {} \
         where the link model's delays dominate computing (two cores serve every render \
         node, so compute-bound points would measure the cores, not the method). Each is \
         beside the simulator's prediction of the same render, made from the recording with \
         this machine's real per-message costs (read off the first measured render: start \
         {:.1} ms, {:.0} us per hop, {:.0} us between two nodes' jobs).\n\n{}",
        config.measured_time_scale,
        r.overheads.start_ns as f64 * 1e-6,
        r.overheads.hop_ns as f64 * 1e-3,
        r.overheads.job_stagger_ns as f64 * 1e-3,
        measured_table(r, x_name),
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topologies_have_the_asked_number_of_render_nodes() {
        for n in [1, 2, 4, 8, 16, 32, 48, 64, 80, 160, 320, 640, 1000] {
            let t = Topology::resolve(&topology_for(n)).unwrap();
            assert_eq!(t.render_nodes().len() as u32, n, "{}", topology_for(n));
        }
    }

    #[test]
    fn the_scales_keep_the_papers_ratio() {
        let [(slow, _), (fast, _)] = paper_time_scales(10e-6);
        assert!((slow - 5e-4).abs() < 1e-12);
        assert!((fast - 5e-3).abs() < 1e-12);
    }
}
