//! `magg-fork-node`: the fork node role (the paper's FP). Joins a host and serves its card.

use magg::{NodeArgs, init_logging};

#[derive(clap::Parser)]
#[command(
    name = "magg-fork-node",
    version,
    about = "magg fork node: a card's shared memory and its render nodes' demand data"
)]
struct Cli {
    #[command(flatten)]
    node: NodeArgs,
}

fn main() {
    let cli = magg::parse_args::<Cli>();
    init_logging(&cli.node.log);
    cli.node.arm_parent_death();
    let result = (|| -> anyhow::Result<()> {
        let join = cli.node.join_config(protocol::Role::Fork)?;
        magg::run_node(fork_node::run(fork_node::Config { join }))?;
        Ok(())
    })();
    if let Err(e) = result {
        eprintln!("error: {}", magg::report(&e));
        std::process::exit(1);
    }
}
