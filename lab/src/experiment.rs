//! `magg-host experiment links`: the paper's figures 1.5 and 1.6 redone on real processes.
//!
//! With the `paper` link model: one-way times of 84-byte packets across the mesh against
//! the paper's formula; then average demand-transfer times against data size, by serial link
//! and by DMA, with the data on card 1 as in the paper, for 1 render node active at several
//! distances from its fork node, then for 16 and for all render nodes asking at once. Last,
//! with no delay model, the raw cost of the fabric: one hop's round trip and throughput on
//! loopback.

use std::{
    collections::HashMap, io::Write, path::PathBuf, sync::atomic::AtomicBool, time::Duration,
};

use fabric::{Delivery, Topology, Via, clock::now_ns, model::LinkModelKind};
use protocol::{Message, NodeId, Transfer};
use serde::Serialize;

use host::cluster::{Cluster, ClusterConfig, start};

#[derive(Clone, Debug)]
pub struct LinksConfig {
    pub cluster: ClusterConfig,
    pub sizes: Vec<u32>,
    pub count: u32,
    pub probes: u32,
    pub out_dir: PathBuf,
}

#[derive(Clone, Debug, Serialize)]
pub struct OneWay {
    pub d_row: u32,
    pub d_col: u32,
    pub samples: usize,
    pub mean_us: f64,
    pub stddev_us: f64,
    pub formula_us: f64,
    pub error_pct: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct TransferRow {
    pub transfer: String,
    /// Who was active: one node (named by its card and position) or how many at once.
    pub active: String,
    pub bytes: u32,
    pub samples: usize,
    pub mean_us: f64,
}

#[derive(Clone, Debug, Serialize, Default)]
pub struct RawFabric {
    pub one_hop_round_trip_us: f64,
    pub one_hop_one_way_us: f64,
    pub serial_hop_mb_per_s: f64,
    pub direct_mb_per_s: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LinksReport {
    pub topology: String,
    pub time_scale: f64,
    pub data_card: u16,
    pub one_way: Vec<OneWay>,
    pub transfers: Vec<TransferRow>,
    pub raw: RawFabric,
}

#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    #[error(transparent)]
    Start(#[from] host::cluster::StartError),
    #[error("sending a measurement command: {0}")]
    Send(#[from] fabric::SendError),
    #[error("nodes did not report their measurements within {0} s")]
    NoReport(u64),
    #[error("lost node {0} during the experiment")]
    LostNode(NodeId),
    #[error("the host's fabric stopped during the experiment")]
    FabricStopped,
    #[error("no render node at the corner of card {0}")]
    NoCornerNode(u16),
    #[error(transparent)]
    Topology(#[from] fabric::topology::TopologyError),
    #[error("plotting: {0}")]
    Plot(#[from] crate::LabError),
    #[error("writing results: {0}")]
    Io(#[from] std::io::Error),
}

fn node_at(t: &Topology, row: i32, col: i32) -> Option<NodeId> {
    (0..t.len() as NodeId).find(|&i| t.position(i) == Some((row, col)))
}

/// Sends each (node, command) on the node's control connection and collects the samples
/// every node reports back.
async fn measure(
    cluster: &mut Cluster,
    commands: Vec<(NodeId, Message)>,
) -> Result<HashMap<NodeId, Vec<u64>>, ExperimentError> {
    let f = &cluster.formed.fabric;
    for (n, m) in &commands {
        f.send_control(*n, m)?;
    }
    let mut results = HashMap::new();
    const REPORT_WITHIN_S: u64 = 600;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(REPORT_WITHIN_S);
    while results.len() < commands.len() {
        let d = tokio::time::timeout_at(deadline, cluster.formed.inbox.recv())
            .await
            .map_err(|_| ExperimentError::NoReport(REPORT_WITHIN_S))?;
        match d {
            Some(Delivery::Frame {
                frame,
                via: Via::Control(_),
            }) => {
                if let Ok(Message::Measured { node, samples_ns }) = frame.message() {
                    results.insert(node, samples_ns);
                }
            }
            Some(Delivery::Lost { peer, .. }) => return Err(ExperimentError::LostNode(peer)),
            Some(_) => {}
            None => return Err(ExperimentError::FabricStopped),
        }
    }
    Ok(results)
}

fn mean_std(samples: &[u64]) -> (f64, f64) {
    if samples.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = samples.len() as f64;
    let mean = samples.iter().map(|&s| s as f64).sum::<f64>() / n;
    let var = samples
        .iter()
        .map(|&s| (s as f64 - mean).powi(2))
        .sum::<f64>()
        / n.max(1.0);
    (mean / 1000.0, var.sqrt() / 1000.0)
}

/// Where the demand-transfer data lives and how the cards' render nodes are laid out.
struct MeshLayout {
    topology: Topology,
    /// The card holding the data: card 1 as in the paper (card 0 when there is only one).
    data_card: u16,
    cards: Vec<u16>,
    /// Rows and columns of render nodes on one card.
    rows: i32,
    cols: i32,
}

impl MeshLayout {
    fn new(topology: Topology) -> MeshLayout {
        let cards = topology.cards();
        let data_card = if cards.len() > 1 { cards[1] } else { cards[0] };
        let mut layout = MeshLayout {
            topology,
            data_card,
            cards,
            rows: 0,
            cols: 0,
        };
        let pos: Vec<(i32, i32)> = layout
            .card_nodes(layout.cards[0])
            .iter()
            .filter_map(|&n| layout.topology.position(n))
            .collect();
        layout.rows = pos.iter().map(|p| p.0).max().unwrap_or(0) + 1;
        layout.cols = pos.iter().map(|p| p.1).max().unwrap_or(0) + 1;
        layout
    }

    fn card_nodes(&self, card: u16) -> Vec<NodeId> {
        self.topology
            .render_nodes()
            .into_iter()
            .filter(|&r| self.topology.card(r) == Some(card))
            .collect()
    }

    fn first_col(&self, card: u16) -> i32 {
        self.card_nodes(card)
            .iter()
            .filter_map(|&n| self.topology.position(n))
            .map(|p| p.1)
            .min()
            .unwrap_or(0)
    }
}

pub async fn links(
    config: &LinksConfig,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<LinksReport, ExperimentError> {
    let paper = config
        .cluster
        .clone()
        .with_model(Some(LinkModelKind::Paper), None);
    let layout = MeshLayout::new(paper.topology.clone());
    progress(&format!("starting {}", layout.topology.summary()));
    let mut cluster = start(&paper, &|_, _| {}, &AtomicBool::new(false)).await?;
    progress("one-packet times across the mesh");
    let one_way = one_packet_times(&mut cluster, &layout, config.probes).await?;
    let transfers = demand_transfers(&mut cluster, &layout, config, progress).await?;
    cluster.shutdown("experiment done").await;
    progress("raw fabric cost (no delay model)");
    let raw = raw_fabric(config).await?;
    let report = LinksReport {
        topology: layout.topology.name.clone(),
        time_scale: layout.topology.model.time_scale,
        data_card: layout.data_card,
        one_way,
        transfers,
        raw,
    };
    write_outputs(&report, config)?;
    Ok(report)
}

/// One-packet times from the data card's corner to nodes at several distances, against the
/// paper's formula.
async fn one_packet_times(
    cluster: &mut Cluster,
    layout: &MeshLayout,
    probes: u32,
) -> Result<Vec<OneWay>, ExperimentError> {
    let t = &layout.topology;
    let model = fabric::Model::new(t.model.clone());
    let c0 = layout.first_col(layout.data_card);
    let source = node_at(t, 0, c0).ok_or(ExperimentError::NoCornerNode(layout.data_card))?;
    let mut one_way = Vec::new();
    for (dr, dc) in [
        (0, 1),
        (0, 2),
        (0, 3),
        (1, 0),
        (2, 0),
        (3, 0),
        (1, 1),
        (2, 2),
        (3, 3),
        (1, 3),
        (3, 1),
    ] {
        if dr >= layout.rows || dc >= layout.cols {
            continue;
        }
        let Some(to) = node_at(t, dr, c0 + dc) else {
            continue;
        };
        let cmd = Message::RunProbes {
            to,
            bytes: 84,
            count: probes,
            round_trip: false,
        };
        let r = measure(cluster, vec![(source, cmd)]).await?;
        let samples = r.get(&source).cloned().unwrap_or_default();
        let (mean, std) = mean_std(&samples);
        let formula = model.formula_ns(dr as u32, dc as u32) as f64 / 1000.0;
        one_way.push(OneWay {
            d_row: dr as u32,
            d_col: dc as u32,
            samples: samples.len(),
            mean_us: mean,
            stddev_us: std,
            formula_us: formula,
            error_pct: (mean - formula) / formula * 100.0,
        });
    }
    Ok(one_way)
}

/// Demand transfers: one node at a time at several distances, then one card's nodes, then
/// everyone at once.
async fn demand_transfers(
    cluster: &mut Cluster,
    layout: &MeshLayout,
    config: &LinksConfig,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Vec<TransferRow>, ExperimentError> {
    let t = &layout.topology;
    let mut groups: Vec<(String, Vec<NodeId>)> = Vec::new();
    for &card in layout.cards.iter().take(2) {
        let c = layout.first_col(card);
        for (r, cc) in [(0, 0), (layout.rows - 1, layout.cols - 1)] {
            if let Some(n) = node_at(t, r, c + cc) {
                groups.push((format!("1 node: card {card} ({r},{cc})"), vec![n]));
            }
        }
    }
    let card0 = layout.card_nodes(layout.cards[0]);
    groups.push((
        format!("{} nodes at once (card {})", card0.len(), layout.cards[0]),
        card0,
    ));
    let all = t.render_nodes();
    groups.push((format!("{} nodes at once (all)", all.len()), all));
    let mut transfers = Vec::new();
    for (label, nodes) in &groups {
        for transfer in [Transfer::Serial, Transfer::Dma] {
            for &bytes in &config.sizes {
                progress(&format!("{label}: {transfer:?} transfers of {bytes} bytes"));
                let start_ns = now_ns() + 50_000_000;
                let command = Message::RunTransfers {
                    transfer,
                    bytes,
                    count: config.count,
                    owner_card: layout.data_card,
                    start_ns,
                };
                let cmds = nodes.iter().map(|&n| (n, command.clone())).collect();
                let r = measure(cluster, cmds).await?;
                let samples: Vec<u64> = r.values().flatten().copied().collect();
                let (mean, _) = mean_std(&samples);
                transfers.push(TransferRow {
                    transfer: format!("{transfer:?}"),
                    active: label.clone(),
                    bytes,
                    samples: samples.len(),
                    mean_us: mean,
                });
            }
        }
    }
    Ok(transfers)
}

/// The raw fabric on a small cluster with no delay model: one hop's times and throughput.
async fn raw_fabric(config: &LinksConfig) -> Result<RawFabric, ExperimentError> {
    let mut raw_cfg = config
        .cluster
        .clone()
        .with_model(Some(LinkModelKind::None), Some(1.0));
    raw_cfg.topology = Topology::preset("tiny")?;
    let mut raw_cluster = start(&raw_cfg, &|_, _| {}, &AtomicBool::new(false)).await?;
    let rt = &raw_cfg.topology;
    let (a, b) = (
        node_at(rt, 0, 0).unwrap_or(2),
        node_at(rt, 0, 1).unwrap_or(3),
    );
    let probe = |round_trip| Message::RunProbes {
        to: b,
        bytes: 84,
        count: 2000,
        round_trip,
    };
    let rtt = measure(&mut raw_cluster, vec![(a, probe(true))]).await?;
    let ow = measure(&mut raw_cluster, vec![(a, probe(false))]).await?;
    let big = 16 << 20;
    let data_card = rt.card(a).unwrap_or(0);
    let mut rates = Vec::new();
    for transfer in [Transfer::Serial, Transfer::Dma] {
        let cmd = Message::RunTransfers {
            transfer,
            bytes: big,
            count: 5,
            owner_card: data_card,
            start_ns: 0,
        };
        let r = measure(&mut raw_cluster, vec![(a, cmd)]).await?;
        let (mean_us, _) = mean_std(r.get(&a).map(Vec::as_slice).unwrap_or(&[]));
        rates.push(big as f64 / mean_us);
    }
    raw_cluster.shutdown("experiment done").await;
    Ok(RawFabric {
        one_hop_round_trip_us: mean_std(rtt.get(&a).map(Vec::as_slice).unwrap_or(&[])).0,
        one_hop_one_way_us: mean_std(ow.get(&a).map(Vec::as_slice).unwrap_or(&[])).0,
        serial_hop_mb_per_s: rates[0],
        direct_mb_per_s: rates[1],
    })
}

/// A table or figures written whole or not at all, as every output of magg.
fn write_whole(path: &std::path::Path, bytes: &[u8]) -> Result<(), ExperimentError> {
    scene_io::image_io::write_atomic(path, bytes).map_err(|e| ExperimentError::Plot(e.into()))
}

fn write_outputs(r: &LinksReport, config: &LinksConfig) -> Result<(), ExperimentError> {
    std::fs::create_dir_all(&config.out_dir)?;
    let mut f = Vec::new();
    writeln!(
        f,
        "d_row,d_col,samples,mean_us,stddev_us,formula_us,error_pct"
    )?;
    for o in &r.one_way {
        writeln!(
            f,
            "{},{},{},{:.1},{:.1},{:.1},{:.2}",
            o.d_row, o.d_col, o.samples, o.mean_us, o.stddev_us, o.formula_us, o.error_pct
        )?;
    }
    write_whole(&config.out_dir.join("one_way.csv"), &f)?;
    let mut f = Vec::new();
    writeln!(f, "transfer,active,bytes,samples,mean_us")?;
    for t in &r.transfers {
        writeln!(
            f,
            "{},\"{}\",{},{},{:.1}",
            t.transfer, t.active, t.bytes, t.samples, t.mean_us
        )?;
    }
    write_whole(&config.out_dir.join("transfers.csv"), &f)?;
    write_whole(
        &config.out_dir.join("links.json"),
        &serde_json::to_vec_pretty(r).unwrap_or_default(),
    )?;
    let one = config.out_dir.join("fig1.5-one-node.png");
    crate::plot::transfers_png(
        &one,
        r,
        false,
        "Fig. 1.5: average transfer time, one render node active",
    )?;
    let many = config.out_dir.join("fig1.6-many-nodes.png");
    crate::plot::transfers_png(
        &many,
        r,
        true,
        "Fig. 1.6: average transfer time, many render nodes active",
    )?;
    Ok(())
}

/// The report as Markdown tables.
pub fn tables(r: &LinksReport) -> String {
    let mut s = String::new();
    s.push_str(&format!(
        "One 84-byte packet across the mesh ({} topology, time scale {}):\n\n",
        r.topology, r.time_scale
    ));
    s.push_str(
        "| d_row | d_col | measured (us) | formula (us) | error |\n|---:|---:|---:|---:|---:|\n",
    );
    for o in &r.one_way {
        s.push_str(&format!(
            "| {} | {} | {:.0} ± {:.0} | {:.0} | {:+.1}% |\n",
            o.d_row, o.d_col, o.mean_us, o.stddev_us, o.formula_us, o.error_pct
        ));
    }
    let sizes: Vec<u32> = {
        let mut v: Vec<u32> = r.transfers.iter().map(|t| t.bytes).collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    s.push_str(&format!(
        "\nAverage demand-transfer time (us), data on card {}:\n\n| active | transfer |",
        r.data_card
    ));
    for b in &sizes {
        s.push_str(&format!(" {b} B |"));
    }
    s.push_str("\n|---|---|");
    for _ in &sizes {
        s.push_str("---:|");
    }
    s.push('\n');
    let mut keys: Vec<(String, String)> = Vec::new();
    for t in &r.transfers {
        let k = (t.active.clone(), t.transfer.clone());
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    for (active, transfer) in keys {
        s.push_str(&format!("| {active} | {transfer} |"));
        for b in &sizes {
            let v = r
                .transfers
                .iter()
                .find(|t| t.active == active && t.transfer == transfer && t.bytes == *b);
            s.push_str(&match v {
                Some(t) => format!(" {:.0} |", t.mean_us),
                None => " |".into(),
            });
        }
        s.push('\n');
    }
    s.push_str(&format!(
        "\nRaw fabric, no delay model, one hop on loopback: round trip {:.0} us, one way {:.0} us; \
         throughput {:.0} MB/s through a mesh link, {:.0} MB/s over a direct connection.\n",
        r.raw.one_hop_round_trip_us,
        r.raw.one_hop_one_way_us,
        r.raw.serial_hop_mb_per_s,
        r.raw.direct_mb_per_s
    ));
    s
}
