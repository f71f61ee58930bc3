//! The simulator against closed forms on synthetic costs: perfect balance, the paper's link
//! formula hop by hop, a batch handout, a cache that holds everything, determinism, and a
//! 1000-node machine in a bounded number of events. No wall time is measured anywhere.

use fabric::{Topology, model::LinkModelKind};
use protocol::{DataId, Frame, Message, Rect, Transfer as Via};
use sim::{Balance, SimConfig, SimResult, Subscreen, Transfer, Workload, simulate};

fn rect(x: u32, y: u32, width: u32, height: u32) -> Rect {
    Rect {
        x,
        y,
        width,
        height,
    }
}

/// `count` horizontal strips of `rows` rows each, every one costing `cpu_s` and touching
/// the chunks `items(i)`.
fn strips(
    width: u32,
    count: u32,
    rows: u32,
    cpu_s: f64,
    chunk_bytes: Vec<u64>,
    items: impl Fn(u32) -> Vec<u32>,
) -> Workload {
    Workload {
        width,
        height: count * rows,
        subscreens: (0..count)
            .map(|i| Subscreen::single(rect(0, i * rows, width, rows), cpu_s, items(i), vec![]))
            .collect(),
        chunk_bytes,
        tile_bytes: vec![],
    }
}

fn config(topology: &str) -> SimConfig {
    SimConfig::new(Topology::preset(topology).unwrap())
}

fn paper(topology: &str) -> SimConfig {
    SimConfig {
        link: LinkModelKind::Paper,
        ..config(topology)
    }
}

fn each_node_adds_up(r: &SimResult) {
    for n in &r.nodes {
        let sum = n.busy_s + n.waiting_s + n.idle_s;
        assert!(
            (sum - r.total_s).abs() < 1e-6,
            "node {}: {sum} vs {}",
            n.node,
            r.total_s
        );
    }
}

#[test]
fn equal_subscreens_without_transfer_costs_take_a_nth_of_one_node() {
    let w = strips(8, 32, 2, 0.25, vec![], |_| vec![]);
    let one = simulate(&w, &config("grid:1x1x1")).unwrap();
    assert_eq!(one.total_ns, 8_000_000_000);
    for (topology, n) in [("tiny", 4), ("grid:2x2x4", 16), ("grid:1x4x8", 32)] {
        let r = simulate(&w, &config(topology)).unwrap();
        assert_eq!(r.render_nodes, n);
        assert_eq!(r.total_ns, one.total_ns / n as u64, "{topology}");
        for node in &r.nodes {
            assert_eq!(node.busy_s, r.total_s, "{topology}: no one waits");
        }
        each_node_adds_up(&r);
    }
    // The static division of an evenly costly image: one subscreen each, the same time.
    let r = simulate(
        &w,
        &SimConfig {
            balance: Balance::Static,
            ..config("tiny")
        },
    )
    .unwrap();
    assert_eq!(r.subscreens, 4);
    assert_eq!(r.total_ns, 2_000_000_000);
}

/// One packet of `wire` bytes crossing one link, in ns, as the paper's formula extends to
/// packets of other sizes: 234 us along a column, 300 us along a row, and the bytes past 84
/// at 1.74 bytes per us.
/// Render nodes sharing a machine that lets two of them work at once: two render all the
/// subscreens, the others wait, as the host's `--at-work` has it; a node of no machine works
/// beside them.
#[test]
fn a_machine_lets_only_its_number_of_nodes_work_at_once() {
    let w = strips(8, 32, 2, 0.25, vec![], |_| vec![]);
    let t = Topology::preset("tiny").unwrap();
    let nodes = t.render_nodes();
    let limited = |on_machine: &[protocol::NodeId], at_work| SimConfig {
        machines: vec![sim::Machine {
            nodes: on_machine.to_vec(),
            at_work,
        }],
        ..config("tiny")
    };
    let r = simulate(&w, &limited(&nodes, 2)).unwrap();
    assert_eq!(r.total_ns, 4_000_000_000, "8 s of work on two nodes");
    let working: Vec<u32> = r.nodes.iter().map(|n| n.subscreens).collect();
    assert_eq!(working, [16, 16, 0, 0], "the first two to ask keep working");
    each_node_adds_up(&r);
    let r = simulate(&w, &limited(&nodes[..3], 1)).unwrap();
    assert_eq!(r.total_ns, 4_000_000_000, "one of three, and the fourth");
    assert_eq!(r.nodes.iter().filter(|n| n.subscreens > 0).count(), 2);
    // A limit that names no render node, a node twice, or lets none work is refused.
    for (on_machine, at_work) in [
        (vec![0], 1),
        (vec![nodes[0], nodes[0]], 1),
        (nodes.clone(), 0),
    ] {
        assert!(simulate(&w, &limited(&on_machine, at_work)).is_err());
    }
}

fn hop_ns(vertical: bool, wire: usize) -> u64 {
    let base = if vertical { 234.0 } else { 300.0 };
    ((base + (wire as f64 - 84.0) / 1.74) * 1000.0).round() as u64
}

const BASE_NS: u64 = 310_000;

fn wire(message: &Message, data_bytes: usize) -> usize {
    Frame::new(0, 0, message, Box::new([])).wire_len() + data_bytes
}

#[test]
fn one_miss_on_one_link_costs_the_formula_for_each_message() {
    // Host 0 - fork 1 - render node 2: the request for work crosses two links each way, the
    // data request and the row of pixels one; the chunk comes back by DMA.
    let chunk = 2000;
    let w = strips(4, 1, 1, 0.0, vec![chunk], |_| vec![0]);
    let r = simulate(&w, &paper("grid:1x1x1")).unwrap();
    let ask = wire(
        &Message::SubscreenRequest {
            finished: None,
            ahead: false,
        },
        0,
    );
    let answer = wire(
        &Message::Subscreen {
            id: 0,
            rect: rect(0, 0, 4, 1),
        },
        0,
    );
    let data_request = wire(
        &Message::DataRequest {
            id: DataId::Chunk(0),
            transfer: Via::Dma,
            owner: 1,
        },
        0,
    );
    let pixels = wire(
        &Message::Pixels {
            subscreen: 0,
            y: 0,
            x: 0,
            width: 4,
        },
        4 * 12,
    );
    let dma_ns = (100 + chunk / 20) * 1000;
    let expected = (BASE_NS + 2 * hop_ns(false, ask))
        + (BASE_NS + 2 * hop_ns(false, answer))
        + (BASE_NS + hop_ns(false, data_request))
        + dma_ns
        + (BASE_NS + hop_ns(false, pixels));
    assert_eq!(r.total_ns, expected);
    assert_eq!((r.transfers, r.bytes.dma, r.bytes.gbus), (1, chunk, 0));
    each_node_adds_up(&r);
    let node = &r.nodes[0];
    assert_eq!(node.busy_s, 0.0);
    assert_eq!(
        (node.waiting_s * 1e9).round() as u64,
        BASE_NS + hop_ns(false, data_request) + dma_ns
    );
}

#[test]
fn data_through_the_mesh_pays_every_hop_and_pipelines_its_packets() {
    // Render node (1,1) of tiny fetches by serial link: its fork node is one row step, one
    // column step and the fork link away (routes go along the row first). A chunk of 6000
    // bytes travels as 10 packets of 1 KB, store-and-forward: the last arrives after
    // (10 + 3 - 1) packet times, the slowest link setting the pace. The other nodes render
    // for a second meanwhile, so no other message shares a link.
    let chunk = 6000u64;
    let w = Workload {
        width: 4,
        height: 1,
        subscreens: vec![
            Subscreen::single(rect(0, 0, 1, 1), 1.0, vec![], vec![]),
            Subscreen::single(rect(1, 0, 1, 1), 1.0, vec![], vec![]),
            Subscreen::single(rect(2, 0, 1, 1), 1.0, vec![], vec![]),
            Subscreen::single(rect(3, 0, 1, 1), 0.0, vec![0], vec![]),
        ],
        chunk_bytes: vec![chunk],
        tile_bytes: vec![],
    };
    let serial = SimConfig {
        transfer: Transfer::Demand {
            cache_bytes: chunk,
            via: Via::Serial,
        },
        ..paper("tiny")
    };
    let r = simulate(&w, &serial).unwrap();
    assert_eq!((r.transfers, r.bytes.mesh), (1, chunk));
    let far = r.nodes.iter().find(|n| n.fetches == 1).unwrap();
    assert_eq!(far.node, 5, "the last to ask is the farthest, (1,1)");
    let request = wire(
        &Message::DataRequest {
            id: DataId::Chunk(0),
            transfer: Via::Serial,
            owner: 1,
        },
        0,
    );
    let reply = wire(
        &Message::DataReply {
            id: DataId::Chunk(0),
        },
        chunk as usize,
    );
    let packets = reply.div_ceil(640) as u64;
    let (row, col) = (hop_ns(false, 1024), hop_ns(true, 1024));
    // Fork link and row step cost `row` each, the column step `col`; the pipeline's pace
    // is the slowest link.
    let reply_ns = BASE_NS + row + col + row + (packets - 1) * row;
    let request_ns = BASE_NS + 2 * hop_ns(false, request) + hop_ns(true, request);
    assert_eq!(
        (far.waiting_s * 1e9).round() as u64,
        request_ns + reply_ns,
        "waiting is the request there and the packets back"
    );
}

#[test]
fn a_batch_handout_is_every_item_to_every_node_on_the_card_bus() {
    let sizes = vec![1000u64, 3000, 500];
    let w = strips(4, 4, 1, 0.0, sizes.clone(), |_| vec![]);
    let batch = SimConfig {
        transfer: Transfer::Batch,
        ..paper("tiny")
    };
    let r = simulate(&w, &batch).unwrap();
    let per_node: u64 = sizes.iter().map(|b| (100 + b / 20) * 1000).sum();
    let last = r
        .nodes
        .iter()
        .map(|n| (n.waiting_s * 1e9).round() as u64)
        .max()
        .unwrap();
    assert_eq!(last, 4 * per_node, "four nodes, one DMA bus");
    let first = r
        .nodes
        .iter()
        .map(|n| (n.waiting_s * 1e9).round() as u64)
        .min()
        .unwrap();
    // The first node gets the last item first of all four.
    assert_eq!(first, 4 * per_node - 3 * (100 + 500 / 20) * 1000);
    assert_eq!(r.bytes.batch, 4 * 4500);
    assert_eq!((r.transfers, r.bytes.dma, r.bytes.gbus), (0, 0, 0));
    each_node_adds_up(&r);
    // Two cards: the other card's items come over the G-bus once per card. Card 1's first
    // item (chunk 0) comes that way, so its DMA bus starts that much later; after that the
    // G-bus keeps ahead of the slower DMA bus.
    let two = simulate(
        &w,
        &SimConfig {
            transfer: Transfer::Batch,
            ..paper("grid:2x1x2")
        },
    )
    .unwrap();
    // Chunks 0 and 2 live on card 0, chunk 1 on card 1.
    assert_eq!(two.bytes.gbus, 1000 + 500 + 3000);
    assert_eq!(two.bytes.batch, 4 * 4500);
    let last = two
        .nodes
        .iter()
        .map(|n| (n.waiting_s * 1e9).round() as u64)
        .max()
        .unwrap();
    let gbus_chunk0 = ((5.0 + 1000.0 / 84.0) * 1000.0_f64).round() as u64;
    assert_eq!(last, 2 * per_node + gbus_chunk0);
}

#[test]
fn a_cache_holding_the_scene_never_fetches_twice() {
    let sizes: Vec<u64> = (0..12).map(|i| 1000 + 100 * i).collect();
    let scene: u64 = sizes.iter().sum();
    let w = strips(8, 64, 1, 0.01, sizes, |i| vec![i % 12, (i * 5) % 12, 3]);
    let cfg = SimConfig {
        transfer: Transfer::Demand {
            cache_bytes: scene,
            via: Via::Dma,
        },
        ..paper("tiny")
    };
    let r = simulate(&w, &cfg).unwrap();
    for n in &r.nodes {
        assert!(n.fetches <= 12, "node {} fetched {}", n.node, n.fetches);
        assert!(n.fetched_bytes <= scene);
        assert_eq!(n.evictions, 0);
    }
    let one = simulate(
        &w,
        &SimConfig {
            topology: Topology::preset("grid:1x1x1").unwrap(),
            ..cfg.clone()
        },
    )
    .unwrap();
    assert_eq!(one.transfers, 12, "one node fetches each item exactly once");
    // A cache of the largest item alone fetches at every change of item.
    let tight = simulate(
        &strips(8, 6, 1, 0.01, vec![10, 10], |i| vec![i % 2]),
        &SimConfig {
            topology: Topology::preset("grid:1x1x1").unwrap(),
            transfer: Transfer::Demand {
                cache_bytes: 10,
                via: Via::Dma,
            },
            ..cfg
        },
    )
    .unwrap();
    assert_eq!((tight.transfers, tight.nodes[0].evictions), (6, 5));
}

#[test]
fn a_cache_smaller_than_an_item_is_refused() {
    let w = strips(4, 1, 1, 0.0, vec![100], |_| vec![0]);
    let cfg = SimConfig {
        transfer: Transfer::Demand {
            cache_bytes: 99,
            via: Via::Dma,
        },
        ..config("tiny")
    };
    let e = simulate(&w, &cfg).unwrap_err().to_string();
    assert!(e.contains("largest item (100 bytes)"), "{e}");
}

#[test]
fn adaptive_redivision_gives_the_waiting_node_half_of_the_rest() {
    // One subscreen of 8 rows of a second each, two nodes, no link delays. A takes it and
    // begins row 0; B's request makes the host ask A for the unbegun half of rows 1..8:
    // rows 5..8 go to B. A renders 5 rows, B 3; B then waits, and A has nothing to give.
    let w = strips(2, 1, 8, 8.0, vec![], |_| vec![]);
    let cfg = SimConfig {
        adaptive: true,
        ..config("grid:1x1x2")
    };
    let r = simulate(&w, &cfg).unwrap();
    assert_eq!(r.subscreens_split, 1);
    assert_eq!(r.total_ns, 5_000_000_000);
    let rows: Vec<u64> = r.nodes.iter().map(|n| n.rows).collect();
    assert_eq!(rows, vec![5, 3]);
    each_node_adds_up(&r);
    // Without it, one node renders everything.
    let plain = simulate(
        &w,
        &SimConfig {
            adaptive: false,
            ..cfg
        },
    )
    .unwrap();
    assert_eq!(plain.total_ns, 8_000_000_000);
}

#[test]
fn the_same_input_gives_the_same_output() {
    let sizes: Vec<u64> = (0..40).map(|i| 2000 + 37 * i).collect();
    let w = strips(64, 200, 1, 0.003, sizes, |i| vec![i % 40, (i * 7) % 40]);
    let cfg = SimConfig {
        transfer: Transfer::demand_percent(&w, 10.0, Via::Dma),
        balance: Balance::Dynamic { subscreens: 150 },
        adaptive: true,
        time_scale: 0.01,
        ..paper("magg")
    };
    let a = simulate(&w, &cfg).unwrap();
    let b = simulate(&w, &cfg).unwrap();
    assert_eq!(a, b);
    assert_eq!(
        serde_json::to_string(&a).unwrap(),
        serde_json::to_string(&b).unwrap()
    );
    assert!(
        a.transfers > 0 && a.bytes.gbus > 0,
        "the example does exercise data"
    );
    each_node_adds_up(&a);
}

#[test]
fn a_thousand_render_nodes_take_a_bounded_number_of_events() {
    let t = Topology::preset("magg1000").unwrap();
    assert_eq!(t.counts().1, 1000);
    let sizes: Vec<u64> = (0..500).map(|i| 4000 + 13 * i).collect();
    let w = strips(640, 480, 1, 0.02, sizes, |i| vec![i % 500, (i * 11) % 500]);
    let cfg = SimConfig {
        transfer: Transfer::demand_percent(&w, 5.0, Via::Dma),
        balance: Balance::Dynamic { subscreens: 10_000 },
        time_scale: 0.01,
        ..SimConfig::new(t)
    };
    let cfg = SimConfig {
        link: LinkModelKind::Paper,
        ..cfg
    };
    let r = simulate(&w, &cfg).unwrap();
    assert_eq!(r.render_nodes, 1000);
    let rows: u64 = r.nodes.iter().map(|n| n.rows).sum();
    // Per row: its rendering and its arrival; per subscreen: a request, an answer and at
    // most one node start; per fetch: two.
    let bound = 2 * rows + 3 * r.subscreens as u64 + 2 * r.transfers + 1000;
    assert!(r.events <= bound, "{} events, bound {bound}", r.events);
    assert!(r.events < 2_000_000);
    let busy: f64 = r.nodes.iter().map(|n| n.busy_s).sum();
    assert!((busy - w.cpu_s()).abs() < 1e-3, "{busy} vs {}", w.cpu_s());
    each_node_adds_up(&r);
}

#[test]
fn overheads_add_their_cost_per_hop_and_before_the_start() {
    // One node, one row: the request to the host, the answer, the row to the fork node and
    // its pass to the host each pay the hop cost once per hop, on top of the start.
    let w = strips(4, 1, 1, 0.5, vec![], |_| vec![]);
    let topology = Topology::preset("grid:1x1x1").unwrap();
    let node = topology.render_nodes()[0];
    let fork = topology.fork_of(node).unwrap();
    let (start, hop) = (7_000_000, 300_000);
    let r = simulate(
        &w,
        &SimConfig {
            overheads: sim::Overheads {
                start_ns: start,
                hop_ns: hop,
                job_stagger_ns: 0,
            },
            ..config("grid:1x1x1")
        },
    )
    .unwrap();
    let hops = sim::hops(&topology, node, 0)
        + sim::hops(&topology, 0, node)
        + sim::hops(&topology, node, fork)
        + 1;
    assert_eq!(r.total_ns, start + hop * hops as u64 + 500_000_000);
    assert_eq!(r.spans_ns.len(), 1);
    each_node_adds_up(&r);

    // Two nodes whose job arrives a stagger apart: the later one ends the render.
    let w = strips(4, 2, 1, 0.5, vec![], |_| vec![]);
    let r = simulate(
        &w,
        &SimConfig {
            overheads: sim::Overheads {
                start_ns: start,
                hop_ns: 0,
                job_stagger_ns: 2_000_000,
            },
            ..config("grid:1x1x2")
        },
    )
    .unwrap();
    assert_eq!(r.total_ns, start + 2_000_000 + 500_000_000);
    assert_eq!(
        r.spans_ns[1].0,
        start + 2_000_000,
        "the second node's handout"
    );
}
