//! Which render node renders which part of the image: the host's decisions during a cluster
//! render, apart from the messages that carry them.
//!
//! The paper's host hands out subscreens as render nodes ask (simple dynamic load balancing)
//! and, with adaptive redivision, asks the busiest node to give back the unbegun half of its
//! subscreen when a node would otherwise wait. On top of that the host takes back the work of
//! a lost render node, answers a repeated request as it answered it the first time, and says
//! what it waits for when no pixel arrives. Those rules are easy to get subtly wrong and hard
//! to reach with real processes, so they live here as a state machine that does no I/O and
//! never reads the clock: [`Scheduler`] takes events (a request, pixels, a returned half, a
//! lost node, the time passing) with the time as a value, and answers with [`Action`]s that
//! `distributed` carries out. Tests drive it with a made-up clock.

use std::{
    collections::{HashMap, HashSet, VecDeque},
    fmt,
    time::{Duration, Instant},
};

use protocol::{NodeId, Rect};

/// How long the render may go without a pixel before the host says what it waits for.
pub const STALL_REPORT: Duration = Duration::from_secs(10);

/// After a node is lost, rows of a finished subscreen that have not arrived this long after
/// its node finished it are taken as lost on the way (in the dead node) and rendered again.
pub const LOST_ROWS_GRACE: Duration = Duration::from_secs(2);

/// How often, once a node was lost, finished subscreens are checked for rows that never came.
const LOST_ROWS_SWEEP: Duration = Duration::from_millis(250);

/// A render node's request for work. A node repeats a request with the same tag when it
/// cannot know whether the first one (or its answer) got through, so the tag names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Request {
    pub node: NodeId,
    pub tag: u32,
}

/// What a request for work is answered with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Answer {
    Subscreen {
        id: u32,
        rect: Rect,
    },
    NoMoreWork,
    /// To a request ahead (its node still renders): nothing is queued now.
    NothingAhead,
}

/// What the host is to do after an event.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    /// Answer `request` with `answer`.
    Answer { request: Request, answer: Answer },
    /// Ask `node` to give back the rows of `subscreen` it has not begun.
    GiveBack { node: NodeId, subscreen: u32 },
    /// Copy these pixels of the run that just arrived into the image; the run's other pixels
    /// were there already, and the first copy of a pixel is the one kept.
    Store { x: u32, y: u32, width: u32 },
    /// The first pixels of `subscreen` since it was handed to `node` arrived: it is rendering.
    FirstPixels { node: NodeId, subscreen: u32 },
    /// `node` (lost) held `subscreens` subscreens with rows missing; they are queued again.
    Reassigned { node: NodeId, subscreens: u32 },
    /// Rows of a finished `subscreen` never arrived (lost with a node on their way); they are
    /// queued again.
    RowsNeverArrived { subscreen: u32 },
    /// No pixel arrived for [`STALL_REPORT`]; what the host waits for.
    Stalled(StallReport),
    /// Every pixel of the image has arrived.
    Complete,
}

/// What the host waits for when no pixel arrives.
#[derive(Clone, Debug, PartialEq)]
pub struct StallReport {
    pub silent_for: Duration,
    pub missing: u64,
    /// Subscreens with rows still missing, in id order, and who holds each.
    pub not_done: Vec<(u32, Holder)>,
    /// Nodes whose requests for work are not answered yet, first asker first.
    pub waiting: Vec<NodeId>,
}

/// Where a subscreen with missing rows is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Holder {
    /// Not handed to any node (yet or again).
    Queued,
    Rendering(NodeId),
    /// Its node said it sent every row, yet some have not arrived.
    Finished(NodeId),
}

impl fmt::Display for StallReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let not_done: Vec<String> = self
            .not_done
            .iter()
            .map(|(id, holder)| match holder {
                Holder::Rendering(n) => format!("{id}@{n}"),
                Holder::Finished(n) => format!("{id}@{n}(finished)"),
                Holder::Queued => format!("{id}(queued)"),
            })
            .collect();
        write!(
            f,
            "no pixels for {:?}: {} missing; subscreens not done: {}; nodes waiting for work: {:?}",
            self.silent_for,
            self.missing,
            not_done.join(" "),
            self.waiting
        )
    }
}

/// Which queued subscreen a render node asking for work gets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Order {
    /// The paper's: the next in line, whoever asks.
    #[default]
    Plain,
    /// Near the node's last subscreen, so that its cache already holds much of what the
    /// next one needs; each node's first pick spread over the image. Rows taken back from a
    /// lost node still go first.
    Local,
}

impl std::str::FromStr for Order {
    type Err = UnknownOrder;
    fn from_str(s: &str) -> Result<Order, UnknownOrder> {
        match s {
            "plain" => Ok(Order::Plain),
            "local" => Ok(Order::Local),
            _ => Err(UnknownOrder(s.to_string())),
        }
    }
}

impl std::fmt::Display for Order {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Order::Plain => "plain",
            Order::Local => "local",
        })
    }
}

#[derive(Debug, thiserror::Error)]
#[error("unknown subscreen order {0:?} (plain or local)")]
pub struct UnknownOrder(String);

/// What the scheduler starts from.
#[derive(Clone, Debug)]
pub struct Plan {
    pub width: u32,
    pub height: u32,
    /// The subscreens, in the order they are handed out; their ids are their places here.
    pub subscreens: Vec<Rect>,
    pub render_nodes: Vec<NodeId>,
    /// Adaptive redivision: a node that would wait makes the busiest give back half.
    pub adaptive: bool,
    pub order: Order,
    /// Render nodes that share a machine and how many of them may hold work at once; a node
    /// on none of them is not limited.
    pub machines: Vec<Machine>,
}

/// Render nodes on one machine, of which at most `at_work` hold work at once.
///
/// The paper's render nodes each had a processor of their own; on today's machines many may
/// share a few cores (the paper's 80 on a laptop). Rendering on more of them at once than
/// the machine has cores only makes them take turns: each touches the scene (faults a
/// shared segment into its page tables, or fetches it over a socket) and the caches and
/// scheduler of the machine are shared among more of them, for no more work done. So the
/// host hands work to at most `at_work` of them; the others wait for work as they would at
/// the end of a frame, and stand in for one that is lost.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Machine {
    pub nodes: Vec<NodeId>,
    pub at_work: usize,
}

/// How many render nodes of one machine the host lets work at once.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AtWork {
    /// By the CPUs the machine's render nodes report ([`machines`]), unless nodes wait
    /// rather than compute: every node with a link model (as the paper's did), or with a
    /// cache smaller than the scene fetched over sockets (forced TCP, fetches through the
    /// mesh, or nodes on more than one machine). See [`resolve_at_work`].
    #[default]
    Auto,
    /// By the CPUs the machine's render nodes report, whatever the link model.
    Cpus,
    /// Every render node, as in the paper.
    All,
    /// At most this many on each machine.
    Count(u32),
}

impl std::str::FromStr for AtWork {
    type Err = UnknownAtWork;
    fn from_str(s: &str) -> Result<AtWork, UnknownAtWork> {
        match s {
            "auto" => Ok(AtWork::Auto),
            "cpus" => Ok(AtWork::Cpus),
            "all" => Ok(AtWork::All),
            _ => match s.parse::<u32>() {
                Ok(n) if n > 0 => Ok(AtWork::Count(n)),
                _ => Err(UnknownAtWork(s.to_string())),
            },
        }
    }
}

impl fmt::Display for AtWork {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            AtWork::Auto => f.write_str("auto"),
            AtWork::Cpus => f.write_str("cpus"),
            AtWork::All => f.write_str("all"),
            AtWork::Count(n) => write!(f, "{n}"),
        }
    }
}

#[derive(Debug, thiserror::Error)]
#[error("unknown number of render nodes at work {0:?} (auto, cpus, all or a number above 0)")]
pub struct UnknownAtWork(String);

/// A render node as the machine limit sees it.
#[derive(Clone, Debug)]
pub struct NodeMachine<'a> {
    pub node: NodeId,
    /// Which boot of which machine it runs on; empty when unknown.
    pub machine: &'a str,
    /// CPUs the node's process may run on.
    pub cpus: u32,
    /// CPUs online on its machine.
    pub machine_cpus: u32,
}

/// Groups render nodes by machine, each machine letting as many work at once as `at_work`
/// says. With [`AtWork::Cpus`] that is the CPUs the machine's nodes may use between them
/// (at most the machine's; a node limited to one CPU by its container adds one) over the
/// rendering threads of a node. Machines with no more nodes than that, and nodes whose
/// machine is unknown, are not limited. `Auto` and `All` take no limit: the caller decides
/// what `Auto` is.
pub fn machines(nodes: &[NodeMachine<'_>], at_work: AtWork, threads_per_node: u32) -> Vec<Machine> {
    let mut by_machine: Vec<(&str, Vec<&NodeMachine<'_>>)> = Vec::new();
    for n in nodes.iter().filter(|n| !n.machine.is_empty()) {
        match by_machine.iter_mut().find(|(m, _)| *m == n.machine) {
            Some((_, members)) => members.push(n),
            None => by_machine.push((n.machine, vec![n])),
        }
    }
    by_machine
        .into_iter()
        .filter_map(|(_, members)| {
            let limit = match at_work {
                AtWork::Auto | AtWork::All => return None,
                AtWork::Count(n) => n as usize,
                AtWork::Cpus => {
                    let machine = members.iter().map(|n| n.machine_cpus).max().unwrap_or(1);
                    let usable = members
                        .iter()
                        .map(|n| n.cpus as u64)
                        .sum::<u64>()
                        .min(machine as u64);
                    (usable.div_ceil(threads_per_node.max(1) as u64) as usize).max(1)
                }
            };
            (members.len() > limit).then(|| Machine {
                nodes: members.iter().map(|n| n.node).collect(),
                at_work: limit,
            })
        })
        .collect()
}

/// Whether render and fork nodes see more than one shared memory (`fabric::shm::domain`:
/// more than one machine, or containers with a `/dev/shm` each), or one of them none, so
/// that some render node's demand fetches must cross a socket: a card's segment can be
/// mapped only where its fork node's shared memory is seen.
pub fn spans_shared_memories<'a>(domains: impl IntoIterator<Item = &'a str>) -> bool {
    let mut first = None;
    for id in domains {
        if id.is_empty() || *first.get_or_insert(id) != id {
            return true;
        }
    }
    false
}

/// What [`AtWork::Auto`] comes to for one render: every node at work where nodes wait
/// rather than compute (a link model, as the paper's nodes did, or a cache smaller than the
/// scene whose misses cross sockets: more nodes at work fill each other's waits), else as
/// many as the CPUs. Any other choice stands as given.
pub fn resolve_at_work(at_work: AtWork, link_model: bool, misses_cross_sockets: bool) -> AtWork {
    match at_work {
        AtWork::Auto if link_model || misses_cross_sockets => AtWork::All,
        AtWork::Auto => AtWork::Cpus,
        at_work => at_work,
    }
}

/// Which pixels of the image have arrived. The pixels themselves stay with the caller: the
/// decisions need only whether a row is complete.
#[derive(Clone, Debug)]
struct Arrived {
    width: u32,
    height: u32,
    have: Vec<bool>,
    missing: u64,
}

impl Arrived {
    fn new(width: u32, height: u32) -> Arrived {
        let total = width as u64 * height as u64;
        Arrived {
            width,
            height,
            have: vec![false; total as usize],
            missing: total,
        }
    }

    /// Marks a run of pixels as arrived; returns the spans of it that are new, as
    /// (x, width). A run outside the image is ignored whole.
    fn put(&mut self, x: u32, y: u32, width: u32) -> Vec<(u32, u32)> {
        let w = self.width;
        if y >= self.height || x >= w || width > w - x {
            return Vec::new();
        }
        let mut spans: Vec<(u32, u32)> = Vec::new();
        for px in x..x + width {
            let at = (y * w + px) as usize;
            if self.have[at] {
                continue;
            }
            self.have[at] = true;
            self.missing -= 1;
            match spans.last_mut() {
                Some((start, len)) if *start + *len == px => *len += 1,
                _ => spans.push((px, 1)),
            }
        }
        spans
    }

    fn row_missing(&self, r: Rect, y: u32) -> bool {
        (r.x..r.x + r.width).any(|x| !self.have[(y * self.width + x) as usize])
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

/// A subscreen and what the host knows of it.
#[derive(Clone, Debug)]
struct Subscreen {
    rect: Rect,
    /// The node it was last handed to; it stays after the node finishes, so that the rows
    /// still on their way are known to be that node's.
    node: Option<NodeId>,
    /// Whether pixels of it have arrived since it was last handed out.
    pixels_seen: bool,
    giving_back: bool,
    /// When its node said it had sent every row.
    finished_at: Option<Instant>,
    /// Queued again after its node was lost or its rows went missing: first in line in
    /// every order.
    again: bool,
}

impl Subscreen {
    fn new(rect: Rect) -> Subscreen {
        Subscreen {
            rect,
            node: None,
            pixels_seen: false,
            giving_back: false,
            finished_at: None,
            again: false,
        }
    }
}

/// The host's scheduling state during one frame.
///
/// Invariant kept after every event: either no subscreen is queued or every parked request
/// comes from a node whose machine already has its number of nodes at work (whatever can be
/// paired is paired at once).
#[derive(Debug)]
pub struct Scheduler {
    adaptive: bool,
    order: Order,
    render_nodes: HashSet<NodeId>,
    /// The render nodes in id order: where each one's first pick falls in `Order::Local`.
    node_order: Vec<NodeId>,
    /// Each node's last subscreen, for `Order::Local`.
    last_rect: HashMap<NodeId, Rect>,
    /// Per node, subscreens handed to it that it has not finished (nor lost).
    holding: HashMap<NodeId, u32>,
    /// Which of `machines` a node is on.
    machine_of: HashMap<NodeId, usize>,
    machines: Vec<Machine>,
    /// Per machine, its live nodes holding work.
    at_work: Vec<usize>,
    lost: HashSet<NodeId>,
    /// Whether rows may have been lost on their way (a node or a fork node was lost): the
    /// sweep for rows that never arrived runs from then on.
    rows_may_be_lost: bool,
    subscreens: Vec<Subscreen>,
    planned: u32,
    split: u32,
    queue: VecDeque<u32>,
    /// Requests for work not answered yet, first asker first.
    parked: VecDeque<Request>,
    /// Answers given, to repeat if the request comes again.
    answered: HashMap<Request, Answer>,
    arrived: Arrived,
    last_missing: u64,
    last_progress: Instant,
    last_sweep: Instant,
}

impl Scheduler {
    /// A fresh frame: every subscreen queued in plan order.
    pub fn new(plan: Plan, now: Instant) -> Scheduler {
        Scheduler::resume(plan, &[], now)
    }

    /// A frame of which the rows in `finished` are already in the image (read back from a
    /// checkpoint, say): only the rows still missing are queued, each subscreen cut to its
    /// runs of missing rows, and a subscreen with none is never handed out.
    pub fn resume(plan: Plan, finished: &[Rect], now: Instant) -> Scheduler {
        let mut arrived = Arrived::new(plan.width, plan.height);
        for r in finished {
            for y in r.y..r.y.saturating_add(r.height) {
                arrived.put(r.x, y, r.width);
            }
        }
        let planned = plan.subscreens.len() as u32;
        let mut subscreens = Vec::with_capacity(plan.subscreens.len());
        let mut extra = Vec::new();
        let mut queue = VecDeque::new();
        for (id, &rect) in plan.subscreens.iter().enumerate() {
            let runs = arrived.missing_runs(rect);
            match runs.split_first() {
                None => subscreens.push(Subscreen::new(rect)),
                Some((first, rest)) => {
                    subscreens.push(Subscreen::new(*first));
                    queue.push_back(id as u32);
                    extra.extend_from_slice(rest);
                }
            }
        }
        // Further runs get ids after the planned subscreens, so that planned ids stay the
        // places in the plan.
        for rect in extra {
            subscreens.push(Subscreen::new(rect));
            queue.push_back(subscreens.len() as u32 - 1);
        }
        let mut node_order = plan.render_nodes.clone();
        node_order.sort_unstable();
        node_order.dedup();
        Scheduler {
            adaptive: plan.adaptive,
            order: plan.order,
            node_order,
            last_rect: HashMap::new(),
            holding: HashMap::new(),
            machine_of: plan
                .machines
                .iter()
                .enumerate()
                .flat_map(|(m, machine)| machine.nodes.iter().map(move |&n| (n, m)))
                .collect(),
            at_work: vec![0; plan.machines.len()],
            machines: plan.machines,
            render_nodes: plan.render_nodes.into_iter().collect(),
            lost: HashSet::new(),
            rows_may_be_lost: false,
            subscreens,
            planned,
            split: 0,
            queue,
            parked: VecDeque::new(),
            answered: HashMap::new(),
            last_missing: arrived.missing,
            arrived,
            last_progress: now,
            last_sweep: now,
        }
    }

    /// Pixels still missing.
    pub fn missing(&self) -> u64 {
        self.arrived.missing
    }

    pub fn is_complete(&self) -> bool {
        self.arrived.missing == 0
    }

    /// Subscreens in the plan.
    pub fn planned(&self) -> u32 {
        self.planned
    }

    /// Subscreens split off by adaptive redivision.
    pub fn split(&self) -> u32 {
        self.split
    }

    /// Whether `request` waits for an answer.
    pub fn is_waiting(&self, request: Request) -> bool {
        self.parked.contains(&request)
    }

    /// Whether `node` may still be given work: a render node of the plan not lost.
    fn serves(&self, node: NodeId) -> bool {
        self.render_nodes.contains(&node) && !self.lost.contains(&node)
    }

    /// A render node asks for work, saying which subscreen it has just finished, if any.
    /// A request `ahead` comes from a node that still renders a subscreen: it gets a queued
    /// one or [`Answer::NothingAhead`] at once, and is neither parked nor a reason to split
    /// another node's work (the node is not idle). It gets one only while more are queued
    /// than there are render nodes: the last ones go to nodes that have finished, so that no
    /// node sits idle at the end while another holds a subscreen it has not begun, and none
    /// that started late is left without work.
    pub fn request(
        &mut self,
        request: Request,
        finished: Option<u32>,
        ahead: bool,
        now: Instant,
    ) -> Vec<Action> {
        let mut actions = Vec::new();
        if !self.serves(request.node) {
            return actions;
        }
        if let Some(&answer) = self.answered.get(&request) {
            // Sent again after a node was lost: the answer may have been lost too.
            actions.push(Action::Answer { request, answer });
            return actions;
        }
        if self.parked.contains(&request) {
            return actions;
        }
        if let Some(s) = finished.and_then(|id| self.subscreens.get_mut(id as usize))
            && s.node == Some(request.node)
            && s.finished_at.is_none()
        {
            s.finished_at = Some(now);
            s.giving_back = false;
            self.let_go(request.node);
        }
        if ahead && self.queue.len() <= self.workers() {
            let answer = Answer::NothingAhead;
            self.answered.insert(request, answer);
            actions.push(Action::Answer { request, answer });
            return actions;
        }
        // A queued subscreen means no request is parked: one ahead is served at once too.
        self.parked.push_back(request);
        self.hand_out(&mut actions);
        if self.adaptive && self.idle_may_work() {
            self.ask_give_back(&mut actions);
        }
        actions
    }

    /// How many nodes may render at once: the live ones, as many of each machine's as it
    /// lets work.
    fn workers(&self) -> usize {
        let live = |n: &&NodeId| !self.lost.contains(n);
        let on_machines: usize = self
            .machines
            .iter()
            .map(|m| m.nodes.iter().filter(live).count().min(m.at_work))
            .sum();
        let elsewhere = self
            .render_nodes
            .iter()
            .filter(live)
            .filter(|n| !self.machine_of.contains_key(n))
            .count();
        on_machines + elsewhere
    }

    /// Whether `node` may be handed work now: it holds some already, or its machine has
    /// fewer nodes at work than it lets work.
    fn may_work(&self, node: NodeId) -> bool {
        match self.machine_of.get(&node) {
            None => true,
            Some(&m) => {
                self.at_work[m] < self.machines[m].at_work
                    || self.holding.get(&node).is_some_and(|&n| n > 0)
            }
        }
    }

    /// Whether a node that waits for work could take some: one the machine lets work.
    fn idle_may_work(&self) -> bool {
        self.parked.iter().any(|r| self.may_work(r.node))
    }

    /// `node` now holds one more subscreen.
    fn hold(&mut self, node: NodeId) {
        let held = self.holding.entry(node).or_default();
        *held += 1;
        if *held == 1
            && let Some(&m) = self.machine_of.get(&node)
        {
            self.at_work[m] += 1;
        }
    }

    /// `node` no longer holds one of its subscreens (finished, or taken back).
    fn let_go(&mut self, node: NodeId) {
        if let Some(held) = self.holding.get_mut(&node)
            && *held > 0
        {
            *held -= 1;
            if *held == 0
                && let Some(&m) = self.machine_of.get(&node)
            {
                self.at_work[m] -= 1;
            }
        }
    }

    /// `node` gave back the rows of `subscreen` from `from_row` on (relative to its top); a
    /// `from_row` at or past its height means it had begun them all.
    pub fn returned(&mut self, node: NodeId, subscreen: u32, from_row: u32) -> Vec<Action> {
        let mut actions = Vec::new();
        if !self.serves(node) {
            return actions;
        }
        let Some(s) = self.subscreens.get_mut(subscreen as usize) else {
            return actions;
        };
        if s.node != Some(node) {
            return actions;
        }
        s.giving_back = false;
        if from_row < s.rect.height {
            let r = s.rect;
            s.rect.height = from_row;
            self.subscreens.push(Subscreen::new(Rect {
                x: r.x,
                y: r.y + from_row,
                width: r.width,
                height: r.height - from_row,
            }));
            self.split += 1;
            self.queue.push_back(self.subscreens.len() as u32 - 1);
        }
        self.hand_out(&mut actions);
        if self.idle_may_work() {
            self.ask_give_back(&mut actions);
        }
        actions
    }

    /// A run of `width` pixels at (x, y) arrived, rendered for `subscreen`. Pixels count from
    /// whoever sends them, a lost node too: they are as good as anyone's.
    pub fn pixels(&mut self, subscreen: u32, x: u32, y: u32, width: u32) -> Vec<Action> {
        let mut actions: Vec<Action> = self
            .arrived
            .put(x, y, width)
            .into_iter()
            .map(|(x, width)| Action::Store { x, y, width })
            .collect();
        if actions.is_empty() {
            return actions;
        }
        if let Some(s) = self.subscreens.get_mut(subscreen as usize)
            && !s.pixels_seen
        {
            s.pixels_seen = true;
            if let Some(node) = s.node {
                actions.push(Action::FirstPixels { node, subscreen });
            }
        }
        if self.is_complete() {
            actions.push(Action::Complete);
        }
        actions
    }

    /// `node` is lost: its waiting requests are dropped and its subscreens with rows still
    /// missing go back to the queue, first in line.
    pub fn node_lost(&mut self, node: NodeId) -> Vec<Action> {
        if !self.serves(node) {
            return Vec::new();
        }
        self.lost.insert(node);
        self.parked.retain(|r| r.node != node);
        let mut actions = self.take_back(node);
        // Subscreens whose every row came in before it said it finished are not taken
        // back, yet it works no more: its place at work goes to another.
        while self.holding.get(&node).is_some_and(|&n| n > 0) {
            self.let_go(node);
        }
        self.hand_out(&mut actions);
        actions
    }

    /// Queues again, first in line, the rows still missing of every subscreen `node` was
    /// given, and hands them out. Losing the node is one reason; rows on their way lost
    /// while the node goes on (its fork node lost and the node re-homed to another) are
    /// another, which is why the node is not declared lost here. Either way, rows may have
    /// been lost on their way, so the sweep of `tick` runs from now on.
    pub fn take_back(&mut self, node: NodeId) -> Vec<Action> {
        self.rows_may_be_lost = true;
        let mut subscreens = 0;
        for id in 0..self.subscreens.len() {
            let s = &self.subscreens[id];
            if s.node == Some(node) && self.arrived.rows_missing(s.rect) > 0 {
                subscreens += 1;
                self.requeue_missing(id);
            }
        }
        let mut actions = vec![Action::Reassigned { node, subscreens }];
        self.hand_out(&mut actions);
        actions
    }

    /// The time is `now`: reports a stall, and once a node was lost, queues again the rows of
    /// finished subscreens that never arrived. Call it after every event and at least every
    /// few hundred milliseconds.
    pub fn tick(&mut self, now: Instant) -> Vec<Action> {
        let mut actions = Vec::new();
        if self.arrived.missing != self.last_missing {
            self.last_missing = self.arrived.missing;
            self.last_progress = now;
        } else if now.saturating_duration_since(self.last_progress) > STALL_REPORT {
            self.last_progress = now;
            actions.push(Action::Stalled(self.stall_report()));
        }
        // Once a node was lost, rows may have been lost with it on their way to the frame
        // buffer (or a give-back with its answer): finished subscreens still missing rows
        // are rendered again.
        if self.rows_may_be_lost && now.saturating_duration_since(self.last_sweep) > LOST_ROWS_SWEEP
        {
            self.last_sweep = now;
            for id in 0..self.subscreens.len() {
                let s = &self.subscreens[id];
                if s.finished_at
                    .is_some_and(|t| now.saturating_duration_since(t) > LOST_ROWS_GRACE)
                    && self.arrived.rows_missing(s.rect) > 0
                {
                    actions.push(Action::RowsNeverArrived {
                        subscreen: id as u32,
                    });
                    self.requeue_missing(id);
                }
            }
            self.hand_out(&mut actions);
        }
        actions
    }

    /// The frame is over: every request still waiting is told there is no more work.
    pub fn finish(&mut self) -> Vec<Action> {
        self.parked
            .drain(..)
            .map(|request| Action::Answer {
                request,
                answer: Answer::NoMoreWork,
            })
            .collect()
    }

    fn stall_report(&self) -> StallReport {
        let not_done = self
            .subscreens
            .iter()
            .enumerate()
            .filter(|(_, s)| self.arrived.rows_missing(s.rect) > 0)
            .map(|(id, s)| {
                let holder = match (s.node, s.finished_at) {
                    (Some(n), None) => Holder::Rendering(n),
                    (Some(n), Some(_)) => Holder::Finished(n),
                    (None, _) => Holder::Queued,
                };
                (id as u32, holder)
            })
            .collect();
        StallReport {
            silent_for: STALL_REPORT,
            missing: self.arrived.missing,
            not_done,
            waiting: self.parked.iter().map(|r| r.node).collect(),
        }
    }

    /// Pairs waiting requests with queued subscreens, of the nodes that may work: nodes that
    /// rendered before first (their caches hold the scene, and a node that finished and asks
    /// again keeps its place at work), then first asker first.
    fn hand_out(&mut self, actions: &mut Vec<Action>) {
        while !self.queue.is_empty() {
            let may_work = |r: &Request| self.may_work(r.node);
            let Some(at) = (self.parked.iter())
                .position(|r| self.last_rect.contains_key(&r.node) && may_work(r))
                .or_else(|| self.parked.iter().position(may_work))
            else {
                break;
            };
            let request = self.parked.remove(at).expect("a parked request");
            let at = self.choose(request.node);
            let id = self.queue.remove(at).expect("a place in the queue");
            let s = &mut self.subscreens[id as usize];
            s.node = Some(request.node);
            s.pixels_seen = false;
            s.finished_at = None;
            s.giving_back = false;
            s.again = false;
            let rect = s.rect;
            self.last_rect.insert(request.node, rect);
            self.hold(request.node);
            let answer = Answer::Subscreen { id, rect };
            self.answered.insert(request, answer);
            actions.push(Action::Answer { request, answer });
        }
    }

    /// Which queued subscreen `node` gets, as a place in the (non-empty) queue. The one
    /// place where the choice is made (a later one could weigh what the node's cache holds,
    /// or fetch ahead for).
    fn choose(&self, node: NodeId) -> usize {
        if self.order == Order::Plain {
            return 0;
        }
        // Work taken back from a lost node is what the frame waits for: it goes first.
        if let Some(at) = self
            .queue
            .iter()
            .position(|&id| self.subscreens[id as usize].again)
        {
            return at;
        }
        let center = |r: Rect| {
            (
                2 * r.x as i64 + r.width as i64,
                2 * r.y as i64 + r.height as i64,
            )
        };
        match self.last_rect.get(&node) {
            Some(&last) => {
                let (cx, cy) = center(last);
                let distance = |id: u32| {
                    let (x, y) = center(self.subscreens[id as usize].rect);
                    (x - cx).pow(2) + (y - cy).pow(2)
                };
                // The nearest; of equals, the first in line.
                (0..self.queue.len())
                    .min_by_key(|&at| (distance(self.queue[at]), at))
                    .unwrap_or(0)
            }
            None => {
                let k = self.node_order.iter().position(|&n| n == node).unwrap_or(0);
                k * self.queue.len() / self.node_order.len().max(1)
            }
        }
    }

    /// Puts the rows of subscreen `id` that still miss pixels back in the queue, first in
    /// line: the first run of them under the same id, any further runs as new subscreens.
    fn requeue_missing(&mut self, id: usize) {
        let runs = self.arrived.missing_runs(self.subscreens[id].rect);
        let Some((first, rest)) = runs.split_first() else {
            return;
        };
        if let Some(node) = self.subscreens[id].node
            && self.subscreens[id].finished_at.is_none()
        {
            self.let_go(node);
        }
        self.subscreens[id] = Subscreen {
            again: true,
            ..Subscreen::new(*first)
        };
        self.queue.retain(|&q| q as usize != id);
        self.queue.push_front(id as u32);
        for r in rest {
            self.subscreens.push(Subscreen {
                again: true,
                ..Subscreen::new(*r)
            });
            self.queue.push_front(self.subscreens.len() as u32 - 1);
        }
    }

    /// Asks the node with the most rows still to render to give half of them back, unless
    /// a node is already asked.
    fn ask_give_back(&mut self, actions: &mut Vec<Action>) {
        if self.subscreens.iter().any(|s| s.giving_back) {
            return;
        }
        let best = self
            .subscreens
            .iter()
            .enumerate()
            .filter(|(_, s)| s.node.is_some())
            .map(|(i, s)| (self.arrived.rows_missing(s.rect), i))
            .filter(|&(rows, _)| rows >= 2)
            .max();
        if let Some((_, i)) = best {
            let s = &mut self.subscreens[i];
            s.giving_back = true;
            if let Some(node) = s.node {
                actions.push(Action::GiveBack {
                    node,
                    subscreen: i as u32,
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: NodeId = 5;
    const B: NodeId = 6;

    fn rect(x: u32, y: u32, width: u32, height: u32) -> Rect {
        Rect {
            x,
            y,
            width,
            height,
        }
    }

    /// An image `width` wide cut into bands of `rows` rows, one subscreen each, for nodes
    /// A and B.
    fn plan(width: u32, bands: &[u32], adaptive: bool) -> Plan {
        let mut subscreens = Vec::new();
        let mut y = 0;
        for &rows in bands {
            subscreens.push(rect(0, y, width, rows));
            y += rows;
        }
        Plan {
            width,
            height: y,
            subscreens,
            render_nodes: vec![A, B],
            adaptive,
            order: Order::Plain,
            machines: Vec::new(),
        }
    }

    /// A made-up clock: the scheduler only ever sees the instants it is given.
    struct Clock(Instant);

    impl Clock {
        fn at(&self, ms: u64) -> Instant {
            self.0 + Duration::from_millis(ms)
        }
    }

    fn ask(node: NodeId, tag: u32) -> Request {
        Request { node, tag }
    }

    fn given(request: Request, id: u32, rect: Rect) -> Action {
        Action::Answer {
            request,
            answer: Answer::Subscreen { id, rect },
        }
    }

    /// The pixels of rows `ys` of an image `width` wide, as a render node sends them.
    fn rows(
        s: &mut Scheduler,
        subscreen: u32,
        width: u32,
        ys: std::ops::Range<u32>,
    ) -> Vec<Action> {
        ys.flat_map(|y| s.pixels(subscreen, 0, y, width)).collect()
    }

    #[test]
    fn subscreens_go_out_in_plan_order_to_whoever_asks_first() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(4, &[2, 2, 2], false), clock.at(0));
        assert_eq!(
            s.request(ask(B, 1), None, false, clock.at(1)),
            vec![given(ask(B, 1), 0, rect(0, 0, 4, 2))]
        );
        assert_eq!(
            s.request(ask(A, 1), None, false, clock.at(2)),
            vec![given(ask(A, 1), 1, rect(0, 2, 4, 2))]
        );
        assert_eq!(
            s.request(ask(B, 2), Some(0), false, clock.at(3)),
            vec![given(ask(B, 2), 2, rect(0, 4, 4, 2))]
        );
        // Nothing left, and without adaptive redivision nobody is asked to share: A waits.
        assert_eq!(s.request(ask(A, 2), Some(1), false, clock.at(4)), vec![]);
        assert!(s.is_waiting(ask(A, 2)));
        assert_eq!((s.planned(), s.split()), (3, 0));
    }

    #[test]
    fn a_request_ahead_takes_a_queued_subscreen_or_is_told_nothing_at_once() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(4, &[2, 2, 2, 2, 2], true), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        assert_eq!(
            s.request(ask(A, 2), None, true, clock.at(1)),
            vec![given(ask(A, 2), 1, rect(0, 2, 4, 2))],
            "asked while rendering subscreen 0, with more queued than nodes: the next in line"
        );
        s.request(ask(B, 1), None, false, clock.at(1));
        let nothing = |tag| {
            vec![Action::Answer {
                request: ask(B, tag),
                answer: Answer::NothingAhead,
            }]
        };
        // Two queued for two nodes: they are kept for nodes that finish.
        assert_eq!(s.request(ask(B, 2), None, true, clock.at(2)), nothing(2));
        assert!(!s.is_waiting(ask(B, 2)));
        assert_eq!(
            s.request(ask(B, 2), None, true, clock.at(2)),
            nothing(2),
            "a repeat gets the same answer"
        );
        rows(&mut s, 2, 4, 4..6);
        assert_eq!(
            s.request(ask(B, 3), Some(2), false, clock.at(3)),
            vec![given(ask(B, 3), 3, rect(0, 6, 4, 2))]
        );
        rows(&mut s, 3, 4, 6..8);
        assert_eq!(
            s.request(ask(B, 4), Some(3), false, clock.at(4)),
            vec![given(ask(B, 4), 4, rect(0, 8, 4, 2))]
        );
        // Nothing queued: B, busy, is neither parked nor a reason for A to give back half,
        // although redivision is on.
        assert_eq!(s.request(ask(B, 5), None, true, clock.at(5)), nothing(5));
        // Once done, B asks as usual and makes A (which holds two subscreens it has not
        // begun) give back part of one.
        rows(&mut s, 4, 4, 8..10);
        let share = s.request(ask(B, 6), Some(4), false, clock.at(6));
        assert!(
            matches!(share[..], [Action::GiveBack { node: A, .. }]),
            "{share:?}"
        );
        assert!(s.is_waiting(ask(B, 6)));
    }

    #[test]
    fn a_lost_node_gives_up_the_subscreen_it_was_handed_ahead() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[1, 1, 1, 1], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(A, 2), None, true, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 2, 2, 2..3);
        s.request(ask(B, 2), Some(2), false, clock.at(1));
        rows(&mut s, 3, 2, 3..4);
        assert_eq!(s.request(ask(B, 3), Some(3), false, clock.at(1)), vec![]);
        // A rendered neither its subscreen nor the one it was handed ahead.
        let actions = s.node_lost(A);
        assert_eq!(
            actions,
            vec![
                Action::Reassigned {
                    node: A,
                    subscreens: 2
                },
                given(ask(B, 3), 1, rect(0, 1, 2, 1)),
            ]
        );
        assert_eq!(
            s.request(ask(B, 4), Some(1), false, clock.at(2)),
            vec![given(ask(B, 4), 0, rect(0, 0, 2, 1))]
        );
    }

    #[test]
    fn the_last_pixel_completes_the_frame_and_waiting_nodes_are_told_no_more_work() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(3, &[1, 1], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        assert_eq!(
            s.pixels(0, 0, 0, 3),
            vec![
                Action::Store {
                    x: 0,
                    y: 0,
                    width: 3
                },
                Action::FirstPixels {
                    node: A,
                    subscreen: 0
                }
            ]
        );
        assert_eq!(s.request(ask(A, 2), Some(0), false, clock.at(1)), vec![]);
        assert_eq!(s.missing(), 3);
        let last = s.pixels(1, 0, 1, 3);
        assert_eq!(last.last(), Some(&Action::Complete));
        assert!(s.is_complete());
        assert_eq!(
            s.finish(),
            vec![Action::Answer {
                request: ask(A, 2),
                answer: Answer::NoMoreWork
            }]
        );
        assert_eq!(s.finish(), vec![], "told once");
    }

    #[test]
    fn pixels_already_there_are_kept_and_only_new_ones_stored() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(6, &[1], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.pixels(0, 2, 0, 2);
        assert_eq!(
            s.pixels(0, 0, 0, 6),
            vec![
                Action::Store {
                    x: 0,
                    y: 0,
                    width: 2
                },
                Action::Store {
                    x: 4,
                    y: 0,
                    width: 2
                },
                Action::Complete
            ]
        );
        assert_eq!(s.pixels(0, 0, 0, 6), vec![], "complete only once");
    }

    #[test]
    fn an_idle_node_makes_the_busiest_give_back_half_when_adaptive() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[8, 2], true), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 1, 2, 8..10);
        // B is done and asks; A holds 8 rows still missing.
        assert_eq!(
            s.request(ask(B, 2), Some(1), false, clock.at(1)),
            vec![Action::GiveBack {
                node: A,
                subscreen: 0
            }]
        );
        // A repeat of the ask does not ask A twice.
        assert_eq!(s.request(ask(B, 3), None, false, clock.at(2)), vec![]);
        // A has begun 3 rows and gives back the other 5, split off as subscreen 2, which
        // goes to the first waiting request; for the second, B now holds the most rows.
        assert_eq!(
            s.returned(A, 0, 3),
            vec![
                given(ask(B, 2), 2, rect(0, 3, 2, 5)),
                Action::GiveBack {
                    node: B,
                    subscreen: 2
                }
            ]
        );
        assert_eq!(
            s.returned(B, 2, 2),
            vec![given(ask(B, 3), 3, rect(0, 5, 2, 3))]
        );
        assert_eq!((s.planned(), s.split()), (2, 2));
    }

    #[test]
    fn no_give_back_without_adaptive_nor_for_a_single_row() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[1], true), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        assert_eq!(s.request(ask(B, 1), None, false, clock.at(0)), vec![]);
        let mut s = Scheduler::new(plan(2, &[8], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        assert_eq!(s.request(ask(B, 1), None, false, clock.at(0)), vec![]);
    }

    #[test]
    fn a_node_lost_mid_subscreen_has_its_missing_rows_rendered_by_another() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[6, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        // A sent rows 0, 1 and 3 of its subscreen before it died.
        rows(&mut s, 0, 2, 0..2);
        rows(&mut s, 0, 2, 3..4);
        rows(&mut s, 1, 2, 6..8);
        assert_eq!(s.request(ask(B, 2), Some(1), false, clock.at(1)), vec![]);
        // Rows 2 and 4..6 are missing: the first run keeps id 0, the second becomes 2, and
        // the later run is first in line.
        assert_eq!(
            s.node_lost(A),
            vec![
                Action::Reassigned {
                    node: A,
                    subscreens: 1
                },
                given(ask(B, 2), 2, rect(0, 4, 2, 2)),
            ]
        );
        assert_eq!(
            s.request(ask(B, 3), Some(2), false, clock.at(2)),
            vec![given(ask(B, 3), 0, rect(0, 2, 2, 1))]
        );
        rows(&mut s, 2, 2, 4..6);
        assert_eq!(rows(&mut s, 0, 2, 2..3).last(), Some(&Action::Complete));
    }

    #[test]
    fn rows_taken_back_go_before_subscreens_never_handed_out() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2, 2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        s.node_lost(A);
        assert_eq!(
            s.request(ask(B, 2), None, false, clock.at(1)),
            vec![given(ask(B, 2), 0, rect(0, 0, 2, 2))]
        );
        assert_eq!(
            s.request(ask(B, 3), None, false, clock.at(2)),
            vec![given(ask(B, 3), 2, rect(0, 4, 2, 2))]
        );
    }

    #[test]
    fn work_taken_back_from_a_node_still_there_may_go_to_it_again() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 0, 2, 0..1);
        assert_eq!(
            s.take_back(A),
            vec![Action::Reassigned {
                node: A,
                subscreens: 1
            }]
        );
        assert_eq!(
            s.request(ask(A, 2), None, false, clock.at(1)),
            vec![given(ask(A, 2), 0, rect(0, 1, 2, 1))]
        );
    }

    #[test]
    fn once_work_is_taken_back_rows_that_never_came_are_rendered_again() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 0, 2, 0..2);
        // B says it finished, but a row went to a fork node that is lost.
        rows(&mut s, 1, 2, 2..3);
        s.request(ask(B, 2), Some(1), false, clock.at(1000));
        assert_eq!(s.tick(clock.at(5000)), vec![], "nothing suspected yet");
        // A's fork node is lost: A's work is taken back (none is missing), and from now
        // on finished subscreens missing rows are suspect.
        assert_eq!(
            s.take_back(A),
            vec![Action::Reassigned {
                node: A,
                subscreens: 0
            }]
        );
        assert_eq!(
            s.tick(clock.at(5001)),
            vec![
                Action::RowsNeverArrived { subscreen: 1 },
                given(ask(B, 2), 1, rect(0, 3, 2, 1)),
            ]
        );
    }

    #[test]
    fn a_node_lost_after_its_rows_arrived_leaves_nothing_to_redo() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 0, 2, 0..2);
        s.request(ask(A, 2), Some(0), false, clock.at(1));
        assert_eq!(
            s.node_lost(A),
            vec![Action::Reassigned {
                node: A,
                subscreens: 0
            }]
        );
        // Its waiting request went with it.
        assert!(!s.is_waiting(ask(A, 2)));
        assert_eq!(s.finish(), vec![]);
        assert_eq!(s.node_lost(A), vec![], "lost once");
    }

    #[test]
    fn a_node_lost_after_finishing_with_rows_on_the_way_has_them_redone() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 0, 2, 0..1);
        s.request(ask(A, 2), Some(0), false, clock.at(1));
        s.request(ask(B, 2), Some(1), false, clock.at(1));
        assert_eq!(
            s.node_lost(A),
            vec![
                Action::Reassigned {
                    node: A,
                    subscreens: 1
                },
                given(ask(B, 2), 0, rect(0, 1, 2, 1)),
            ]
        );
    }

    #[test]
    fn a_repeated_request_is_answered_as_the_first_and_costs_no_subscreen() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[1, 1, 1], false), clock.at(0));
        let first = s.request(ask(A, 7), None, false, clock.at(0));
        assert_eq!(first, vec![given(ask(A, 7), 0, rect(0, 0, 2, 1))]);
        assert_eq!(s.request(ask(A, 7), None, false, clock.at(1)), first);
        assert_eq!(
            s.request(ask(B, 7), None, false, clock.at(2)),
            vec![given(ask(B, 7), 1, rect(0, 1, 2, 1))],
            "the same tag from another node is another request"
        );
    }

    #[test]
    fn a_request_repeated_while_it_waits_is_answered_once() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2], true), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        assert_eq!(
            s.request(ask(B, 1), None, false, clock.at(0)),
            vec![Action::GiveBack {
                node: A,
                subscreen: 0
            }]
        );
        assert_eq!(s.request(ask(B, 1), None, false, clock.at(1)), vec![]);
        assert_eq!(
            s.returned(A, 0, 1),
            vec![given(ask(B, 1), 1, rect(0, 1, 2, 1))]
        );
        assert_eq!(s.finish(), vec![]);
    }

    #[test]
    fn a_stall_is_reported_after_ten_quiet_seconds_and_again_ten_later() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[1, 1, 1], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 1, 2, 1..2);
        s.request(ask(B, 2), Some(1), false, clock.at(0));
        rows(&mut s, 2, 2, 2..3);
        s.request(ask(B, 3), Some(2), false, clock.at(0));
        // The pixels are noticed at the first tick; the silence counts from there.
        assert_eq!(s.tick(clock.at(100)), vec![]);
        assert_eq!(s.tick(clock.at(10_100)), vec![]);
        let report = StallReport {
            silent_for: STALL_REPORT,
            missing: 2,
            not_done: vec![(0, Holder::Rendering(A))],
            waiting: vec![B],
        };
        assert_eq!(
            s.tick(clock.at(10_101)),
            vec![Action::Stalled(report.clone())]
        );
        assert_eq!(
            report.to_string(),
            "no pixels for 10s: 2 missing; subscreens not done: 0@5; nodes waiting for work: [6]"
        );
        assert_eq!(s.tick(clock.at(20_000)), vec![]);
        assert_eq!(s.tick(clock.at(20_102)).len(), 1);
        s.pixels(0, 0, 0, 1);
        assert_eq!(
            s.tick(clock.at(30_200)),
            vec![],
            "progress resets the silence"
        );
    }

    #[test]
    fn a_stall_report_says_who_holds_what() {
        let report = StallReport {
            silent_for: STALL_REPORT,
            missing: 9,
            not_done: vec![
                (0, Holder::Finished(5)),
                (3, Holder::Queued),
                (4, Holder::Rendering(6)),
            ],
            waiting: vec![],
        };
        assert_eq!(
            report.to_string(),
            "no pixels for 10s: 9 missing; subscreens not done: 0@5(finished) 3(queued) 4@6; nodes waiting for work: []"
        );
    }

    #[test]
    fn once_a_node_is_lost_rows_that_never_arrive_are_rendered_again() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(
            Plan {
                render_nodes: vec![A, B, 7],
                ..plan(2, &[2, 2], false)
            },
            clock.at(0),
        );
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        assert_eq!(s.request(ask(7, 1), None, false, clock.at(0)), vec![]);
        // A and B say they finished, but one row of each was lost on the way (through 7).
        rows(&mut s, 0, 2, 0..1);
        rows(&mut s, 1, 2, 2..3);
        s.request(ask(B, 2), Some(1), false, clock.at(1000));
        s.request(ask(A, 2), Some(0), false, clock.at(3200));
        // Without a lost node nothing is suspected, however long it takes.
        assert_eq!(s.tick(clock.at(5000)), vec![]);
        assert_eq!(
            s.node_lost(7),
            vec![Action::Reassigned {
                node: 7,
                subscreens: 0
            }]
        );
        // B finished more than the grace ago, A not yet.
        assert_eq!(
            s.tick(clock.at(5001)),
            vec![
                Action::RowsNeverArrived { subscreen: 1 },
                given(ask(B, 2), 1, rect(0, 3, 2, 1)),
            ]
        );
        assert_eq!(s.tick(clock.at(5201)), vec![], "swept at most every 250 ms");
        assert_eq!(
            s.tick(clock.at(5252)),
            vec![
                Action::RowsNeverArrived { subscreen: 0 },
                given(ask(A, 2), 0, rect(0, 1, 2, 1)),
            ]
        );
    }

    #[test]
    fn rows_of_a_subscreen_finished_less_than_the_grace_ago_are_awaited() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], false), clock.at(0));
        s.request(ask(A, 1), None, false, clock.at(0));
        s.request(ask(B, 1), None, false, clock.at(0));
        rows(&mut s, 1, 2, 2..4);
        s.node_lost(B);
        s.request(ask(A, 2), Some(0), false, clock.at(1000));
        assert_eq!(s.tick(clock.at(2900)), vec![]);
        assert_eq!(
            s.tick(clock.at(3200)),
            vec![
                Action::RowsNeverArrived { subscreen: 0 },
                given(ask(A, 2), 0, rect(0, 0, 2, 2)),
            ]
        );
    }

    #[test]
    fn unknown_and_lost_nodes_and_stale_ids_change_nothing() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(plan(2, &[2, 2], true), clock.at(0));
        assert_eq!(s.request(ask(99, 1), None, false, clock.at(0)), vec![]);
        assert_eq!(s.node_lost(99), vec![]);
        s.request(ask(A, 1), None, false, clock.at(0));
        // B never held subscreen 0; there is no subscreen 9.
        assert_eq!(s.returned(B, 0, 1), vec![]);
        assert_eq!(s.returned(A, 9, 1), vec![]);
        // Pixels outside the image, or running past its edge, are dropped whole.
        assert_eq!(s.pixels(0, 0, 4, 2), vec![]);
        assert_eq!(s.pixels(0, 1, 0, 2), vec![]);
        assert_eq!(s.pixels(0, 2, 0, 0), vec![]);
        s.node_lost(B);
        assert_eq!(s.request(ask(B, 2), None, false, clock.at(1)), vec![]);
        assert_eq!(s.returned(B, 0, 1), vec![]);
        // A lost node's late pixels still count.
        assert_eq!(
            s.pixels(1, 0, 2, 2),
            vec![Action::Store {
                x: 0,
                y: 2,
                width: 2
            }]
        );
        assert_eq!(s.missing(), 6);
        assert_eq!(
            s.request(ask(A, 2), None, false, clock.at(2)),
            vec![given(ask(A, 2), 1, rect(0, 2, 2, 2))]
        );
    }

    #[test]
    fn resuming_queues_only_the_rows_not_yet_done() {
        let clock = Clock(Instant::now());
        // Subscreen 0 is done; of subscreen 1 (rows 2..8) rows 3 and 5 are.
        let done = [rect(0, 0, 2, 2), rect(0, 3, 2, 1), rect(0, 5, 2, 1)];
        let mut s = Scheduler::resume(plan(2, &[2, 6, 1], false), &done, clock.at(0));
        assert_eq!(s.missing(), 2 * 5);
        let answers: Vec<Action> = (1..=5)
            .flat_map(|tag| s.request(ask(A, tag), None, false, clock.at(0)))
            .collect();
        assert_eq!(
            answers,
            vec![
                given(ask(A, 1), 1, rect(0, 2, 2, 1)),
                given(ask(A, 2), 2, rect(0, 8, 2, 1)),
                given(ask(A, 3), 3, rect(0, 4, 2, 1)),
                given(ask(A, 4), 4, rect(0, 6, 2, 2)),
            ]
        );
        assert_eq!(s.planned(), 3);
        let fresh = Scheduler::new(plan(2, &[2, 6, 1], false), clock.at(0));
        assert_eq!(fresh.queue, VecDeque::from([0, 1, 2]));
    }

    /// A 4x4 grid of 2x2 subscreens in scan-line order, for nodes A and B, in local order.
    fn grid_plan() -> Plan {
        let subscreens = (0..4)
            .flat_map(|gy| (0..4).map(move |gx| rect(2 * gx, 2 * gy, 2, 2)))
            .collect();
        Plan {
            width: 8,
            height: 8,
            subscreens,
            render_nodes: vec![B, A],
            adaptive: false,
            order: Order::Local,
            machines: Vec::new(),
        }
    }

    fn subscreen_of(actions: &[Action]) -> u32 {
        match actions {
            [
                Action::Answer {
                    answer: Answer::Subscreen { id, .. },
                    ..
                },
            ] => *id,
            other => panic!("not one subscreen handed out: {other:?}"),
        }
    }

    #[test]
    fn in_local_order_first_picks_spread_and_later_ones_stay_near() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(grid_plan(), clock.at(0));
        // A (the lower id) starts at the top, B half-way down the queue.
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        let b_first = subscreen_of(&s.request(ask(B, 1), None, false, clock.at(2)));
        assert_eq!(b_first, 8, "half of the 15 left, from the top");
        // Each then takes a neighbour of its last, of equally near ones the first in line:
        // A the one to its right, B the one above (before those right of and below it).
        assert_eq!(
            subscreen_of(&s.request(ask(A, 2), Some(0), false, clock.at(3))),
            1
        );
        assert_eq!(
            subscreen_of(&s.request(ask(B, 2), Some(8), false, clock.at(4))),
            4
        );
        assert_eq!(
            subscreen_of(&s.request(ask(A, 3), Some(1), false, clock.at(5))),
            2
        );
        assert_eq!(
            subscreen_of(&s.request(ask(B, 3), Some(4), false, clock.at(6))),
            5
        );
    }

    #[test]
    fn in_local_order_rows_of_a_lost_node_still_go_first() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(grid_plan(), clock.at(0));
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        assert_eq!(
            subscreen_of(&s.request(ask(B, 1), None, false, clock.at(2))),
            8
        );
        s.node_lost(A);
        // Subscreen 0 is far from B's last (8), yet it is what the frame waits for.
        assert_eq!(
            subscreen_of(&s.request(ask(B, 2), Some(8), false, clock.at(3))),
            0
        );
        assert_eq!(
            subscreen_of(&s.request(ask(B, 3), Some(0), false, clock.at(4))),
            1
        );
    }

    #[test]
    fn machines_let_as_many_work_as_their_nodes_have_cpus() {
        let node = |node, machine, cpus, machine_cpus| NodeMachine {
            node,
            machine,
            cpus,
            machine_cpus,
        };
        // Four nodes on a 2-CPU laptop, two on a 16-CPU box, one whose machine is unknown.
        let nodes = [
            node(1, "laptop", 2, 2),
            node(2, "laptop", 2, 2),
            node(3, "laptop", 2, 2),
            node(4, "laptop", 2, 2),
            node(5, "box", 16, 16),
            node(6, "box", 16, 16),
            node(7, "", 2, 2),
        ];
        let laptop = |at_work| Machine {
            nodes: vec![1, 2, 3, 4],
            at_work,
        };
        assert_eq!(machines(&nodes, AtWork::Cpus, 1), vec![laptop(2)]);
        assert_eq!(machines(&nodes, AtWork::Cpus, 2), vec![laptop(1)]);
        assert_eq!(machines(&nodes, AtWork::Cpus, 3), vec![laptop(1)]);
        assert_eq!(
            machines(&nodes, AtWork::Count(1), 1),
            vec![
                laptop(1),
                Machine {
                    nodes: vec![5, 6],
                    at_work: 1
                }
            ]
        );
        assert_eq!(machines(&nodes, AtWork::All, 1), vec![]);
        assert_eq!(machines(&nodes, AtWork::Auto, 1), vec![]);
        // Containers of one CPU each on an 8-CPU machine: the CPUs they may use add up.
        let boxed: Vec<_> = (1..=12).map(|n| node(n, "host", 1, 8)).collect();
        assert_eq!(machines(&boxed, AtWork::Cpus, 1)[0].at_work, 8);
        assert_eq!(machines(&boxed[..4], AtWork::Cpus, 1), vec![]);
    }

    #[test]
    fn auto_puts_every_node_to_work_where_nodes_wait_for_the_links() {
        // One machine: every card can be read in place.
        assert!(!spans_shared_memories(["boot-a/2a:1"; 86]));
        assert!(!spans_shared_memories([]));
        // A rack (a card on another machine), containers of one machine with a /dev/shm
        // each, or a node that sees no shared memory.
        assert!(spans_shared_memories([
            "boot-a/2a:1",
            "boot-a/2a:1",
            "boot-b/2a:1"
        ]));
        assert!(spans_shared_memories(["boot-a/2a:1", "boot-a/2b:1"]));
        assert!(spans_shared_memories(["boot-a/2a:1", ""]));
        assert!(spans_shared_memories([""]));
        let auto = |link_model, crossing| resolve_at_work(AtWork::Auto, link_model, crossing);
        assert_eq!(auto(false, false), AtWork::Cpus);
        assert_eq!(auto(false, true), AtWork::All);
        assert_eq!(auto(true, false), AtWork::All);
        // What the user chose stands.
        for chosen in [AtWork::Cpus, AtWork::All, AtWork::Count(3)] {
            assert_eq!(resolve_at_work(chosen, true, true), chosen);
            assert_eq!(resolve_at_work(chosen, false, false), chosen);
        }
    }

    #[test]
    fn at_work_is_auto_cpus_all_or_a_count() {
        for text in ["auto", "cpus", "all", "3"] {
            assert_eq!(text.parse::<AtWork>().unwrap().to_string(), text);
        }
        assert!("0".parse::<AtWork>().is_err());
        assert!(
            "many"
                .parse::<AtWork>()
                .unwrap_err()
                .to_string()
                .contains("auto, cpus, all")
        );
    }

    #[test]
    fn orders_are_named_plain_and_local() {
        assert_eq!("local".parse::<Order>().unwrap(), Order::Local);
        assert_eq!(Order::Plain.to_string(), "plain");
        assert!(
            "nearest"
                .parse::<Order>()
                .unwrap_err()
                .to_string()
                .contains("plain or local")
        );
    }

    const C: NodeId = 7;

    /// Bands of 2 rows for nodes A, B and C, all on one machine that lets `at_work` of them
    /// work at once.
    fn one_machine(bands: usize, at_work: usize, adaptive: bool) -> Plan {
        Plan {
            render_nodes: vec![A, B, C],
            machines: vec![Machine {
                nodes: vec![A, B, C],
                at_work,
            }],
            ..plan(4, &vec![2; bands], adaptive)
        }
    }

    #[test]
    fn a_machine_has_no_more_nodes_at_work_than_it_lets() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(one_machine(5, 2, false), clock.at(0));
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        assert_eq!(
            subscreen_of(&s.request(ask(B, 1), None, false, clock.at(1))),
            1
        );
        // Work is queued, yet C waits: two of the machine's nodes are at work.
        assert_eq!(s.request(ask(C, 1), None, false, clock.at(2)), vec![]);
        assert!(s.is_waiting(ask(C, 1)));
        // A node at work asking ahead is one already counted.
        assert_eq!(
            subscreen_of(&s.request(ask(A, 2), None, true, clock.at(3))),
            2
        );
        // Two queued for two nodes at work: nothing ahead.
        let nothing = s.request(ask(A, 3), Some(0), true, clock.at(4));
        assert!(matches!(
            nothing[..],
            [Action::Answer {
                answer: Answer::NothingAhead,
                ..
            }]
        ));
        // Finishing frees a place at work only for a moment: the node that asks again
        // keeps it, and C still waits.
        assert_eq!(
            subscreen_of(&s.request(ask(B, 2), Some(1), false, clock.at(5))),
            3
        );
        assert_eq!(
            subscreen_of(&s.request(ask(A, 4), Some(2), false, clock.at(6))),
            4
        );
        assert!(s.is_waiting(ask(C, 1)));
        // With nothing queued, a node that finished waits like any other, and the frame's
        // end tells every waiting node there is no more.
        assert_eq!(s.request(ask(A, 5), Some(4), false, clock.at(7)), vec![]);
        let ends = s.finish();
        assert_eq!(ends.len(), 2, "{ends:?}");
        assert!(ends.iter().all(|a| matches!(
            a,
            Action::Answer {
                answer: Answer::NoMoreWork,
                ..
            }
        )));
    }

    #[test]
    fn a_node_that_stops_holding_work_makes_room_for_one_that_waits() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(one_machine(4, 1, false), clock.at(0));
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        assert_eq!(s.request(ask(B, 1), None, false, clock.at(1)), vec![]);
        assert_eq!(s.request(ask(C, 1), None, false, clock.at(1)), vec![]);
        // A is lost at work: its subscreen goes to the first that waited, and only to it.
        let actions = s.node_lost(A);
        assert!(
            actions.contains(&given(ask(B, 1), 0, rect(0, 0, 4, 2))),
            "{actions:?}"
        );
        assert!(s.is_waiting(ask(C, 1)));
        // B finishes and asks again: it is the one at work now, so it goes on.
        assert_eq!(
            subscreen_of(&s.request(ask(B, 2), Some(0), false, clock.at(2))),
            1
        );
        assert!(s.is_waiting(ask(C, 1)));
    }

    #[test]
    fn a_node_kept_from_work_by_its_machine_is_not_idle_for_adaptive_redivision() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(one_machine(1, 1, true), clock.at(0));
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        // B could not take half of A's work: asking A to give it back would only split it.
        assert_eq!(s.request(ask(B, 1), None, false, clock.at(2)), vec![]);
    }

    #[test]
    fn requests_ahead_count_only_nodes_that_may_work() {
        let clock = Clock(Instant::now());
        let mut s = Scheduler::new(one_machine(3, 1, false), clock.at(0));
        assert_eq!(
            subscreen_of(&s.request(ask(A, 1), None, false, clock.at(1))),
            0
        );
        // Two queued, one node at work on the machine: more queued than can work at once.
        assert_eq!(
            subscreen_of(&s.request(ask(A, 2), Some(0), true, clock.at(2))),
            1
        );
        assert_eq!(
            s.request(ask(A, 3), Some(1), true, clock.at(3)),
            vec![Action::Answer {
                request: ask(A, 3),
                answer: Answer::NothingAhead
            }]
        );
    }
}
