//! Control messages: the `meta` part of a frame, encoded with bincode 2.
//!
//! The header's `kind` byte is the variant index below (bincode's own enum tag), so a node
//! forwarding a frame never needs to decode it. New variants are only ever appended.

use serde::{Deserialize, Serialize};

use crate::{frame::NodeId, handshake::Identity};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Role {
    Host,
    Fork,
    Render,
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Role::Host => "host",
            Role::Fork => "fork node",
            Role::Render => "render node",
        })
    }
}

/// How bulk data travels from a fork node's shared memory to a render node (the paper's
/// two ways, compared in its figures 1.5 and 1.6).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Transfer {
    /// In paper-sized packets, hop by hop through the mesh.
    Serial,
    /// Over the direct connection to the render node's own fork node.
    Dma,
}

/// How a render node's DMA reads of its card's memory really travel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum DmaTransport {
    /// Through a shared-memory segment when the card's fork node runs on the same machine
    /// (and its segment maps and carries the announced nonce), else over TCP.
    #[default]
    Auto,
    /// Always a request and a reply over TCP, as between machines.
    Tcp,
}

impl DmaTransport {
    pub fn as_str(self) -> &'static str {
        match self {
            DmaTransport::Auto => "auto",
            DmaTransport::Tcp => "tcp",
        }
    }
}

/// How a render node's requests for work reach the host, and the answers come back.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum AskVia {
    /// Hop by hop through the render nodes' mesh and the fork nodes, as in the paper (the
    /// delay model charges each hop).
    #[default]
    Mesh,
    /// Over the node's own connection to the host: one hop, and no other process woken.
    Control,
}

impl AskVia {
    pub fn as_str(self) -> &'static str {
        match self {
            AskVia::Mesh => "mesh",
            AskVia::Control => "control",
        }
    }
}

/// Whether render nodes trace memory-coherent rays: a path whose data the cache lacks is put
/// aside while the thread goes on with others (`renderer::render::render_rect_coherent`),
/// instead of the thread waiting for each miss.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum CoherentRays {
    /// Each miss is fetched at once while the thread waits, as in the paper.
    #[default]
    Off,
    On,
    /// On, except while a node reads every card's memory in place (shared memory, links
    /// with no delay model): a miss there copies nothing and waits for no one, so putting
    /// paths aside would cost more than it saves.
    Auto,
}

impl CoherentRays {
    pub fn as_str(self) -> &'static str {
        match self {
            CoherentRays::Off => "off",
            CoherentRays::On => "on",
            CoherentRays::Auto => "auto",
        }
    }
}

/// A piece of data a render node can ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DataId {
    Chunk(u32),
    Tile(u32),
    /// `bytes` of filler, for the link experiments.
    Synthetic {
        bytes: u32,
    },
}

/// Subscreens travel as the renderer's own rectangles (protocol may carry renderer types).
pub use renderer::Rect;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Message {
    // Handshake, on every connection.
    Hello {
        version: u32,
        cluster_id: String,
        nonce: [u8; 32],
        identity: Identity,
        /// The caller's [`crate::build_id`].
        build: String,
    },
    Challenge {
        version: u32,
        nonce: [u8; 32],
        proof: [u8; 32],
    },
    Proof {
        proof: [u8; 32],
    },
    Welcome,
    Refused {
        reason: String,
    },

    // Registration, on a node's control connection to the host.
    Register {
        role: Role,
        advertise: String,
        pid: u32,
        hostname: String,
        boot_id: String,
        /// Which shared memory it sees (`fabric::shm::domain`): nodes with the same one can
        /// map each other's segments.
        shm_domain: String,
        /// CPUs this process may run on (its affinity and CPU quota counted).
        cpus: u32,
        /// CPUs online on its machine.
        machine_cpus: u32,
    },
    /// The node's slot: its id, the topology (in bincode: `fabric::Topology::to_wire`), and
    /// the peers' addresses come later.
    Assigned {
        node: NodeId,
        topology: Vec<u8>,
    },
    /// Every node's advertised address and machine, once the topology is filled.
    Peers {
        addresses: Vec<(NodeId, String, String)>,
    },
    /// The node has connected all its links.
    LinksUp {
        node: NodeId,
    },
    /// Start the cluster's work (sent when every node reported `LinksUp`).
    Go,
    Heartbeat {
        node: NodeId,
    },
    Shutdown {
        reason: String,
    },
    NodeFailed {
        node: NodeId,
        message: String,
    },

    // Link experiments (`magg-host experiment links`).
    /// Host to a render node: measure `count` transfers of `bytes` each from its fork node.
    RunTransfers {
        transfer: Transfer,
        bytes: u32,
        count: u32,
        owner_card: u16,
        start_ns: u64,
    },
    /// Host to a render node: send `count` packets of `bytes` to `to`, one after another, and
    /// report one-way times (or round trips, when `round_trip`).
    RunProbes {
        to: NodeId,
        bytes: u32,
        count: u32,
        round_trip: bool,
    },
    /// A timing probe through the mesh; `sent_ns` is the sender's CLOCK_MONOTONIC.
    Probe {
        id: u32,
        sent_ns: u64,
    },
    /// Results of a measurement: one-way or round-trip times in nanoseconds.
    Measured {
        node: NodeId,
        samples_ns: Vec<u64>,
    },
    /// The answer to a `Probe`: when it was delivered (receiver's CLOCK_MONOTONIC).
    ProbeEcho {
        id: u32,
        received_ns: u64,
    },
    /// A routing check: whoever receives it reports `Seen` to the host.
    Ping {
        id: u32,
    },
    Seen {
        id: u32,
        from: NodeId,
        node: NodeId,
        hops: u8,
    },
    /// Host to a node: send `Ping { id }` to each of `to` (one-to-one), or broadcast it.
    RunPings {
        id: u32,
        to: Vec<NodeId>,
        broadcast: bool,
    },

    // Demand data transfer.
    /// A render node asks its fork node for data held by fork node `owner`.
    DataRequest {
        id: DataId,
        transfer: Transfer,
        owner: NodeId,
    },
    /// The data follows in the frame's data part.
    DataReply {
        id: DataId,
    },
    /// A fork node asks the fork node that holds `id` for it (over the G-bus).
    RemoteRead {
        id: DataId,
        ready_ns: u64,
    },
    RemoteData {
        id: DataId,
        done_ns: u64,
    },
    /// A fork node asks the G-bus arbiter for a slot to move `bytes`.
    BusRequest {
        bytes: u32,
        ready_ns: u64,
    },
    BusGrant {
        done_ns: u64,
    },
    /// A card's memory is also published as a shared-memory segment ([`CardSegment`]). A
    /// render node that can map it and finds the nonce is on the same machine and may read
    /// that card's items from it instead of asking for them; any other stays on TCP.
    SharedSegment(CardSegment),
    /// A render node reads `id` (held by `owner`'s card) from a shared segment while the
    /// links are delayed: its fork node books the DMA transfer (and the G-bus read) as for
    /// a `DataRequest` and answers with a `DataReply` without data at the model time the
    /// transfer completes.
    SharedRead {
        id: DataId,
        owner: NodeId,
    },

    // Distributed rendering.
    /// Host to the first fork node: part `part` of `parts` of the scene description (bincode
    /// of `renderer::SceneDesc`, `total` bytes in all); this part's `len` bytes follow as data.
    /// `chunk_triangles` is the most triangles the fork node may put in one chunk.
    ScenePart {
        part: u32,
        parts: u32,
        total: u64,
        len: u32,
        chunk_triangles: u32,
    },
    /// The prepared scene header (bincode of `renderer::SceneHeader`, `len` bytes, as data) and the
    /// address table: which fork node holds each chunk and each texture tile.
    Header {
        len: u64,
        chunk_owner: Vec<NodeId>,
        tile_owner: Vec<NodeId>,
    },
    /// Data to keep (a fork node's share of the scene, or a render node's batch copy).
    Hold {
        id: DataId,
    },
    /// Everything to hold has been sent: `count` items.
    HoldDone {
        count: u32,
    },
    /// The render job, from the host to every node.
    Job(Box<JobSpec>),
    /// A render node asks the host for work, saying which subscreen it last finished (all
    /// its rows sent), so the host can tell a finished subscreen from one that lost rows.
    /// `ahead`: asked while it still renders one, for the one after (see
    /// [`JobSpec::ask_ahead`]); answered at once, with [`Message::NothingAhead`] when no
    /// subscreen is queued.
    SubscreenRequest {
        finished: Option<u32>,
        ahead: bool,
    },
    Subscreen {
        id: u32,
        rect: Rect,
    },
    NoMoreWork,
    /// Scan lines of a subscreen, top down from (x, y): as data, a whole number of rows of
    /// `width` RGB f32 pixels each.
    Pixels {
        subscreen: u32,
        y: u32,
        x: u32,
        width: u32,
    },
    /// Host to a busy render node: give back the part of this subscreen you have not begun.
    GiveBack {
        subscreen: u32,
    },
    /// Rows `from_row..` of the subscreen are given back (none if `from_row` is its end).
    Returned {
        subscreen: u32,
        from_row: u32,
    },
    StatsRequest,
    NodeStats(Box<NodeStats>),
    /// A node cannot go on with the job.
    Failed {
        node: NodeId,
        message: String,
    },
    /// Host to every node: `node` is gone; route around it.
    NodeDown {
        node: NodeId,
    },
    /// The answer to a request ahead when no subscreen is queued: ask again when done.
    NothingAhead,
    /// The first fork node to another on its machine: that card's share of the scene,
    /// `count` items, is already written as its shared-memory segment (words and walking
    /// forms), instead of coming as `Hold`s; `segments` are the segments of every card it
    /// wrote, this one's among them, for the card's render nodes to map before they start.
    /// The fork node answers with [`Message::ShareAnswer`]; one that cannot use its segment
    /// gets its share as `Hold`s.
    ShareInSegment {
        count: u32,
        segments: Vec<CardSegment>,
    },
    /// Whether a fork node took its card's segment from a [`Message::ShareInSegment`].
    ShareAnswer {
        adopted: bool,
    },
}

/// Fork node `card`'s memory published as the shared-memory segment `name` (a file name in
/// the machine's shared-memory directory), `bytes` long, whose header holds `nonce`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CardSegment {
    pub card: NodeId,
    pub name: String,
    pub nonce: [u32; 4],
    pub bytes: u64,
}

/// How render nodes get shape and texture data.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TransferMode {
    /// Every render node receives everything before rendering.
    Batch,
    /// Render nodes fetch what rays need into a bounded cache.
    Demand,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub settings: renderer::RenderSettings,
    pub camera: renderer::Camera,
    pub transfer: TransferMode,
    /// How demand fetches travel from the fork node.
    pub demand_via: Transfer,
    /// How DMA reads really travel (the model's timing is the same either way).
    pub dma_transport: DmaTransport,
    /// Cache budget of each render node, in bytes of chunks and tiles.
    pub cache_bytes: u64,
    /// Rendering threads per render node.
    pub render_threads: u32,
    /// Whether render nodes put a path that needs data they lack aside and go on with
    /// others; never with a cache that holds the whole scene.
    #[serde(default)]
    pub coherent_rays: CoherentRays,
    /// Render nodes ask for their next subscreen as they begin one, so that the answer is
    /// there when they finish it (instead of a round trip through the mesh after each).
    #[serde(default)]
    pub ask_ahead: bool,
    /// How requests for work travel.
    #[serde(default)]
    pub ask_via: AskVia,
}

/// What one node did, reported at the end of a render.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct NodeStats {
    pub node: NodeId,
    pub role: Option<Role>,
    pub subscreens: u32,
    pub rows: u64,
    pub pixels: u64,
    pub samples: u64,
    pub rays: u64,
    /// Rays by kind, and samples that came out NaN or infinite (counted as black).
    pub camera_rays: u64,
    pub secondary_rays: u64,
    pub shadow_rays: u64,
    pub bad_samples: u64,
    pub cache_hits: u64,
    pub cache_misses: u64,
    pub cache_evictions: u64,
    pub cache_peak_bytes: u64,
    pub bytes_fetched_dma: u64,
    pub bytes_fetched_serial: u64,
    /// Of `bytes_fetched_dma`, those read from a card's shared-memory segment (the rest
    /// came over TCP).
    pub bytes_fetched_shared: u64,
    /// Cards whose shared-memory segment this render node mapped.
    pub shared_segments: u32,
    /// Fork nodes: bytes served to render nodes, and read from other cards over the G-bus.
    pub bytes_served: u64,
    pub bytes_gbus: u64,
    pub frames_forwarded: u64,
    /// Frames that took a direct or control connection because lost nodes cut the mesh.
    pub frames_around_mesh: u64,
    pub bytes_forwarded: u64,
    pub busy_s: f64,
    pub waiting_s: f64,
    pub idle_s: f64,
    pub peak_rss_bytes: u64,
    /// Most memory of the process's own (not mapped shared segments) seen resident: render
    /// nodes look after every subscreen and at the end, other roles at the end.
    pub peak_private_bytes: u64,
    /// Render nodes: chunks walked in place in a card's shared memory (never copied).
    pub chunks_in_place: u64,
    /// Render nodes with coherent rays: times a path was put aside for an item the cache
    /// lacked, and items fetched for waiting paths (each serving all that waited for it).
    #[serde(default)]
    pub paths_deferred: u64,
    #[serde(default)]
    pub deferred_fetches: u64,
    /// Fork nodes: items of the card's share taken from the segment the first fork node
    /// wrote for the card on their shared machine (0 where the share came over a socket).
    #[serde(default)]
    pub share_items_in_segment: u64,
    /// Render nodes: what each subscreen they rendered cost, in the order they finished.
    pub records: Vec<SubscreenWork>,
}

/// What one subscreen cost a render node, which the host joins with the times it handed the
/// subscreen out and received its pixels into the stats' per-subscreen records.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct SubscreenWork {
    pub subscreen: u32,
    /// The rows it rendered: fewer than handed out when it gave the tail back.
    pub rect: Rect,
    /// CPU time of the rendering thread on it.
    pub cpu_s: f64,
    pub pixels: u64,
    pub samples: u64,
    pub rays: u64,
    /// Ids of the chunks and texture tiles its rays touched, ascending.
    pub chunks: Vec<u32>,
    pub tiles: Vec<u32>,
    /// What the cache fetched for it (misses).
    pub fetched_bytes: u64,
    pub fetches: u32,
}

/// Bytes carried in a frame's data part (whose length is counted in words).
pub fn bytes_to_words(bytes: &[u8]) -> Box<[u32]> {
    let mut words = vec![0u32; bytes.len().div_ceil(4)].into_boxed_slice();
    bytemuck::cast_slice_mut::<u32, u8>(&mut words)[..bytes.len()].copy_from_slice(bytes);
    words
}

/// The first `len` bytes of a data part, if it has that many.
pub fn words_to_bytes(words: &[u32], len: usize) -> Option<&[u8]> {
    bytemuck::cast_slice::<u32, u8>(words).get(..len)
}

/// bincode 2 (standard configuration) of any serde value, for payloads carried as data.
pub fn encode_value<T: Serialize>(v: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(v, bincode::config::standard()).expect("values always encode")
}

/// Decodes a payload carried as data, with a size limit against hostile lengths.
pub fn decode_value<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, DecodeError> {
    let cfg = bincode::config::standard().with_limit::<{ 1 << 31 }>();
    let (v, used): (T, usize) =
        bincode::serde::decode_from_slice(bytes, cfg).map_err(|e| DecodeError(e.to_string()))?;
    if used != bytes.len() {
        return Err(DecodeError(format!(
            "{} trailing bytes",
            bytes.len() - used
        )));
    }
    Ok(v)
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("undecodable control message: {0}")]
pub struct DecodeError(pub String);

fn config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<{ crate::frame::MAX_META as usize }>()
}

impl Message {
    pub fn encode(&self) -> Vec<u8> {
        bincode::serde::encode_to_vec(self, config()).expect("messages always encode")
    }

    /// Decodes a control part; every byte must be used.
    pub fn decode(bytes: &[u8]) -> Result<Message, DecodeError> {
        let (m, used): (Message, usize) = bincode::serde::decode_from_slice(bytes, config())
            .map_err(|e| DecodeError(e.to_string()))?;
        if used != bytes.len() {
            return Err(DecodeError(format!(
                "{} trailing bytes",
                bytes.len() - used
            )));
        }
        Ok(m)
    }

    /// The variant index, as it appears in the header's `kind` byte.
    pub fn kind(&self) -> u8 {
        // bincode's standard configuration writes the enum tag as a varint: one byte below 251.
        self.encode()[0]
    }

    pub fn name(&self) -> &'static str {
        match self {
            Message::Hello { .. } => "Hello",
            Message::Challenge { .. } => "Challenge",
            Message::Proof { .. } => "Proof",
            Message::Welcome => "Welcome",
            Message::Refused { .. } => "Refused",
            Message::Register { .. } => "Register",
            Message::Assigned { .. } => "Assigned",
            Message::Peers { .. } => "Peers",
            Message::LinksUp { .. } => "LinksUp",
            Message::Go => "Go",
            Message::Heartbeat { .. } => "Heartbeat",
            Message::Shutdown { .. } => "Shutdown",
            Message::NodeFailed { .. } => "NodeFailed",
            Message::RunTransfers { .. } => "RunTransfers",
            Message::RunProbes { .. } => "RunProbes",
            Message::Probe { .. } => "Probe",
            Message::Measured { .. } => "Measured",
            Message::ProbeEcho { .. } => "ProbeEcho",
            Message::Ping { .. } => "Ping",
            Message::Seen { .. } => "Seen",
            Message::RunPings { .. } => "RunPings",
            Message::DataRequest { .. } => "DataRequest",
            Message::DataReply { .. } => "DataReply",
            Message::RemoteRead { .. } => "RemoteRead",
            Message::RemoteData { .. } => "RemoteData",
            Message::BusRequest { .. } => "BusRequest",
            Message::BusGrant { .. } => "BusGrant",
            Message::SharedSegment(_) => "SharedSegment",
            Message::SharedRead { .. } => "SharedRead",
            Message::ScenePart { .. } => "ScenePart",
            Message::Header { .. } => "Header",
            Message::Hold { .. } => "Hold",
            Message::HoldDone { .. } => "HoldDone",
            Message::Job(_) => "Job",
            Message::SubscreenRequest { .. } => "SubscreenRequest",
            Message::Subscreen { .. } => "Subscreen",
            Message::NoMoreWork => "NoMoreWork",
            Message::Pixels { .. } => "Pixels",
            Message::GiveBack { .. } => "GiveBack",
            Message::Returned { .. } => "Returned",
            Message::StatsRequest => "StatsRequest",
            Message::NodeStats(_) => "NodeStats",
            Message::Failed { .. } => "Failed",
            Message::NodeDown { .. } => "NodeDown",
            Message::NothingAhead => "NothingAhead",
            Message::ShareInSegment { .. } => "ShareInSegment",
            Message::ShareAnswer { .. } => "ShareAnswer",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_texture_encodes_as_a_plain_byte_sequence_would() {
        // Its pixels are written as one byte string; the bytes on the wire (and so the
        // scene's hash in checkpoints) must be those of a sequence of u8.
        use renderer::{
            scene::TextureDesc,
            texture::{Filter, Wrap},
        };
        #[derive(Serialize)]
        struct Plain {
            name: String,
            width: u32,
            height: u32,
            rgba: Vec<u8>,
            wrap_s: Wrap,
            wrap_t: Wrap,
            filter: Filter,
            texels_of: Option<u32>,
        }
        let rgba: Vec<u8> = (0..300u32).map(|i| (i * 7) as u8).collect();
        let t = TextureDesc {
            name: "t".into(),
            width: 5,
            height: 15,
            rgba: rgba.clone(),
            wrap_s: Wrap::default(),
            wrap_t: Wrap::default(),
            filter: Filter::default(),
            texels_of: Some(3),
        };
        let plain = Plain {
            name: "t".into(),
            width: 5,
            height: 15,
            rgba,
            wrap_s: Wrap::default(),
            wrap_t: Wrap::default(),
            filter: Filter::default(),
            texels_of: Some(3),
        };
        let bytes = encode_value(&t);
        assert_eq!(bytes, encode_value(&plain));
        assert_eq!(decode_value::<TextureDesc>(&bytes).unwrap(), t);
    }

    #[test]
    fn round_trip_and_kind_is_the_tag() {
        let msgs = [
            Message::Welcome,
            Message::Refused {
                reason: "no".into(),
            },
            Message::DataRequest {
                id: DataId::Chunk(7),
                transfer: Transfer::Dma,
                owner: 12,
            },
            Message::Peers {
                addresses: vec![(1, "127.0.0.1:5".into(), "m".into())],
            },
        ];
        for m in msgs {
            let b = m.encode();
            assert_eq!(Message::decode(&b).unwrap(), m);
            assert_eq!(m.kind(), b[0]);
        }
        assert_eq!(Message::Welcome.kind(), 3);
    }

    proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = Message::decode(&bytes);
        }
    }
}
