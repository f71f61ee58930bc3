//! Which nodes a cluster has and how they are linked.
//!
//! The default, `magg`, reproduces the paper's machine: a host, 5 cards each with a fork node
//! and 16 render nodes in a 4x4 block, 86 processes. The render nodes of all cards form one
//! 2D mesh of 4 rows by 20 columns, the cards side by side, so each card's outer render nodes
//! are linked to the neighbouring card's (the paper: "the FP and the outer 10 NPs are also
//! connected to FPs or NPs on other GPUs"). Each fork node is linked to the top-left render
//! node of its card (the entry point of its card's mesh) and to the fork nodes of the cards
//! beside it; the host is linked to the first fork node, the paper's FP (0,-1). No node has
//! more than 4 links, as a T800 has 4.
//!
//! ```text
//!  host
//!   |
//!   F0 ------------- F1 ------------- F2 ------------- F3 ------------- F4
//!   |                 |                 |                 |                 |
//!  r00-r01-r02-r03 - r04-r05-r06-r07 - r08-r09-r10-r11 - r12-r13-r14-r15 - r16-r17-r18-r19
//!   |   |   |   |     |   |   |   |     |   |   |   |     |   |   |   |     |   |   |   |
//!  r20-r21-r22-r23 - r24-r25-r26-r27 - ...                                     ...     r39
//!   |   |   |   |     |   |   |   |
//!  r40-...
//!   |
//!  r60-r61-r62-r63 - r64-...                                                           r79
//!   \______card 0____/ \____card 1_____/   ...                                \____card 4___/
//! ```
//!
//! A render node's requests to its fork node travel the mesh, column first then row
//! (dimension-ordered), to the card's entry node and up; the paper's transfer time grows
//! with the row and column distance exactly so. Topology is data: `tiny` (one card of 2x2),
//! `magg1000` (50 cards of 4x5, 1000 render nodes, for the simulator to go past the paper's
//! 80) and `grid:CARDSxROWSxCOLS` are presets, and a TOML file can describe any layout, listing
//! nodes and links one by one or by a `[grid]` section, with the delay model's constants.

use std::collections::{BTreeSet, VecDeque};

use protocol::{NodeId, Role};
use serde::{Deserialize, Serialize};

use crate::model::ModelParams;

/// Most links one node may have (a T800 transputer has four).
pub const MAX_LINKS: usize = 4;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct NodeSpec {
    pub role: Role,
    /// The card (the paper's GPU board) a fork or render node belongs to.
    pub card: Option<u16>,
    /// Position of a render node in the mesh.
    pub row: Option<i32>,
    pub col: Option<i32>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Topology {
    pub name: String,
    /// The id every process of the cluster gives at the handshake: the file's `cluster_id`,
    /// else [`crate::cluster::DEFAULT_CLUSTER_ID`] (what nodes started by hand give unless
    /// told otherwise), which the host's `--cluster-id` replaces.
    pub cluster_id: String,
    /// Indexed by node id; the host is node 0.
    pub nodes: Vec<NodeSpec>,
    pub links: Vec<[NodeId; 2]>,
    pub model: ModelParams,
    adjacency: Vec<Vec<NodeId>>,
}

#[derive(Debug, thiserror::Error)]
pub enum TopologyError {
    #[error("cannot be read as a topology (TOML of the keys README.md's Topologies lists): {0}")]
    Toml(#[source] toml::de::Error),
    #[error("undecodable topology: {0}")]
    Wire(String),
    #[error("cannot read the topology file {path}: {source}")]
    Read {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("in the topology file {path}: {source}")]
    File {
        path: std::path::PathBuf,
        source: Box<TopologyError>,
    },
    #[error("unknown topology preset {0:?} (magg, magg1000, tiny, or grid:CARDSxROWSxCOLS)")]
    UnknownPreset(String),
    #[error("{0}: no such topology file")]
    NoFile(std::path::PathBuf),
    #[error("invalid topology: {0}")]
    Invalid(String),
    #[error("invalid topology: {0}")]
    Model(crate::model::ModelError),
}

#[derive(Deserialize, Serialize, Default)]
#[serde(deny_unknown_fields)]
struct File {
    name: Option<String>,
    cluster_id: Option<String>,
    grid: Option<Grid>,
    #[serde(default)]
    node: Vec<FileNode>,
    #[serde(default)]
    link: Vec<FileLink>,
    #[serde(default)]
    model: ModelParams,
}

#[derive(Deserialize, Serialize, Clone, Copy)]
#[serde(deny_unknown_fields)]
struct Grid {
    cards: u16,
    rows: u16,
    cols: u16,
}

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct FileNode {
    id: NodeId,
    role: String,
    card: Option<u16>,
    row: Option<i32>,
    col: Option<i32>,
}

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct FileLink {
    between: [NodeId; 2],
}

/// Largest topology accepted (node ids are 16-bit, 0xFFFF means broadcast).
pub const MAX_NODES: usize = 4096;

impl Topology {
    /// A preset by name, or a TOML file's contents when `spec` names a file.
    pub fn resolve(spec: &str) -> Result<Topology, TopologyError> {
        let preset = Topology::preset(spec);
        if let Ok(t) = preset {
            return Ok(t);
        }
        let path = std::path::Path::new(spec);
        if path.exists() {
            let text = std::fs::read_to_string(path).map_err(|source| TopologyError::Read {
                path: path.to_path_buf(),
                source,
            })?;
            return Topology::from_toml(&text).map_err(|e| TopologyError::File {
                path: path.to_path_buf(),
                source: Box::new(e),
            });
        }
        match preset {
            // A grid of numbers the grid refuses (a zero, too many nodes) says why.
            Err(e) if spec.starts_with("grid:") => Err(e),
            // What looks like a path was meant as a file (`--spawn my.toml`), not a preset.
            _ if spec.contains('/') || spec.ends_with(".toml") => {
                Err(TopologyError::NoFile(path.to_path_buf()))
            }
            _ => Err(TopologyError::UnknownPreset(spec.to_string())),
        }
    }

    pub fn preset(name: &str) -> Result<Topology, TopologyError> {
        match name {
            "magg" => Topology::grid("magg", 5, 4, 4),
            "tiny" => Topology::grid("tiny", 1, 2, 2),
            "magg1000" => Topology::grid("magg1000", 50, 4, 5),
            other => {
                let dims = other
                    .strip_prefix("grid:")
                    .ok_or_else(|| TopologyError::UnknownPreset(other.into()))?;
                let parts: Vec<u16> = dims
                    .split('x')
                    .map(|p| p.parse::<u16>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| TopologyError::UnknownPreset(other.into()))?;
                match parts[..] {
                    [cards, rows, cols] => Topology::grid(other, cards, rows, cols),
                    _ => Err(TopologyError::UnknownPreset(other.into())),
                }
            }
        }
    }

    /// The paper's layout, generalised: `cards` blocks of `rows` x `cols` render nodes side by
    /// side in one mesh, a fork node per card.
    pub fn grid(name: &str, cards: u16, rows: u16, cols: u16) -> Result<Topology, TopologyError> {
        let file = File {
            name: Some(name.into()),
            grid: Some(Grid { cards, rows, cols }),
            ..File::default()
        };
        Topology::from_file(file)
    }

    pub fn from_toml(text: &str) -> Result<Topology, TopologyError> {
        let file: File = toml::from_str(text).map_err(TopologyError::Toml)?;
        Topology::from_file(file)
    }

    fn from_file(file: File) -> Result<Topology, TopologyError> {
        let invalid = |m: String| TopologyError::Invalid(m);
        let name = file.name.clone().unwrap_or_else(|| "custom".into());
        let (nodes, links) = match (file.grid, file.node.is_empty()) {
            (Some(g), true) => grid_layout(g)?,
            (Some(_), false) => {
                return Err(invalid(
                    "give either [grid] or [[node]] entries, not both".into(),
                ));
            }
            (None, _) => {
                let mut nodes = vec![None; file.node.len()];
                for n in &file.node {
                    let role = match n.role.as_str() {
                        "host" => Role::Host,
                        "fork" => Role::Fork,
                        "render" => Role::Render,
                        r => {
                            return Err(invalid(format!(
                                "node {}: unknown role {r:?} (host, fork, render)",
                                n.id
                            )));
                        }
                    };
                    let slot = nodes.get_mut(n.id as usize).ok_or_else(|| {
                        invalid(format!(
                            "node ids must be 0..{}, found {}",
                            file.node.len(),
                            n.id
                        ))
                    })?;
                    if slot.is_some() {
                        return Err(invalid(format!("node {} is listed twice", n.id)));
                    }
                    *slot = Some(NodeSpec {
                        role,
                        card: n.card,
                        row: n.row,
                        col: n.col,
                    });
                }
                let nodes: Vec<NodeSpec> = nodes
                    .into_iter()
                    .map(|n| n.expect("every slot filled"))
                    .collect();
                (nodes, file.link.iter().map(|l| l.between).collect())
            }
        };
        // Not the name: a file that names its machine and says nothing of the id keeps the
        // id that nodes started by hand give by default, as a preset does.
        let cluster_id = file
            .cluster_id
            .unwrap_or_else(|| crate::cluster::DEFAULT_CLUSTER_ID.to_string());
        let mut t = Topology {
            name,
            cluster_id,
            nodes,
            links,
            model: file.model,
            adjacency: Vec::new(),
        };
        t.validate()?;
        Ok(t)
    }

    /// Whether the preset of this topology's name ([`Topology::preset`]) is this very
    /// machine (the same nodes, links and model, but for the link model and time scale, which
    /// a render may set and its stats record), so that its name is enough to make it again.
    /// A topology file's is not: its name is its own (or `custom`).
    pub fn is_preset(&self) -> bool {
        Topology::preset(&self.name).is_ok_and(|p| {
            let model = crate::model::ModelParams {
                link: p.model.link,
                time_scale: p.model.time_scale,
                ..self.model.clone()
            };
            p.nodes == self.nodes && p.links == self.links && p.model == model
        })
    }

    /// The topology as a TOML file (explicit nodes and links).
    pub fn to_toml(&self) -> String {
        toml::to_string(&self.to_file()).expect("a topology always serialises")
    }

    /// The topology as the host sends it to each node that joins: the TOML file's fields in
    /// bincode. Every one of a cluster's processes reads it at start, and parsing the
    /// paper's 86-node topology as TOML took about 0.4 ms of CPU (writing it, on the host,
    /// 0.1 ms a node).
    pub fn to_wire(&self) -> Vec<u8> {
        protocol::encode_value(&self.to_file())
    }

    /// A topology the host sent ([`Topology::to_wire`]), checked as a file is.
    pub fn from_wire(bytes: &[u8]) -> Result<Topology, TopologyError> {
        let file: File =
            protocol::decode_value(bytes).map_err(|e| TopologyError::Wire(e.to_string()))?;
        Topology::from_file(file)
    }

    fn to_file(&self) -> File {
        File {
            name: Some(self.name.clone()),
            cluster_id: Some(self.cluster_id.clone()),
            grid: None,
            node: self
                .nodes
                .iter()
                .enumerate()
                .map(|(id, n)| FileNode {
                    id: id as NodeId,
                    role: match n.role {
                        Role::Host => "host",
                        Role::Fork => "fork",
                        Role::Render => "render",
                    }
                    .into(),
                    card: n.card,
                    row: n.row,
                    col: n.col,
                })
                .collect(),
            link: self
                .links
                .iter()
                .map(|l| FileLink { between: *l })
                .collect(),
            model: self.model.clone(),
        }
    }

    fn validate(&mut self) -> Result<(), TopologyError> {
        let invalid = |m: String| Err(TopologyError::Invalid(m));
        let n = self.nodes.len();
        if n < 3 {
            return invalid(
                "a cluster needs a host, a fork node and a render node at least".into(),
            );
        }
        if n > MAX_NODES {
            return invalid(format!("{n} nodes is more than the {MAX_NODES} supported"));
        }
        if self.nodes[0].role != Role::Host
            || self.nodes.iter().filter(|s| s.role == Role::Host).count() != 1
        {
            return invalid("node 0 must be the host, and the only one".into());
        }
        let cards: BTreeSet<u16> = self.nodes.iter().filter_map(|s| s.card).collect();
        for (id, s) in self.nodes.iter().enumerate() {
            if s.role != Role::Host && s.card.is_none() {
                return invalid(format!("node {id} ({}) has no card", s.role));
            }
        }
        for c in &cards {
            let forks = self
                .nodes
                .iter()
                .filter(|s| s.card == Some(*c) && s.role == Role::Fork)
                .count();
            if forks != 1 {
                return invalid(format!(
                    "card {c} has {forks} fork nodes; each card needs exactly one"
                ));
            }
            if !self
                .nodes
                .iter()
                .any(|s| s.card == Some(*c) && s.role == Role::Render)
            {
                return invalid(format!("card {c} has no render nodes"));
            }
        }
        let mut adjacency = vec![Vec::new(); n];
        let mut seen = BTreeSet::new();
        for &[a, b] in &self.links {
            if a as usize >= n || b as usize >= n {
                return invalid(format!("link {a}-{b} names a node that does not exist"));
            }
            if a == b {
                return invalid(format!("link {a}-{b} links a node to itself"));
            }
            if !seen.insert((a.min(b), a.max(b))) {
                return invalid(format!("link {a}-{b} is listed twice"));
            }
            adjacency[a as usize].push(b);
            adjacency[b as usize].push(a);
        }
        for (id, adj) in adjacency.iter_mut().enumerate() {
            if adj.len() > MAX_LINKS {
                return invalid(format!(
                    "node {id} has {} links; a node has at most {MAX_LINKS}",
                    adj.len()
                ));
            }
            adj.sort_unstable();
        }
        // Connected?
        let mut reached = vec![false; n];
        let mut queue = VecDeque::from([0usize]);
        reached[0] = true;
        while let Some(x) = queue.pop_front() {
            for &y in &adjacency[x] {
                if !reached[y as usize] {
                    reached[y as usize] = true;
                    queue.push_back(y as usize);
                }
            }
        }
        if let Some(lost) = reached.iter().position(|r| !r) {
            return invalid(format!("node {lost} cannot be reached from the host"));
        }
        self.model.check().map_err(TopologyError::Model)?;
        self.adjacency = adjacency;
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    pub fn neighbors(&self, id: NodeId) -> &[NodeId] {
        &self.adjacency[id as usize]
    }

    pub fn role(&self, id: NodeId) -> Role {
        self.nodes[id as usize].role
    }

    pub fn card(&self, id: NodeId) -> Option<u16> {
        self.nodes[id as usize].card
    }

    pub fn ids_with(&self, role: Role) -> Vec<NodeId> {
        (0..self.nodes.len() as NodeId)
            .filter(|&i| self.role(i) == role)
            .collect()
    }

    pub fn render_nodes(&self) -> Vec<NodeId> {
        self.ids_with(Role::Render)
    }

    pub fn fork_nodes(&self) -> Vec<NodeId> {
        self.ids_with(Role::Fork)
    }

    /// The fork node of a card.
    pub fn fork_of_card(&self, card: u16) -> Option<NodeId> {
        (0..self.nodes.len() as NodeId)
            .find(|&i| self.role(i) == Role::Fork && self.card(i) == Some(card))
    }

    /// The fork node serving a render node (the one on its card).
    pub fn fork_of(&self, id: NodeId) -> Option<NodeId> {
        self.card(id).and_then(|c| self.fork_of_card(c))
    }

    /// The first fork node, the paper's FP (0,-1), which prepares the scene.
    pub fn master_fork(&self) -> NodeId {
        self.fork_nodes()[0]
    }

    /// The fork node that serves render node `id` while the nodes `alive` says are alive
    /// live: its card's, or, once that one is lost, the live fork node of the nearest card
    /// (the lower card on a tie), so that every node that knows the same losses picks the
    /// same one without asking. `None` when no fork node is alive.
    pub fn serving_fork(&self, id: NodeId, alive: &[bool]) -> Option<NodeId> {
        let live = |f: &NodeId| alive.get(*f as usize).copied().unwrap_or(false);
        let own = self.fork_of(id);
        if let Some(f) = own.filter(live) {
            return Some(f);
        }
        let card = self.card(id).unwrap_or(0) as i32;
        self.fork_nodes().into_iter().filter(live).min_by_key(|&f| {
            let c = self.card(f).unwrap_or(0) as i32;
            ((c - card).abs(), c)
        })
    }

    /// The first live fork node: the G-bus arbiter, a role that passes on when its holder
    /// is lost.
    pub fn first_live_fork(&self, alive: &[bool]) -> Option<NodeId> {
        self.fork_nodes()
            .into_iter()
            .find(|&f| alive.get(f as usize).copied().unwrap_or(false))
    }

    pub fn cards(&self) -> Vec<u16> {
        self.nodes
            .iter()
            .filter_map(|s| s.card)
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect()
    }

    /// Mesh position of a render node.
    pub fn position(&self, id: NodeId) -> Option<(i32, i32)> {
        let s = &self.nodes[id as usize];
        Some((s.row?, s.col?))
    }

    /// A link between two render nodes of the same column runs along a row of the paper's
    /// formula (d_row); every other link counts as a column step (d_col).
    pub fn is_vertical(&self, a: NodeId, b: NodeId) -> bool {
        match (self.position(a), self.position(b)) {
            (Some((_, ca)), Some((_, cb))) => ca == cb,
            _ => false,
        }
    }

    /// Number of processes of each role: (fork nodes, render nodes).
    pub fn counts(&self) -> (usize, usize) {
        (self.fork_nodes().len(), self.render_nodes().len())
    }

    /// A short description: name, processes, links.
    pub fn summary(&self) -> String {
        let (f, r) = self.counts();
        let nodes =
            |n: usize, role: &str| format!("{n} {role} node{}", if n == 1 { "" } else { "s" });
        format!(
            "{}: 1 host + {} + {} = {} processes, {} links",
            self.name,
            nodes(f, "fork"),
            nodes(r, "render"),
            self.nodes.len(),
            self.links.len()
        )
    }
}

fn grid_layout(g: Grid) -> Result<(Vec<NodeSpec>, Vec<[NodeId; 2]>), TopologyError> {
    if g.cards == 0 || g.rows == 0 || g.cols == 0 {
        return Err(TopologyError::Invalid(
            "a grid needs at least one card, row and column".into(),
        ));
    }
    let total = 1 + g.cards as usize * (1 + g.rows as usize * g.cols as usize);
    if total > MAX_NODES {
        return Err(TopologyError::Invalid(format!(
            "grid of {total} nodes is more than the {MAX_NODES} supported"
        )));
    }
    let mut nodes = vec![NodeSpec {
        role: Role::Host,
        card: None,
        row: None,
        col: None,
    }];
    for k in 0..g.cards {
        nodes.push(NodeSpec {
            role: Role::Fork,
            card: Some(k),
            row: None,
            col: None,
        });
    }
    let first_render = nodes.len();
    let width = g.cards as i32 * g.cols as i32;
    let id_at =
        |row: i32, col: i32| -> NodeId { (first_render + (row * width + col) as usize) as NodeId };
    for row in 0..g.rows as i32 {
        for col in 0..width {
            nodes.push(NodeSpec {
                role: Role::Render,
                card: Some((col / g.cols as i32) as u16),
                row: Some(row),
                col: Some(col),
            });
        }
    }
    let mut links = vec![[0, 1]];
    for k in 0..g.cards {
        let fork = 1 + k;
        links.push([fork, id_at(0, k as i32 * g.cols as i32)]);
        if k + 1 < g.cards {
            links.push([fork, fork + 1]);
        }
    }
    for row in 0..g.rows as i32 {
        for col in 0..width {
            if col + 1 < width {
                links.push([id_at(row, col), id_at(row, col + 1)]);
            }
            if row + 1 < g.rows as i32 {
                links.push([id_at(row, col), id_at(row + 1, col)]);
            }
        }
    }
    Ok((nodes, links))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The README's example topology file is one, as the README describes it.
    #[test]
    fn the_readmes_topology_file_is_one() {
        let readme =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../README.md")).unwrap();
        let start = readme
            .find("```toml\n")
            .expect("a TOML block in the README")
            + 8;
        let text = &readme[start..start + readme[start..].find("```").unwrap()];
        let t = Topology::from_toml(text).unwrap();
        let (forks, renders) = t.counts();
        assert_eq!((t.name.as_str(), forks, renders), ("two-cards", 2, 8));
        assert_eq!(t.cluster_id, "lab");
        assert_eq!(t.model.link, crate::model::LinkModelKind::Paper);
        assert_eq!(t.model.time_scale, 0.1);
        assert_eq!(t.model.base_us, ModelParams::default().base_us);
    }

    /// A grid the grid refuses says why, not that no such preset exists; a name that is
    /// neither a grid nor a file is an unknown preset.
    #[test]
    fn a_grid_that_cannot_be_says_why() {
        let e = Topology::resolve("grid:1x64x64").unwrap_err().to_string();
        assert!(
            e.contains("4098 nodes is more than the 4096 supported"),
            "{e}"
        );
        let e = Topology::resolve("grid:0x1x1").unwrap_err().to_string();
        assert!(e.contains("at least one card"), "{e}");
        let e = Topology::resolve("grid:axb").unwrap_err().to_string();
        assert!(e.contains("unknown topology preset"), "{e}");
        let e = Topology::resolve("no-such").unwrap_err().to_string();
        assert!(e.contains("unknown topology preset"), "{e}");
        for file in ["no-such.toml", "topologies/mine"] {
            let e = Topology::resolve(file).unwrap_err().to_string();
            assert_eq!(e, format!("{file}: no such topology file"));
        }
    }

    #[test]
    fn a_preset_is_known_by_its_machine_not_only_its_name() {
        for name in ["magg", "tiny", "grid:2x1x3"] {
            assert!(Topology::resolve(name).unwrap().is_preset(), "{name}");
        }
        let renamed =
            Topology::from_toml("name = \"tiny\"\n[grid]\ncards = 1\nrows = 1\ncols = 3\n");
        assert!(!renamed.unwrap().is_preset());
        let own = Topology::from_toml("name = \"pair\"\n[grid]\ncards = 1\nrows = 1\ncols = 2\n");
        assert!(!own.unwrap().is_preset());
        // The same grid and name with a model of its own is not the preset either; another
        // link model or time scale (a render's flags) leaves it the preset.
        let tiny = "name = \"tiny\"\n[grid]\ncards = 1\nrows = 2\ncols = 2\n";
        assert!(Topology::from_toml(tiny).unwrap().is_preset());
        let buses = Topology::from_toml(&format!("{tiny}[model]\ngbus_count = 3\n"));
        assert!(!buses.unwrap().is_preset());
        let mut scaled = Topology::preset("magg").unwrap();
        scaled.model.time_scale = 0.5;
        scaled.model.link = crate::model::LinkModelKind::Paper;
        assert!(scaled.is_preset());
    }

    /// A file's cluster id and link model are its own, and come back in its TOML form (which
    /// a render's stats keep); with no id, the one nodes give by default, not the file's name
    /// (the host gave nodes that id whatever the file said, and the name was never used).
    #[test]
    fn a_files_cluster_id_and_model_are_its_own() {
        let grid = "[grid]\ncards = 1\nrows = 1\ncols = 2\n";
        let own = Topology::from_toml(&format!(
            "name = \"g\"\ncluster_id = \"other\"\n{grid}[model]\nlink = \"paper\"\ntime_scale = 0.5\n"
        ))
        .unwrap();
        assert_eq!(own.cluster_id, "other");
        assert_eq!(own.model.link, crate::model::LinkModelKind::Paper);
        assert_eq!(own.model.time_scale, 0.5);
        let again = Topology::from_toml(&own.to_toml()).unwrap();
        assert_eq!(
            (again.cluster_id.as_str(), again.model),
            ("other", own.model)
        );
        let unnamed = Topology::from_toml(&format!("name = \"g\"\n{grid}")).unwrap();
        assert_eq!(unnamed.cluster_id, crate::cluster::DEFAULT_CLUSTER_ID);
        for preset in ["magg", "tiny", "grid:2x1x3"] {
            let t = Topology::preset(preset).unwrap();
            assert_eq!(t.cluster_id, crate::cluster::DEFAULT_CLUSTER_ID, "{preset}");
        }
    }

    #[test]
    fn magg_preset_is_the_papers_machine() {
        let t = Topology::preset("magg").unwrap();
        assert_eq!(t.len(), 86);
        assert_eq!(t.counts(), (5, 80));
        for id in 0..t.len() as NodeId {
            assert!(t.neighbors(id).len() <= 4, "node {id}");
        }
        for card in t.cards() {
            let members = t
                .render_nodes()
                .into_iter()
                .filter(|&r| t.card(r) == Some(card))
                .count();
            assert_eq!(members, 16);
        }
        assert_eq!(t.neighbors(0), &[1]);
        assert_eq!(t.master_fork(), 1);
    }

    #[test]
    fn tiny_and_grids() {
        let t = Topology::preset("tiny").unwrap();
        assert_eq!(t.counts(), (1, 4));
        let big = Topology::preset("magg1000").unwrap();
        assert_eq!(big.counts(), (50, 1000));
        let g = Topology::preset("grid:10x8x5").unwrap();
        assert_eq!(g.counts(), (10, 400));
        assert!(Topology::preset("grid:0x1x1").is_err());
        assert!(Topology::preset("grid:2x2").is_err());
    }

    #[test]
    fn a_lost_fork_nodes_render_nodes_go_to_the_nearest_live_card() {
        let t = Topology::preset("magg").unwrap();
        let mut alive = vec![true; t.len()];
        // Render node 6 is on card 0 (fork node 1), node 10 on card 1 (fork node 2).
        assert_eq!(t.serving_fork(6, &alive), Some(1));
        assert_eq!(t.first_live_fork(&alive), Some(1));
        alive[2] = false;
        assert_eq!(t.serving_fork(6, &alive), Some(1), "its own card is alive");
        assert_eq!(
            t.serving_fork(10, &alive),
            Some(1),
            "a tie goes to the lower card"
        );
        alive[1] = false;
        assert_eq!(t.serving_fork(6, &alive), Some(3));
        assert_eq!(t.serving_fork(10, &alive), Some(3));
        assert_eq!(t.first_live_fork(&alive), Some(3));
        for f in t.fork_nodes() {
            alive[f as usize] = false;
        }
        assert_eq!(t.serving_fork(6, &alive), None);
        assert_eq!(t.first_live_fork(&alive), None);
    }

    #[test]
    fn toml_round_trip() {
        let t = Topology::preset("magg").unwrap();
        let again = Topology::from_toml(&t.to_toml()).unwrap();
        assert_eq!(again.nodes, t.nodes);
        assert_eq!(again.links, t.links);
        assert_eq!(again.model, t.model);
    }

    #[test]
    fn the_wire_form_reads_back_and_is_checked_as_a_file_is() {
        for preset in ["tiny", "magg", "grid:2x3x2"] {
            let t = Topology::preset(preset).unwrap();
            assert_eq!(Topology::from_wire(&t.to_wire()).unwrap(), t, "{preset}");
        }
        // Well formed but not a cluster: refused by the same checks as a file.
        let mut file = Topology::preset("tiny").unwrap().to_file();
        file.node[1].role = "wizard".into();
        let e = Topology::from_wire(&protocol::encode_value(&file)).unwrap_err();
        assert!(e.to_string().contains("wizard"), "{e}");
        let mut bytes = Topology::preset("tiny").unwrap().to_wire();
        bytes.truncate(bytes.len() / 2);
        assert!(matches!(
            Topology::from_wire(&bytes),
            Err(TopologyError::Wire(_))
        ));
    }

    #[test]
    fn bad_files_say_what_is_wrong() {
        let cases = [
            ("this is = not toml [", "TOML"),
            ("[grid]\ncards = 1\nrows = 1\ncols = 1\nbogus = 3", "bogus"),
            (
                "[[node]]\nid = 0\nrole = \"host\"\n[[node]]\nid = 1\nrole = \"fork\"\ncard = 0\n[[node]]\nid = 2\nrole = \"render\"\ncard = 0\n",
                "reached",
            ),
            (
                "[[node]]\nid = 0\nrole = \"host\"\n[[node]]\nid = 1\nrole = \"wizard\"\n[[node]]\nid = 2\nrole = \"render\"\ncard = 0",
                "wizard",
            ),
            (
                "[[node]]\nid = 0\nrole = \"host\"\n[[node]]\nid = 1\nrole = \"fork\"\ncard = 0\n[[node]]\nid = 2\nrole = \"render\"\ncard = 0\n[[link]]\nbetween = [0, 9]",
                "does not exist",
            ),
        ];
        for (text, needle) in cases {
            let e = Topology::from_toml(text).unwrap_err().to_string();
            assert!(e.contains(needle), "{e:?} should mention {needle:?}");
        }
    }

    #[test]
    fn a_topology_file_that_cannot_be_read_or_parsed_says_which() {
        let dir = std::env::temp_dir().join(format!("magg-topology-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, "name = [").unwrap();
        let e = Topology::resolve(bad.to_str().unwrap()).unwrap_err();
        let TopologyError::File { path, source } = &e else {
            panic!("{e}")
        };
        assert_eq!(path, &bad);
        assert!(matches!(**source, TopologyError::Toml(_)), "{e}");
        let start = format!(
            "in the topology file {}: cannot be read as a topology",
            bad.display()
        );
        assert!(e.to_string().starts_with(&start), "{e}");
        // A directory exists but cannot be read as a file.
        let e = Topology::resolve(dir.to_str().unwrap()).unwrap_err();
        assert!(matches!(e, TopologyError::Read { .. }), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
