//! `magg-render-node`: the render node role (the paper's NP). Joins a host and renders subscreens.

use magg::{NodeArgs, init_logging};

#[derive(clap::Parser)]
#[command(
    name = "magg-render-node",
    version,
    about = "magg render node: renders subscreens, fetching shape data on demand"
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
        let join = cli.node.join_config(protocol::Role::Render)?;
        magg::run_node(render_node::run(render_node::Config { join }))?;
        Ok(())
    })();
    if let Err(e) = result {
        eprintln!("error: {}", magg::report(&e));
        std::process::exit(1);
    }
}
