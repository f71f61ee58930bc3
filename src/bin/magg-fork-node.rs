//! `magg-fork-node`: the fork node role (the paper's FP). Joins a host and serves its card.
//! For clusters started by hand and containers; a spawning host runs its own executable in
//! this role instead (`magg-host fork-node`), so that every process is the same build.

use magg::NodeArgs;

magg::check_cpu_at_start!();

#[derive(clap::Parser)]
#[command(name = "magg-fork-node", version = protocol::BUILD_ID, about = "magg fork node: a card's shared memory and its render nodes' demand data")]
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
    if let Err(e) = magg::node_main(protocol::Role::Fork, &cli.node) {
        eprintln!("error: {}", magg::report(&e));
        std::process::exit(1);
    }
}
