//! `magg-render-node`: the render node role (the paper's NP). Joins a host and renders subscreens.
//! For clusters started by hand and containers; a spawning host runs its own executable in
//! this role instead (`magg-host render-node`), so that every process is the same build.

use magg::NodeArgs;

magg::check_cpu_at_start!();

#[derive(clap::Parser)]
#[command(name = "magg-render-node", version = protocol::BUILD_ID, about = "magg render node: renders subscreens, fetching shape data on demand")]
struct Cli {
    #[command(flatten)]
    node: NodeArgs,
    /// Log level filter.
    #[arg(long, env = "MAGG_LOG", default_value = "info")]
    log: String,
}

fn main() {
    let cli = magg::parse_args::<Cli>();
    magg::init_logging(&cli.log);
    if let Err(e) = magg::node_main(protocol::Role::Render, &cli.node) {
        eprintln!("error: {}", magg::report(&e));
        std::process::exit(1);
    }
}
