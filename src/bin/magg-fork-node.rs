//! `magg-fork-node`: the fork node role (the paper's FP). Joins a host and serves its card.
//! For clusters started by hand and containers; a spawning host runs its own executable in
//! this role instead (`magg-host fork-node`), so that every process is the same build.

magg::check_cpu_at_start!();

fn main() {
    magg::node_binary_main(
        protocol::Role::Fork,
        "magg-fork-node",
        "magg fork node: a card's shared memory and its render nodes' demand data",
    );
}
