//! `magg-host simulate STATS.json`: the simulator run on a real render's own records, its
//! prediction printed beside the render time the host measured.
//!
//! By default the simulation takes every setting from the stats file (topology, link model
//! and time scale, transfer, cache size, adaptive redivision, the recorded subscreens), so
//! that prediction and measurement are of the same render: that is how the simulator is
//! validated. Any setting can be overridden, to ask what the same costs would take on
//! another machine or under another policy.

use fabric::{Topology, model::LinkModelKind};
use host::schedule::AtWork;
use protocol::TransferMode;
use serde::{Deserialize, Serialize};
use sim::{Balance, Machine, Overheads, SimConfig, SimResult, Transfer, Workload};

/// What to change from the recorded render; `None` keeps the recorded setting.
#[derive(Clone, Debug, Default)]
pub struct Overrides {
    pub topology: Option<String>,
    pub link: Option<LinkModelKind>,
    pub time_scale: Option<f64>,
    pub transfer: Option<TransferMode>,
    pub cache_percent: Option<f64>,
    pub via: Option<protocol::Transfer>,
    /// About this many subscreens instead of the recorded ones.
    pub subscreens: Option<u32>,
    /// One subscreen per render node.
    pub static_division: bool,
    pub adaptive: Option<bool>,
    /// Multiplies every recorded CPU time.
    pub cpu_scale: Option<f64>,
    /// How many render nodes work at once: `All`, or `Count(n)` of all the render nodes
    /// (one machine). `None`: the recorded render's limits on its own machine, none on
    /// another.
    pub at_work: Option<AtWork>,
    /// The real costs beyond the models (see [`measure_overheads`]); none by default. They
    /// describe the machine the processes ran on, not the render, so giving them still
    /// compares the prediction with the recorded render's time.
    pub overheads: Option<Overheads>,
}

/// The settings of the recorded render, as its stats file states them.
#[derive(Deserialize, Default)]
struct Recorded {
    topology: Option<String>,
    /// A topology that is no preset, whole (a topology file's).
    topology_file: Option<String>,
    link_model: Option<String>,
    time_scale: Option<f64>,
    transfer: Option<String>,
    cache_percent: Option<f64>,
    adaptive: Option<bool>,
    demand_via: Option<String>,
    render_threads: Option<u32>,
    /// `--at-work` as asked for, and the limits it came to.
    at_work: Option<String>,
    #[serde(default)]
    machine_limits: Vec<Machine>,
    #[serde(default)]
    seconds: RecordedSeconds,
    #[serde(default)]
    subscreens: serde_json::Value,
    #[serde(default)]
    nodes: Vec<RecordedNode>,
}

#[derive(Deserialize, Default)]
struct RecordedNode {
    role: Option<String>,
    /// Rendering, by the clock.
    busy_s: Option<f64>,
}

#[derive(Deserialize, Default)]
struct RecordedSeconds {
    render: Option<f64>,
}

/// Why a simulation of a stats file could not run.
#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error(transparent)]
    Workload(#[from] sim::WorkloadError),
    #[error(transparent)]
    Sim(#[from] sim::SimError),
    #[error(transparent)]
    Topology(#[from] fabric::topology::TopologyError),
    #[error(
        "the stats file does not say which {0} the render used (an in-process render?); give it with --{0}"
    )]
    Missing(&'static str),
    #[error(
        "the stats file's {name} {value:?} is not one the simulator knows; give it with --{name}"
    )]
    Unknown { name: &'static str, value: String },
    #[error("a cache of {0}%: give a percentage above 0 and at most 100")]
    Cache(f64),
    #[error(
        "--at-work {0}: the simulator knows no machine's CPUs; give all or a number of render nodes"
    )]
    AtWork(AtWork),
    #[error(
        "a subscreen record names node {node}, which is not a render node of topology {topology}"
    )]
    NotARenderNode {
        node: protocol::NodeId,
        topology: String,
    },
}

/// A prediction beside the measurement, with the settings it was made under.
#[derive(Clone, Debug, Serialize)]
pub struct Prediction {
    pub topology: String,
    /// The machine as it was named: what `--topology` gave (a preset or a topology file's
    /// path), else the recorded render's topology name (a preset's, or a topology file's own
    /// name, whose machine the stats keep whole).
    pub topology_name: String,
    pub link_model: LinkModelKind,
    pub time_scale: f64,
    pub transfer: String,
    pub subscreens: String,
    pub adaptive: bool,
    pub cpu_scale: f64,
    /// Render nodes that share a machine and how many of them worked at once (none: every
    /// render node had a processor of its own).
    pub machine_limits: Vec<Machine>,
    /// The host's render time in the stats file, when the simulated render is that render.
    pub measured_s: Option<f64>,
    pub predicted_s: f64,
    /// (predicted - measured) / measured, in percent.
    pub error_percent: Option<f64>,
    /// Where the prediction is of a different render than the recorded one.
    pub notes: Vec<String>,
    pub result: SimResult,
}

/// The machine to simulate: `asked` (a preset or a topology file) if given, else the
/// recorded render's (a preset by name, or the whole topology a file gave).
fn topology_of(recorded: &Recorded, asked: Option<&str>) -> Result<Topology, SimulateError> {
    Ok(match (asked, &recorded.topology_file) {
        (Some(spec), _) => Topology::resolve(spec)?,
        (None, Some(file)) => Topology::from_toml(file)?,
        (None, None) => Topology::resolve(
            recorded
                .topology
                .as_deref()
                .ok_or(SimulateError::Missing("topology"))?,
        )?,
    })
}

/// Simulates the render a stats file describes, with `overrides` applied.
pub fn predict(stats_json: &str, overrides: &Overrides) -> Result<Prediction, SimulateError> {
    predict_on(stats_json, overrides).map(|(prediction, _)| prediction)
}

/// [`predict`], and the machine it simulated.
fn predict_on(
    stats_json: &str,
    overrides: &Overrides,
) -> Result<(Prediction, Topology), SimulateError> {
    let workload = Workload::from_stats_json(stats_json)?;
    let recorded: Recorded = serde_json::from_str(stats_json).unwrap_or_default();
    let topology = topology_of(&recorded, overrides.topology.as_deref())?;
    let topology_name = overrides
        .topology
        .clone()
        .unwrap_or_else(|| topology.name.clone());
    // A topology file given here is a machine with its own `[model]`: its link model and
    // time scale hold as they would for `render --spawn FILE` (they gave way to the recorded
    // render's). A preset's are defaults, not its own, so the recorded ones carry over.
    let own_model = overrides
        .topology
        .as_deref()
        .is_some_and(|spec| Topology::preset(spec).is_err());
    let link = match (overrides.link, recorded.link_model.as_deref()) {
        (Some(l), _) => l,
        (None, _) if own_model => topology.model.link,
        (None, Some(name)) => name
            .to_lowercase()
            .parse()
            .map_err(|_| SimulateError::Unknown {
                name: "link-model",
                value: name.into(),
            })?,
        (None, None) => topology.model.link,
    };
    let time_scale = overrides
        .time_scale
        .or(recorded.time_scale.filter(|_| !own_model))
        .unwrap_or(topology.model.time_scale);
    let mode = match (overrides.transfer, recorded.transfer.as_deref()) {
        (Some(t), _) => t,
        (None, Some(name)) => match name.to_lowercase().as_str() {
            "batch" => TransferMode::Batch,
            "demand" => TransferMode::Demand,
            _ => {
                return Err(SimulateError::Unknown {
                    name: "transfer",
                    value: name.into(),
                });
            }
        },
        (None, None) => return Err(SimulateError::Missing("transfer")),
    };
    // The file says how demand fetches travelled; an older one only per record, where the
    // mesh means serial link.
    let recorded_via = match recorded.demand_via.as_deref().map(str::to_lowercase) {
        Some(v) if v == "serial" => Some(protocol::Transfer::Serial),
        Some(v) if v == "dma" => Some(protocol::Transfer::Dma),
        Some(_) => None,
        None => recorded
            .subscreens
            .as_array()
            .is_some_and(|s| {
                s.iter()
                    .any(|r| r.get("fetched_via").and_then(|v| v.as_str()) == Some("mesh"))
            })
            .then_some(protocol::Transfer::Serial),
    };
    let via = overrides
        .via
        .or(recorded_via)
        .unwrap_or(protocol::Transfer::Dma);
    let (transfer, transfer_name) = match mode {
        TransferMode::Batch => (Transfer::Batch, "batch".to_string()),
        TransferMode::Demand => {
            let percent = overrides
                .cache_percent
                .or(recorded.cache_percent)
                .ok_or(SimulateError::Missing("cache"))?;
            // As render takes it: a percentage above 0 and at most 100.
            if !(percent > 0.0 && percent <= 100.0) {
                return Err(SimulateError::Cache(percent));
            }
            (
                Transfer::demand_percent(&workload, percent, via),
                format!("demand by {via:?}, cache {percent}%").to_lowercase(),
            )
        }
    };
    let (balance, subscreens) = match (overrides.static_division, overrides.subscreens) {
        (true, _) => (Balance::Static, "one per render node".to_string()),
        (false, Some(n)) => (Balance::Dynamic { subscreens: n }, format!("about {n}")),
        (false, None) => (
            Balance::AsRecorded,
            format!("{} as recorded", workload.subscreens.len()),
        ),
    };
    let adaptive = overrides.adaptive.or(recorded.adaptive).unwrap_or(false);
    let cpu_scale = overrides.cpu_scale.unwrap_or(1.0);
    let mut notes = Vec::new();
    // The recorded render let only so many of its render nodes work at once where they
    // shared a machine's few CPUs (`machine_limits`); left out, the replay gave work to all
    // 80 of a laptop's nodes and predicted a fortieth of the time.
    let machines = match overrides.at_work {
        None if overrides.topology.is_none() => {
            let changes_auto = overrides.link.is_some()
                || overrides.transfer.is_some()
                || overrides.cache_percent.is_some()
                || overrides.via.is_some();
            if !recorded.machine_limits.is_empty()
                && changes_auto
                && recorded.at_work.as_deref() == Some("auto")
            {
                notes.push(format!(
                    "the recorded render's limit ({}) is kept; --at-work auto chose it for the recorded settings, and the host might choose another for these (--at-work all or a number sets it)",
                    at_work_text(&recorded.machine_limits)
                ));
            }
            recorded.machine_limits.clone()
        }
        None => {
            if !recorded.machine_limits.is_empty() {
                notes.push(format!(
                    "the recorded render's limit ({}) is of its own machine; on this one every render node works at once (--at-work a number limits them)",
                    at_work_text(&recorded.machine_limits)
                ));
            }
            Vec::new()
        }
        Some(AtWork::All) => Vec::new(),
        Some(AtWork::Count(n)) => {
            let nodes = topology.render_nodes();
            if nodes.len() > n as usize {
                vec![Machine {
                    nodes,
                    at_work: n as usize,
                }]
            } else {
                Vec::new()
            }
        }
        Some(other) => return Err(SimulateError::AtWork(other)),
    };
    let config = SimConfig {
        link,
        time_scale,
        transfer,
        balance,
        adaptive,
        cpu_scale,
        overheads: overrides.overheads.unwrap_or_default(),
        machines: machines.clone(),
        ..SimConfig::new(topology)
    };
    let result = sim::simulate(&workload, &config)?;
    // The measurement is of the same render only when nothing that changes it was changed.
    let same_render = overrides.topology.is_none()
        && overrides.link.is_none()
        && overrides.time_scale.is_none()
        && overrides.transfer.is_none()
        && overrides.cache_percent.is_none()
        && overrides.via.is_none()
        && overrides.subscreens.is_none()
        && !overrides.static_division
        && overrides.adaptive.is_none()
        && overrides.cpu_scale.is_none()
        && overrides.at_work.is_none();
    let measured_s = recorded.seconds.render.filter(|_| same_render);
    if let Some(threads) = recorded.render_threads.filter(|&t| t > 1) {
        notes.push(format!(
            "the render ran {threads} rendering threads per render node; the simulator models one, so it predicts a render of one thread per node"
        ));
    } else if let Some(note) = cpus_shared(&recorded).filter(|_| overrides.cpu_scale.is_none()) {
        notes.push(note);
    }
    let predicted_s = result.total_s;
    let prediction = Prediction {
        topology: config.topology.summary(),
        topology_name,
        link_model: link,
        time_scale,
        transfer: transfer_name,
        subscreens,
        adaptive,
        cpu_scale,
        machine_limits: machines,
        measured_s,
        predicted_s,
        error_percent: measured_s
            .filter(|&m| m > 0.0)
            .map(|m| (predicted_s - m) / m * 100.0),
        notes,
        result,
    };
    Ok((prediction, config.topology))
}

/// A note when the render nodes rendered markedly longer by the clock than on the CPU: other
/// processes (the host's, or anyone's on a shared machine) took part of their CPUs, which a
/// replay of CPU times cannot know of. Of one rendering thread a node only, where the clock
/// and the CPU time are of the same thread.
fn cpus_shared(recorded: &Recorded) -> Option<String> {
    let busy: f64 = recorded
        .nodes
        .iter()
        .filter(|n| n.role.as_deref() == Some("Render"))
        .filter_map(|n| n.busy_s)
        .sum();
    let cpu: f64 = recorded
        .subscreens
        .as_array()?
        .iter()
        .filter_map(|r| r.get("cpu_s").and_then(|c| c.as_f64()))
        .sum();
    let ratio = busy / cpu;
    // Under a tenth more is the noise of a quiet machine.
    (cpu > 0.0 && ratio > 1.1).then(|| {
        format!(
            "the render nodes rendered for {busy:.3} s by the clock but {cpu:.3} s on the CPU ({ratio:.2}x): other processes shared their CPUs, which the replay of CPU times leaves out (--cpu-scale {ratio:.2} stands for it)"
        )
    })
}

/// How many render nodes worked at once, machine by machine.
fn at_work_text(machines: &[Machine]) -> String {
    if machines.is_empty() {
        return "every render node at once".into();
    }
    let each: Vec<String> = machines
        .iter()
        .map(|m| format!("{} of the {} on one machine", m.at_work, m.nodes.len()))
        .collect();
    format!("render nodes at work at once: {}", each.join(", "))
}

/// The overheads read off a recorded render, with what they were read from.
#[derive(Clone, Debug, Serialize)]
pub struct MeasuredOverheads {
    pub overheads: Overheads,
    /// Hops on the recorded subscreens' critical paths that the excess was divided over.
    pub hops: u64,
    /// The recorded subscreens' spans added up, and the modelled ones, in seconds.
    pub recorded_spans_s: f64,
    pub modelled_spans_s: f64,
}

/// Reads off a recorded cluster render what its processes paid beyond the models, by
/// replaying it without overheads and comparing with the host's own clock:
///
/// * **start**: the host handed out its first subscreen `start_s` after the job began
///   (the job reaching every node, the scene header, for batch the handout); the replay
///   hands its first one out earlier by the modelled times alone. The difference.
/// * **job stagger**: the first wave (one subscreen to each render node) is spread over
///   longer than the replay spreads it, because the host sends the job to one node after
///   another; the excess spread divided over the render nodes.
/// * **per message**: each recorded subscreen's span (handed out to its last row in, the
///   host's clock) against the replay's span of the same subscreen; the excess over all
///   subscreens, divided by the messages on a span's critical path: the answer, a request
///   and a reply per recorded fetch, the last scan line, and the fork node passing it to
///   the host. The rows before the last overlap with rendering and are not counted.
///
/// An approximation, stated: every message is charged the same mean cost, whatever its size
/// or route; and where the real render fetched more often than the replay (a cache smaller
/// than a subscreen's set refetches; a record holds the set, not the order), those fetches'
/// modelled time is in the excess too.
pub fn measure_overheads(stats_json: &str) -> Result<MeasuredOverheads, SimulateError> {
    #[derive(Deserialize)]
    struct Record {
        node: protocol::NodeId,
        x: u32,
        y: u32,
        start_s: f64,
        end_s: f64,
        #[serde(default)]
        fetches: u64,
    }
    #[derive(Deserialize)]
    struct Records {
        subscreens: Vec<Record>,
    }
    let (bare, topology) = predict_on(stats_json, &Overrides::default())?;
    let mut records = serde_json::from_str::<Records>(stats_json)
        .map_err(sim::WorkloadError::Json)?
        .subscreens;
    // Each record's node is looked up in the topology below: one that names no render node
    // of it (a file edited, or of another render) is refused, not indexed.
    if let Some(r) = records.iter().find(|r| {
        (r.node as usize) >= topology.len() || topology.role(r.node) != protocol::Role::Render
    }) {
        return Err(SimulateError::NotARenderNode {
            node: r.node,
            topology: bare.topology_name.clone(),
        });
    }
    // The replay numbers the recorded subscreens as the workload orders them.
    records.sort_by_key(|r| (r.y, r.x));
    // The first handout to each render node: the first wave, as long as the job took to
    // reach them all.
    // As many as may work at once: a machine's limit keeps the rest waiting.
    let held_back: usize = bare
        .machine_limits
        .iter()
        .map(|m| m.nodes.len().saturating_sub(m.at_work))
        .sum();
    let render_nodes = bare.result.render_nodes.saturating_sub(held_back).max(1);
    let mut recorded_starts: Vec<f64> = records.iter().map(|r| r.start_s).collect();
    recorded_starts.sort_by(f64::total_cmp);
    let mut modelled_starts: Vec<f64> = bare
        .result
        .spans_ns
        .iter()
        .map(|s| s.0 as f64 * 1e-9)
        .collect();
    modelled_starts.sort_by(f64::total_cmp);
    let wave = |starts: &[f64]| {
        let k = starts.len().min(render_nodes);
        (starts[0], starts[k - 1] - starts[0], k)
    };
    let (first_recorded, spread_recorded, k) = wave(&recorded_starts);
    let (first_modelled, spread_modelled, _) = wave(&modelled_starts);
    let recorded_spans_s: f64 = records.iter().map(|r| (r.end_s - r.start_s).max(0.0)).sum();
    let modelled_spans_s: f64 = bare
        .result
        .spans_ns
        .iter()
        .take(records.len())
        .map(|&(a, b)| b.saturating_sub(a) as f64 * 1e-9)
        .sum();
    // Hops on each span's critical path: the answer from the host; per recorded fetch the
    // request to the fork node and the reply (one); the last scan line to the fork node and
    // its pass to the host (one).
    let mut hops: u64 = 0;
    for r in &records {
        let fork = topology.fork_of(r.node).unwrap_or(0);
        let from_host = sim::hops(&topology, 0, r.node).max(1) as u64;
        let to_fork = sim::hops(&topology, r.node, fork).max(1) as u64;
        hops += from_host + r.fetches * (to_fork + 1) + to_fork + 1;
    }
    // The first request, to the host, pays its hops' cost in the replay too.
    let first_request_hops = records
        .iter()
        .min_by(|a, b| a.start_s.total_cmp(&b.start_s))
        .map_or(1, |r| sim::hops(&topology, r.node, 0).max(1)) as f64;
    let ns = |s: f64| (s.max(0.0) * 1e9).round() as u64;
    let hop_s = (recorded_spans_s - modelled_spans_s) / hops.max(1) as f64;
    Ok(MeasuredOverheads {
        overheads: Overheads {
            // The first request pays its message cost in the replay too.
            start_ns: ns(first_recorded - first_modelled - hop_s * first_request_hops),
            hop_ns: ns(hop_s),
            job_stagger_ns: ns((spread_recorded - spread_modelled) / (k.max(2) - 1) as f64),
        },
        hops,
        recorded_spans_s,
        modelled_spans_s,
    })
}

/// The prediction as a few lines and a table of the render nodes.
pub fn summary(p: &Prediction) -> String {
    let mut out = format!(
        "{}\nlink model {:?} at time scale {}, transfer {}, subscreens {}, adaptive {}, cpu scale {}, {}\n",
        p.topology,
        p.link_model,
        p.time_scale,
        p.transfer,
        p.subscreens,
        p.adaptive,
        p.cpu_scale,
        at_work_text(&p.machine_limits)
    );
    for note in &p.notes {
        out += &format!("note: {note}\n");
    }
    let r = &p.result;
    out += &format!("predicted render time {:.4} s", p.predicted_s);
    match (p.measured_s, p.error_percent) {
        (Some(m), Some(e)) => out += &format!(", measured {m:.4} s ({e:+.1}%)\n"),
        _ => out += "\n",
    }
    out += &format!(
        "{} subscreens handed out ({} split off), {} fetches: {} bytes by DMA, {} through the mesh, {} over the G-bus, {} in the batch handout; {} messages, {} events\n",
        r.subscreens,
        r.subscreens_split,
        r.transfers,
        r.bytes.dma,
        r.bytes.mesh,
        r.bytes.gbus,
        r.bytes.batch,
        r.messages,
        r.events
    );
    out += "node   busy_s  waiting_s   idle_s  subscreens  fetches\n";
    for n in &r.nodes {
        out += &format!(
            "{:>4} {:>8.4} {:>10.4} {:>8.4} {:>11} {:>8}\n",
            n.node, n.busy_s, n.waiting_s, n.idle_s, n.subscreens, n.fetches
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A demand render on `tiny` with the paper's links at a tenth of their time: four
    /// subscreens, each touching one of two chunks.
    fn stats() -> String {
        let record = |i: u32, chunk: u32| {
            format!(
                r#"{{"node": {}, "x": 0, "y": {i}, "width": 8, "height": 1, "start_s": 0.0,
                    "end_s": 0.1, "cpu_s": 0.1, "pixels": 8, "samples": 8, "rays": 8,
                    "chunks": [{chunk}], "tiles": [], "fetched_bytes": 4000, "fetches": 1,
                    "fetched_via": "dma"}}"#,
                2 + i
            )
        };
        format!(
            r#"{{"width": 8, "height": 4, "topology": "tiny", "link_model": "Paper",
                "time_scale": 0.1, "transfer": "Demand", "cache_percent": 50.0,
                "adaptive": false, "seconds": {{"render": 0.125}},
                "subscreens": [{}, {}, {}, {}],
                "chunk_bytes": [4000, 4000], "tile_bytes": []}}"#,
            record(0, 0),
            record(1, 1),
            record(2, 0),
            record(3, 1)
        )
    }

    #[test]
    fn simulates_the_recorded_render_and_compares_with_its_time() {
        let p = predict(&stats(), &Overrides::default()).unwrap();
        assert_eq!(p.link_model, LinkModelKind::Paper);
        assert_eq!(p.time_scale, 0.1);
        assert_eq!(p.result.render_nodes, 4);
        assert_eq!(p.result.transfers, 4, "each node fetches its one chunk");
        // A tenth of a second of rendering on each node, plus the messages.
        assert!(
            p.predicted_s > 0.1 && p.predicted_s < 0.11,
            "{}",
            p.predicted_s
        );
        assert_eq!(p.measured_s, Some(0.125));
        let e = p.error_percent.unwrap();
        assert!((e - (p.predicted_s - 0.125) / 0.125 * 100.0).abs() < 1e-9);
        let text = summary(&p);
        assert!(text.contains("measured 0.1250 s"), "{text}");
        assert!(
            text.contains("tiny: 1 host + 1 fork node + 4 render nodes"),
            "{text}"
        );
        assert_eq!(text.lines().filter(|l| l.starts_with("   ")).count(), 4);
    }

    #[test]
    fn the_recorded_demand_path_and_thread_count_are_heeded() {
        let serial = stats().replace(
            r#""adaptive": false,"#,
            r#""adaptive": false, "demand_via": "Serial", "render_threads": 2,"#,
        );
        let p = predict(&serial, &Overrides::default()).unwrap();
        assert_eq!((p.result.bytes.mesh, p.result.bytes.dma), (16000, 0));
        assert_eq!(p.notes.len(), 1);
        assert!(summary(&p).contains("note: the render ran 2 rendering threads"));
    }

    #[test]
    fn an_override_makes_it_another_render_with_no_measurement() {
        let more = Overrides {
            topology: Some("grid:1x1x2".into()),
            link: Some(LinkModelKind::None),
            ..Overrides::default()
        };
        let p = predict(&stats(), &more).unwrap();
        assert_eq!(p.result.render_nodes, 2);
        assert_eq!((p.measured_s, p.error_percent), (None, None));
        assert!(
            (p.predicted_s - 0.2).abs() < 1e-9,
            "two subscreens each, no delays"
        );
    }

    /// A topology file given for the machine brings its own link model and time scale, as
    /// it does to a render (the recorded render's replaced them); a flag still wins, and a
    /// preset, which has none of its own, keeps the recorded ones.
    #[test]
    fn a_topology_files_model_holds_over_the_recorded_one() {
        let dir = std::env::temp_dir().join(format!("lab-simulate-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("pair.toml");
        std::fs::write(
            &file,
            "name = \"pair\"\n[grid]\ncards = 1\nrows = 1\ncols = 2\n[model]\nlink = \"none\"\ntime_scale = 0.5\n",
        )
        .unwrap();
        let on = |topology: &str, time_scale: Option<f64>| {
            let p = predict(
                &stats(),
                &Overrides {
                    topology: Some(topology.into()),
                    time_scale,
                    ..Overrides::default()
                },
            )
            .unwrap();
            (p.link_model, p.time_scale)
        };
        let path = file.to_str().unwrap();
        assert_eq!(on(path, None), (LinkModelKind::None, 0.5));
        assert_eq!(on(path, Some(0.25)), (LinkModelKind::None, 0.25));
        assert_eq!(on("grid:1x1x2", None), (LinkModelKind::Paper, 0.1));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The test render's stats, its four render nodes on one machine that let one work at
    /// once.
    fn one_at_work_of_four() -> String {
        stats().replace(
            r#""adaptive": false,"#,
            r#""adaptive": false, "at_work": "auto",
               "machine_limits": [{"nodes": [2, 3, 4, 5], "at_work": 1}],"#,
        )
    }

    /// A render whose four nodes shared a machine that let one work at once (the stats'
    /// `machine_limits`) is replayed so: one node renders the four subscreens one after
    /// another. The limit was ignored, every node given work, a quarter of the time.
    #[test]
    fn the_recorded_limit_of_nodes_at_work_is_replayed() {
        let limited = one_at_work_of_four();
        let p = predict(&limited, &Overrides::default()).unwrap();
        assert!(
            p.predicted_s > 0.4 && p.predicted_s < 0.45,
            "four subscreens of 0.1 s one after another: {}",
            p.predicted_s
        );
        let working: Vec<u32> = p.result.nodes.iter().map(|n| n.subscreens).collect();
        assert_eq!(working, [4, 0, 0, 0]);
        assert!(p.notes.is_empty(), "{:?}", p.notes);
        let text = summary(&p);
        assert!(text.contains("1 of the 4 on one machine"), "{text}");
    }

    /// Another machine keeps no limit of the recorded one's, and says so; `--at-work` sets
    /// one; a changed setting that `--at-work auto` depends on keeps it, and says so.
    #[test]
    fn another_machine_or_at_work_sets_the_limit() {
        let limited = one_at_work_of_four();
        let elsewhere = Overrides {
            topology: Some("tiny".into()),
            ..Overrides::default()
        };
        let p = predict(&limited, &elsewhere).unwrap();
        assert!(p.predicted_s < 0.11, "{}", p.predicted_s);
        assert!(p.notes[0].contains("of its own machine"), "{:?}", p.notes);
        for (at_work, nodes) in [(AtWork::Count(2), 2), (AtWork::All, 4)] {
            let set = Overrides {
                at_work: Some(at_work),
                ..Overrides::default()
            };
            let p = predict(&limited, &set).unwrap();
            let working = p.result.nodes.iter().filter(|n| n.subscreens > 0).count();
            assert_eq!(working, nodes, "{at_work}");
            assert_eq!(p.measured_s, None);
        }
        // A setting --at-work auto depends on, changed: the limit is kept, and said to be.
        let paper = Overrides {
            link: Some(LinkModelKind::None),
            ..Overrides::default()
        };
        let p = predict(&limited, &paper).unwrap();
        assert_eq!(p.machine_limits.len(), 1);
        assert!(p.notes[0].contains("is kept"), "{:?}", p.notes);
        let cpus = Overrides {
            at_work: Some(AtWork::Cpus),
            ..Overrides::default()
        };
        let e = predict(&limited, &cpus).unwrap_err();
        assert!(e.to_string().contains("knows no machine's CPUs"), "{e}");
    }

    /// Render nodes that rendered twice as long by the clock as on the CPU shared their
    /// CPUs with something the replay cannot know of: said, with the scale that stands for it.
    #[test]
    fn cpus_shared_with_other_processes_are_noted() {
        let nodes = |busy: f64| {
            stats().replace(
                r#""adaptive": false,"#,
                &format!(
                    r#""adaptive": false, "nodes": [{{"role": "Render", "busy_s": {busy}}},
                       {{"role": "Fork", "busy_s": 5.0}}],"#
                ),
            )
        };
        let p = predict(&nodes(0.8), &Overrides::default()).unwrap();
        assert_eq!(p.notes.len(), 1, "{:?}", p.notes);
        assert!(
            p.notes[0].contains("0.800 s by the clock but 0.400 s on the CPU (2.00x)"),
            "{:?}",
            p.notes
        );
        let p = predict(&nodes(0.41), &Overrides::default()).unwrap();
        assert!(p.notes.is_empty(), "{:?}", p.notes);
    }

    #[test]
    fn overheads_read_off_the_records_bring_the_replay_closer() {
        // Each recorded span is 0.1 s of rendering plus 0.02 s the models do not give.
        let slow = stats().replace(r#""end_s": 0.1"#, r#""end_s": 0.12"#);
        let m = measure_overheads(&slow).unwrap();
        assert!(m.recorded_spans_s > m.modelled_spans_s, "{m:?}");
        assert!(m.overheads.hop_ns > 0 && m.hops > 0, "{m:?}");
        let bare = predict(&slow, &Overrides::default()).unwrap();
        let with = predict(
            &slow,
            &Overrides {
                overheads: Some(m.overheads),
                ..Overrides::default()
            },
        )
        .unwrap();
        assert!(with.predicted_s > bare.predicted_s);
        // The replay's spans now match the recorded ones, to within the queueing the added
        // cost shifts on shared links (here about one hop's cost, under 1%).
        let spans: f64 = with
            .result
            .spans_ns
            .iter()
            .map(|&(a, b)| (b - a) as f64 * 1e-9)
            .sum();
        assert!(
            (spans - m.recorded_spans_s).abs() < 0.01 * m.recorded_spans_s,
            "{spans} vs {m:?}"
        );
    }

    /// A record naming a node the topology lacks, or one that is not a render node, is
    /// refused with its number (node 99 was an index out of bounds).
    #[test]
    fn overheads_of_records_naming_no_render_node_are_refused() {
        for (node, was) in [(99, r#""node": 5,"#), (1, r#""node": 5,"#)] {
            let odd = stats().replace(was, &format!(r#""node": {node},"#));
            assert_ne!(odd, stats());
            let e = measure_overheads(&odd).unwrap_err();
            assert!(
                e.to_string().contains(&format!(
                    "node {node}, which is not a render node of topology tiny"
                )),
                "{e}"
            );
        }
    }

    #[test]
    fn a_stats_file_without_what_is_needed_says_so() {
        let no_topology = stats().replace(r#""topology": "tiny","#, "");
        let e = predict(&no_topology, &Overrides::default()).unwrap_err();
        assert!(e.to_string().contains("--topology"), "{e}");
        let odd = stats().replace(r#""transfer": "Demand""#, r#""transfer": "Carrier""#);
        let e = predict(&odd, &Overrides::default()).unwrap_err();
        assert!(e.to_string().contains("\"Carrier\""), "{e}");
        let e = predict("{}", &Overrides::default()).unwrap_err();
        assert!(e.to_string().contains("no per-subscreen records"), "{e}");
        // A cache that is no percentage, given or recorded (NaN passed as 0 bytes).
        for cache in [f64::NAN, -5.0, 0.0, 250.0] {
            let given = Overrides {
                cache_percent: Some(cache),
                ..Overrides::default()
            };
            let e = predict(&stats(), &given).unwrap_err();
            assert!(
                e.to_string().contains(&format!("a cache of {cache}%")),
                "{e}"
            );
        }
        let recorded = stats().replace(r#""cache_percent": 50.0"#, r#""cache_percent": -1.0"#);
        let e = predict(&recorded, &Overrides::default()).unwrap_err();
        assert!(e.to_string().contains("a cache of -1%"), "{e}");
    }
}
