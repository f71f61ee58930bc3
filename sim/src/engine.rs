//! The event loop: render nodes, the host's scheduling and the fork nodes' data service as
//! state machines over one queue of timed events (nanoseconds of model time), taken in time
//! order and, at equal times, in the order they were made, so a run is reproducible exactly.

use std::{
    cmp::Ordering,
    collections::{BinaryHeap, VecDeque},
};

use fabric::{Model, model::Buses};
use protocol::{DataId, Frame, Message, NodeId, Transfer as Via};

use crate::{
    BytesByPath, NodeTimes, SimConfig, SimResult, Transfer,
    cache::{Item, Lru},
    network::{Hop, Network},
    workload::{Subscreen, Workload},
};

#[derive(Clone, Copy, Debug)]
enum Event {
    /// The node may begin: the job is here (and, for batch transfer, every item).
    Start {
        node: usize,
    },
    RequestAtHost {
        node: usize,
        finished: Option<u32>,
    },
    AnswerAtNode {
        node: usize,
        subscreen: u32,
    },
    RowDone {
        node: usize,
    },
    RowAtFork {
        subscreen: u32,
    },
    DataAtFork {
        node: usize,
        item: Item,
    },
    DataAtNode {
        node: usize,
        item: Item,
    },
    GiveBackAtNode {
        node: usize,
        subscreen: u32,
    },
    ReturnedAtHost {
        node: usize,
        subscreen: u32,
        from_row: u32,
    },
}

struct Timed {
    time: u64,
    seq: u64,
    event: Event,
}

impl PartialEq for Timed {
    fn eq(&self, other: &Self) -> bool {
        (self.time, self.seq) == (other.time, other.seq)
    }
}
impl Eq for Timed {}
impl PartialOrd for Timed {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Timed {
    /// Reversed, so that the heap's greatest is the earliest.
    fn cmp(&self, other: &Self) -> Ordering {
        (other.time, other.seq).cmp(&(self.time, self.seq))
    }
}

#[derive(Default)]
struct Queue {
    heap: BinaryHeap<Timed>,
    seq: u64,
}

impl Queue {
    fn at(&mut self, time: u64, event: Event) {
        self.seq += 1;
        self.heap.push(Timed {
            time,
            seq: self.seq,
            event,
        });
    }
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Phase {
    Busy,
    Waiting,
    Idle,
}

/// The subscreen a render node is rendering: rows `next_row..end_row` are still to begin.
struct Active {
    subscreen: u32,
    next_row: u32,
    end_row: u32,
    /// The row being rendered.
    in_hand: u32,
    /// The band whose items the node holds (checked at the band's first row).
    ready_band: Option<usize>,
    /// How far through that band's items the check has come.
    cursor: usize,
}

struct RenderNode {
    id: NodeId,
    card: usize,
    to_host: Vec<Hop>,
    from_host: Vec<Hop>,
    to_fork: Vec<Hop>,
    from_fork: Vec<Hop>,
    /// `None` in batch transfer: everything is here before the node starts.
    cache: Option<Lru>,
    active: Option<Active>,
    finished: Option<u32>,
    /// Which of the config's machines it shares, if any.
    machine: Option<usize>,
    /// Whether it holds a subscreen, as the host counts it: from the answer to its next
    /// request (a node here asks only once it has finished, so it holds at most one).
    holding: bool,
    /// Whether it has been handed work before: such nodes are served first.
    rendered_before: bool,
    phase: Phase,
    since: u64,
    spent: [u64; 3],
    times: NodeTimes,
}

impl RenderNode {
    fn enter(&mut self, phase: Phase, now: u64) {
        self.spent[self.phase as usize] += now - self.since;
        self.phase = phase;
        self.since = now;
    }
}

/// What the host knows of a subscreen.
#[derive(Clone, Copy, Default)]
struct Held {
    node: Option<usize>,
    giving_back: bool,
    /// Its node gave nothing back when asked: it had at most its row in hand left, and can
    /// only have less later. The real host asks again at once until the subscreen's rows are
    /// in, which changes nothing but traffic; here it waits for the next row instead (with
    /// no link delays, asking again at once would never let the time move).
    refused: bool,
    rows_arrived: u32,
    handed_ns: u64,
    done_ns: u64,
}

struct Sim<'a> {
    config: &'a SimConfig,
    model: Model,
    net: Network,
    queue: Queue,
    nodes: Vec<RenderNode>,
    subscreens: Vec<Subscreen>,
    held: Vec<Held>,
    waiting_list: VecDeque<u32>,
    parked: VecDeque<usize>,
    /// Per machine of the config, how many of its nodes it lets hold work at once, and how
    /// many hold some.
    limits: Vec<usize>,
    at_work: Vec<usize>,
    rows_missing: u64,
    split: u32,
    chunk_bytes: &'a [u64],
    tile_bytes: &'a [u64],
    /// The fork nodes, in id order: card k's is the k-th.
    fork_ids: Vec<NodeId>,
    dma: Vec<Buses>,
    gbus: Buses,
    bytes: BytesByPath,
    transfers: u64,
    events: u64,
}

/// Wire bytes of a frame carrying `message` and `data_bytes` of data (padded to words).
fn wire(from: NodeId, to: NodeId, message: &Message, data_bytes: u64) -> usize {
    Frame::new(from, to, message, Box::new([])).wire_len() + data_bytes.div_ceil(4) as usize * 4
}

fn data_id(item: Item) -> DataId {
    match item {
        Item::Chunk(c) => DataId::Chunk(c),
        Item::Tile(t) => DataId::Tile(t),
    }
}

/// The card whose fork node holds `item`: chunks and tiles are each placed round-robin over
/// the fork nodes in id order, as `fork-node`'s assembly places them.
fn owner_card(item: Item, forks: usize) -> usize {
    match item {
        Item::Chunk(i) | Item::Tile(i) => i as usize % forks,
    }
}

pub(crate) fn run(work: &Workload, config: &SimConfig, model: Model) -> SimResult {
    let topology = &config.topology;
    let forks = topology.fork_nodes();
    let net = Network::new(topology, model.clone());
    let nodes: Vec<RenderNode> = topology
        .render_nodes()
        .into_iter()
        .map(|id| {
            let fork = topology
                .fork_of(id)
                .expect("a validated render node has a card");
            let card = forks
                .iter()
                .position(|&f| f == fork)
                .expect("its fork is a fork");
            RenderNode {
                id,
                card,
                to_host: net.route(id, 0),
                from_host: net.route(0, id),
                to_fork: net.route(id, fork),
                from_fork: net.route(fork, id),
                cache: match config.transfer {
                    Transfer::Batch => None,
                    Transfer::Demand { cache_bytes, .. } => Some(Lru::new(cache_bytes)),
                },
                active: None,
                finished: None,
                machine: config.machines.iter().position(|m| m.nodes.contains(&id)),
                holding: false,
                rendered_before: false,
                phase: Phase::Idle,
                since: 0,
                spent: [0; 3],
                times: NodeTimes {
                    node: id,
                    busy_s: 0.0,
                    waiting_s: 0.0,
                    idle_s: 0.0,
                    subscreens: 0,
                    rows: 0,
                    fetches: 0,
                    fetched_bytes: 0,
                    evictions: 0,
                },
            }
        })
        .collect();
    let subscreens = work.subscreens.clone();
    let mut net = net;
    net.hop_overhead_ns = config.overheads.hop_ns;
    let mut sim = Sim {
        config,
        net,
        queue: Queue::default(),
        held: vec![Held::default(); subscreens.len()],
        waiting_list: (0..subscreens.len() as u32).collect(),
        rows_missing: subscreens.iter().map(|s| s.rect.height as u64).sum(),
        subscreens,
        parked: VecDeque::new(),
        limits: config.machines.iter().map(|m| m.at_work).collect(),
        at_work: vec![0; config.machines.len()],
        split: 0,
        chunk_bytes: &work.chunk_bytes,
        tile_bytes: &work.tile_bytes,
        fork_ids: forks.clone(),
        dma: (0..forks.len()).map(|_| Buses::new(1)).collect(),
        gbus: Buses::new(model.params.gbus_count),
        model,
        nodes,
        bytes: BytesByPath::default(),
        transfers: 0,
        events: 0,
    };
    sim.begin();
    let total_ns = sim.run_events();
    sim.result(total_ns)
}

impl Sim<'_> {
    fn bytes_of(&self, item: Item) -> u64 {
        match item {
            Item::Chunk(c) => self.chunk_bytes[c as usize],
            Item::Tile(t) => self.tile_bytes[t as usize],
        }
    }

    /// Books a G-bus transfer of `item` to `card` ready at `ready`, if another card holds it;
    /// when it is in `card`'s memory.
    fn bring_to_card(&mut self, item: Item, card: usize, ready: u64) -> u64 {
        if owner_card(item, self.fork_ids.len()) == card {
            return ready;
        }
        let bytes = self.bytes_of(item);
        self.bytes.gbus += bytes;
        self.gbus.book(ready, self.model.gbus_ns(bytes))
    }

    /// Starts every render node: at once for demand transfer; for batch transfer once its
    /// fork node has handed it every item by DMA, the card's items in id order, each to the
    /// card's nodes in turn.
    fn begin(&mut self) {
        match self.config.transfer {
            Transfer::Demand { .. } => {
                let o = self.config.overheads;
                for node in 0..self.nodes.len() {
                    let at = o.start_ns + node as u64 * o.job_stagger_ns;
                    self.queue.at(at, Event::Start { node });
                }
            }
            Transfer::Batch => {
                let o = self.config.overheads;
                let start = o.start_ns;
                let mut ready_at: Vec<u64> = (0..self.nodes.len() as u64)
                    .map(|k| start + k * o.job_stagger_ns)
                    .collect();
                let items: Vec<Item> = (0..self.chunk_bytes.len() as u32)
                    .map(Item::Chunk)
                    .chain((0..self.tile_bytes.len() as u32).map(Item::Tile))
                    .collect();
                let by_card: Vec<Vec<usize>> = (0..self.fork_ids.len())
                    .map(|card| {
                        (0..self.nodes.len())
                            .filter(|&n| self.nodes[n].card == card)
                            .collect()
                    })
                    .collect();
                for item in items {
                    let bytes = self.bytes_of(item);
                    for (card, members) in by_card.iter().enumerate() {
                        let ready = self.bring_to_card(item, card, start);
                        for &n in members {
                            let done = self.dma[card].book(ready, self.model.dma_ns(bytes));
                            ready_at[n] = ready_at[n].max(done);
                            self.bytes.batch += bytes;
                        }
                    }
                }
                for (node, &at) in ready_at.iter().enumerate() {
                    self.nodes[node].phase = Phase::Waiting;
                    self.queue.at(at, Event::Start { node });
                }
            }
        }
    }

    /// Runs until the last row reaches its fork node; that time.
    fn run_events(&mut self) -> u64 {
        let mut now = 0;
        while let Some(Timed { time, event, .. }) = self.queue.heap.pop() {
            now = time;
            self.events += 1;
            match event {
                Event::Start { node } => self.advance(node, now),
                Event::RequestAtHost { node, finished } => self.request(node, finished, now),
                Event::AnswerAtNode { node, subscreen } => {
                    let height = self.subscreens[subscreen as usize].rect.height;
                    let n = &mut self.nodes[node];
                    n.active = Some(Active {
                        subscreen,
                        next_row: 0,
                        end_row: height,
                        in_hand: 0,
                        ready_band: None,
                        cursor: 0,
                    });
                    n.times.subscreens += 1;
                    self.advance(node, now);
                }
                Event::RowDone { node } => {
                    self.send_row(node, now);
                    self.advance(node, now);
                }
                Event::RowAtFork { subscreen } => {
                    let h = &mut self.held[subscreen as usize];
                    h.rows_arrived += 1;
                    h.done_ns = now;
                    self.rows_missing -= 1;
                    if self.rows_missing == 0 {
                        return now;
                    }
                    if self.config.adaptive && self.idle_may_work() {
                        self.ask_give_back(now);
                    }
                }
                Event::DataAtFork { node, item } => self.serve(node, item, now),
                Event::DataAtNode { node, item } => {
                    let bytes = self.bytes_of(item);
                    let n = &mut self.nodes[node];
                    n.cache
                        .as_mut()
                        .expect("only demand transfer fetches")
                        .insert(item, bytes);
                    n.times.fetches += 1;
                    n.times.fetched_bytes += bytes;
                    self.advance(node, now);
                }
                Event::GiveBackAtNode { node, subscreen } => self.give_back(node, subscreen, now),
                Event::ReturnedAtHost {
                    node,
                    subscreen,
                    from_row,
                } => self.returned(node, subscreen, from_row, now),
            }
        }
        debug_assert_eq!(self.rows_missing, 0, "the events ran out before the image");
        now
    }

    /// A render node goes on from where it is until it must wait for something.
    fn advance(&mut self, node: usize, now: u64) {
        loop {
            let n = &mut self.nodes[node];
            let Some(a) = n.active.as_mut() else {
                let finished = n.finished.take();
                n.enter(Phase::Idle, now);
                let msg = Message::SubscreenRequest {
                    finished,
                    ahead: false,
                };
                let bytes = wire(n.id, 0, &msg, 0);
                let at = self.net.send(&n.to_host, bytes, now);
                self.queue.at(at, Event::RequestAtHost { node, finished });
                return;
            };
            if a.next_row >= a.end_row {
                n.finished = Some(a.subscreen);
                n.active = None;
                continue;
            }
            let sub = &self.subscreens[a.subscreen as usize];
            let (band_index, row_in_band) = sub
                .band_of(a.next_row)
                .expect("rows to begin are inside the subscreen");
            let band = &sub.bands[band_index];
            if a.ready_band != Some(band_index) {
                if let Some(cache) = n.cache.as_mut() {
                    let items = band
                        .chunks
                        .iter()
                        .map(|&c| Item::Chunk(c))
                        .chain(band.tiles.iter().map(|&t| Item::Tile(t)));
                    if let Some(missing) = items.skip(a.cursor).find(|&item| {
                        let hit = cache.touch(item);
                        if hit {
                            a.cursor += 1;
                        }
                        !hit
                    }) {
                        // Blocked until it arrives; then the check goes on from here.
                        n.enter(Phase::Waiting, now);
                        let Transfer::Demand { via, .. } = self.config.transfer else {
                            unreachable!("a cache means demand transfer")
                        };
                        let msg = Message::DataRequest {
                            id: data_id(missing),
                            transfer: via,
                            owner: self.fork_ids[owner_card(missing, self.fork_ids.len())],
                        };
                        let bytes = wire(n.id, 0, &msg, 0);
                        let at = self.net.send(&n.to_fork, bytes, now);
                        self.queue.at(
                            at,
                            Event::DataAtFork {
                                node,
                                item: missing,
                            },
                        );
                        return;
                    }
                }
                a.ready_band = Some(band_index);
                a.cursor = 0;
            }
            let band_ns = (band.cpu_s * self.config.cpu_scale * 1e9).round().max(0.0) as u128;
            let rows = band.rows as u128;
            let k = row_in_band as u128;
            let row_ns = (band_ns * (k + 1) / rows - band_ns * k / rows) as u64;
            a.in_hand = a.next_row;
            a.next_row += 1;
            n.enter(Phase::Busy, now);
            self.queue
                .at(now.saturating_add(row_ns), Event::RowDone { node });
            return;
        }
    }

    /// A rendered scan line goes through the mesh to the node's fork node.
    fn send_row(&mut self, node: usize, now: u64) {
        let n = &mut self.nodes[node];
        let a = n
            .active
            .as_ref()
            .expect("a row is done only while rendering");
        let rect = self.subscreens[a.subscreen as usize].rect;
        let msg = Message::Pixels {
            subscreen: a.subscreen,
            y: rect.y + a.in_hand,
            x: rect.x,
            width: rect.width,
        };
        let bytes = wire(n.id, 0, &msg, 12 * rect.width as u64);
        // The fork node passes the line on to the host outside the link model: only the
        // real cost of one more message (zero unless overheads are given).
        let at = self.net.send(&n.to_fork, bytes, now) + self.config.overheads.hop_ns;
        n.times.rows += 1;
        let subscreen = a.subscreen;
        self.queue.at(at, Event::RowAtFork { subscreen });
    }

    /// The fork node answers a demand request: over the G-bus first if another card holds
    /// the item, then by DMA (the card's one bus) or back through the mesh.
    fn serve(&mut self, node: usize, item: Item, now: u64) {
        let bytes = self.bytes_of(item);
        let card = self.nodes[node].card;
        let ready = self.bring_to_card(item, card, now);
        self.transfers += 1;
        let Transfer::Demand { via, .. } = self.config.transfer else {
            unreachable!("only demand transfer fetches")
        };
        let at = match via {
            Via::Dma => {
                self.bytes.dma += bytes;
                let sent = if self.model.links_delayed() {
                    self.dma[card].book(ready, self.model.dma_ns(bytes))
                } else {
                    ready
                };
                sent + self.config.overheads.hop_ns
            }
            Via::Serial => {
                self.bytes.mesh += bytes;
                let msg = Message::DataReply { id: data_id(item) };
                let size = wire(0, self.nodes[node].id, &msg, bytes);
                self.net.send(&self.nodes[node].from_fork, size, ready)
            }
        };
        self.queue.at(at, Event::DataAtNode { node, item });
    }

    /// A request for work reaches the host.
    fn request(&mut self, node: usize, finished: Option<u32>, now: u64) {
        if let Some(f) = finished
            && self.held[f as usize].node == Some(node)
        {
            self.held[f as usize].giving_back = false;
        }
        // It asks only once it has finished: whatever it held, it holds no more.
        let n = &mut self.nodes[node];
        if std::mem::take(&mut n.holding)
            && let Some(m) = n.machine
        {
            self.at_work[m] -= 1;
        }
        self.parked.push_back(node);
        self.hand_out(now);
        if self.config.adaptive && self.idle_may_work() {
            self.ask_give_back(now);
        }
    }

    /// Whether `node` may be handed work now: its machine, if it shares one, has fewer of
    /// its nodes holding work than it lets (a node that asks holds none here).
    fn may_work(&self, node: usize) -> bool {
        self.nodes[node]
            .machine
            .is_none_or(|m| self.at_work[m] < self.limits[m])
    }

    /// Whether a node waiting for work could take some.
    fn idle_may_work(&self) -> bool {
        self.parked.iter().any(|&n| self.may_work(n))
    }

    /// Pairs waiting requests with queued subscreens in plan order, as the host does: of
    /// the nodes that may work, those that rendered before first (their caches hold the
    /// scene), then first asker first.
    fn hand_out(&mut self, now: u64) {
        while !self.waiting_list.is_empty() {
            let Some(at) = (self.parked.iter())
                .position(|&n| self.nodes[n].rendered_before && self.may_work(n))
                .or_else(|| self.parked.iter().position(|&n| self.may_work(n)))
            else {
                break;
            };
            let node = self.parked.remove(at).expect("a parked request");
            let n = &mut self.nodes[node];
            n.holding = true;
            n.rendered_before = true;
            if let Some(m) = n.machine {
                self.at_work[m] += 1;
            }
            let id = self.waiting_list.pop_front().expect("not empty");
            self.held[id as usize] = Held {
                node: Some(node),
                giving_back: false,
                refused: false,
                handed_ns: now,
                ..self.held[id as usize]
            };
            let n = &self.nodes[node];
            let msg = Message::Subscreen {
                id,
                rect: self.subscreens[id as usize].rect,
            };
            let at = self.net.send(&n.from_host, wire(0, n.id, &msg, 0), now);
            self.queue.at(
                at,
                Event::AnswerAtNode {
                    node,
                    subscreen: id,
                },
            );
        }
    }

    /// Asks the node with the most rows still missing to give half back, unless one is asked.
    fn ask_give_back(&mut self, now: u64) {
        if self.held.iter().any(|h| h.giving_back) {
            return;
        }
        let best = self
            .held
            .iter()
            .enumerate()
            .filter(|(_, h)| h.node.is_some())
            .map(|(i, h)| (self.subscreens[i].rect.height - h.rows_arrived, i))
            .filter(|&(rows, _)| rows >= 2)
            .max();
        if let Some((_, i)) = best {
            if self.held[i].refused {
                return;
            }
            self.held[i].giving_back = true;
            let node = self.held[i].node.expect("filtered on a node");
            let msg = Message::GiveBack {
                subscreen: i as u32,
            };
            let n = &self.nodes[node];
            let at = self.net.send(&n.from_host, wire(0, n.id, &msg, 0), now);
            self.queue.at(
                at,
                Event::GiveBackAtNode {
                    node,
                    subscreen: i as u32,
                },
            );
        }
    }

    /// The render node halves what it has not begun of `subscreen` and says where it cut.
    fn give_back(&mut self, node: usize, subscreen: u32, now: u64) {
        let n = &mut self.nodes[node];
        let from_row = match n.active.as_mut() {
            Some(a) if a.subscreen == subscreen => {
                if a.end_row <= a.next_row + 1 {
                    a.end_row
                } else {
                    a.end_row = a.next_row + (a.end_row - a.next_row).div_ceil(2);
                    a.end_row
                }
            }
            _ => u32::MAX,
        };
        let msg = Message::Returned {
            subscreen,
            from_row,
        };
        let at = self.net.send(&n.to_host, wire(n.id, 0, &msg, 0), now);
        self.queue.at(
            at,
            Event::ReturnedAtHost {
                node,
                subscreen,
                from_row,
            },
        );
    }

    /// The host queues the rows given back as a subscreen of their own.
    fn returned(&mut self, node: usize, subscreen: u32, from_row: u32, now: u64) {
        let id = subscreen as usize;
        if self.held[id].node != Some(node) {
            return;
        }
        self.held[id].giving_back = false;
        if let Some(tail) = self.subscreens[id].split_off(from_row) {
            self.subscreens.push(tail);
            self.held.push(Held::default());
            self.split += 1;
            self.waiting_list
                .push_back(self.subscreens.len() as u32 - 1);
        } else {
            self.held[id].refused = true;
        }
        self.hand_out(now);
        if self.idle_may_work() {
            self.ask_give_back(now);
        }
    }

    fn result(mut self, total_ns: u64) -> SimResult {
        let s = |ns: u64| ns as f64 * 1e-9;
        let nodes = self
            .nodes
            .iter_mut()
            .map(|n| {
                n.enter(Phase::Idle, total_ns);
                let mut t = n.times.clone();
                t.busy_s = s(n.spent[Phase::Busy as usize]);
                t.waiting_s = s(n.spent[Phase::Waiting as usize]);
                t.idle_s = s(n.spent[Phase::Idle as usize]);
                t.evictions = n.cache.as_ref().map_or(0, |c| c.evictions);
                t
            })
            .collect();
        SimResult {
            total_s: s(total_ns),
            total_ns,
            render_nodes: self.nodes.len(),
            subscreens: self.subscreens.len() as u32,
            subscreens_split: self.split,
            transfers: self.transfers,
            bytes: self.bytes,
            messages: self.net.messages,
            mesh_wire_bytes: self.net.wire_bytes,
            events: self.events,
            nodes,
            spans_ns: self.held.iter().map(|h| (h.handed_ns, h.done_ns)).collect(),
        }
    }
}
