//! `magg-render-node`: the render node role (the paper's NP). Joins a host and renders subscreens.
//! For clusters started by hand and containers; a spawning host runs its own executable in
//! this role instead (`magg-host render-node`), so that every process is the same build.

magg::check_cpu_at_start!();

fn main() {
    magg::node_binary_main(
        protocol::Role::Render,
        "magg-render-node",
        "magg render node: renders subscreens, fetching shape data on demand",
    );
}
