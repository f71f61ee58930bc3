//! Shared plumbing of the three binaries: logging, the cluster secret, and the flags every
//! node takes. The roles themselves live in the `host`, `fork-node` and `render-node` crates.

pub mod fuzzing;

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;

/// Parses the command line; a mistake is one line on stderr and exit code 2 (help and
/// version print as usual).
pub fn parse_args<T: clap::Parser>() -> T {
    match T::try_parse() {
        Ok(t) => t,
        Err(e)
            if matches!(
                e.kind(),
                clap::error::ErrorKind::DisplayHelp
                    | clap::error::ErrorKind::DisplayVersion
                    | clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            ) =>
        {
            e.exit()
        }
        Err(e) => {
            let text = e.render().to_string();
            let first = text
                .lines()
                .find(|l| !l.trim().is_empty())
                .unwrap_or("error: invalid command line");
            eprintln!("{} (see --help)", first.trim_end());
            std::process::exit(2);
        }
    }
}

/// An error and its causes on one line, each cause once (error types here often repeat
/// their source's text in their own message).
pub fn report(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if out.contains(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    out
}

/// Starts logging to stderr at `filter` (a level or RUST_LOG syntax).
pub fn init_logging(filter: &str) {
    let filter = tracing_subscriber::EnvFilter::try_new(filter)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .try_init();
}

/// How a process learns the cluster secret: a file, the environment, or (discouraged, it
/// shows in process listings) a flag.
#[derive(Args, Clone, Debug)]
pub struct SecretArgs {
    /// The cluster secret (visible in process listings: prefer MAGG_SECRET or --secret-file).
    #[arg(long, hide_env_values = true)]
    pub secret: Option<String>,
    /// A file holding the cluster secret.
    #[arg(long)]
    pub secret_file: Option<PathBuf>,
}

impl SecretArgs {
    /// The secret from the flag, the file, or MAGG_SECRET, in that order; `None` if absent.
    pub fn resolve(&self) -> Result<Option<protocol::Secret>> {
        let text = if let Some(s) = &self.secret {
            Some(s.clone())
        } else if let Some(f) = &self.secret_file {
            Some(
                std::fs::read_to_string(f)
                    .with_context(|| format!("reading the secret file {}", f.display()))?,
            )
        } else {
            std::env::var("MAGG_SECRET").ok()
        };
        match text {
            Some(t) => Ok(Some(protocol::Secret::new(&t).map_err(anyhow::Error::msg)?)),
            None => Ok(None),
        }
    }
}

/// Flags of a fork or render node.
#[derive(Args, Clone, Debug)]
pub struct NodeArgs {
    /// The host to join, HOST:PORT.
    #[arg(long, env = "MAGG_JOIN")]
    pub join: String,
    /// Where to listen for other nodes.
    #[arg(long, env = "MAGG_LISTEN", default_value = "0.0.0.0:0")]
    pub listen: String,
    /// The address other nodes should use to reach this one (default: this machine's address
    /// on the route to the host, with the listening port).
    #[arg(long, env = "MAGG_ADVERTISE")]
    pub advertise: Option<String>,
    #[command(flatten)]
    pub secret: SecretArgs,
    /// The cluster's id; every process of one cluster uses the same.
    #[arg(long, env = "MAGG_CLUSTER_ID", default_value = fabric::cluster::DEFAULT_CLUSTER_ID)]
    pub cluster_id: String,
    /// Seconds to wait for the cluster to form.
    #[arg(long, default_value_t = 120)]
    pub timeout: u64,
    /// Exit when the process that started this one exits (set by the host when it spawns).
    #[arg(long, hide = true)]
    pub die_with_parent: Option<u32>,
    /// Log level filter.
    #[arg(long, env = "MAGG_LOG", default_value = "info")]
    pub log: String,
}

impl NodeArgs {
    pub fn join_config(&self, role: protocol::Role) -> Result<fabric::cluster::JoinConfig> {
        let Some(secret) = self.secret.resolve()? else {
            bail!(
                "no cluster secret: give --secret-file FILE or set MAGG_SECRET (the host prints or writes it)"
            );
        };
        Ok(fabric::cluster::JoinConfig {
            host: self.join.clone(),
            listen: self.listen.clone(),
            advertise: self.advertise.clone(),
            role,
            secret,
            cluster_id: self.cluster_id.clone(),
            timeout: std::time::Duration::from_secs(self.timeout),
        })
    }

    /// Arranges to be killed with the parent that spawned us.
    pub fn arm_parent_death(&self) {
        if let Some(parent) = self.die_with_parent {
            let _ = rustix::process::set_parent_process_death_signal(Some(
                rustix::process::Signal::TERM,
            ));
            // The parent may have died before the line above: then we were re-parented.
            if rustix::process::getppid().map(|p| p.as_raw_nonzero().get() as u32) != Some(parent) {
                std::process::exit(1);
            }
        }
    }
}

/// Waits for Ctrl-C (SIGINT) or SIGTERM (what `docker stop` and `kill` send) and names it.
/// A process that is PID 1 in a container gets no default action for these, so every binary
/// waits for them itself.
pub async fn stop_signal() -> &'static str {
    use tokio::signal::unix::{SignalKind, signal};
    let (Ok(mut term), Ok(mut int)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) else {
        return std::future::pending().await;
    };
    tokio::select! {
        _ = term.recv() => "SIGTERM",
        _ = int.recv() => "SIGINT",
    }
}

/// Runs a node role until it ends or a stop signal comes (a clean stop: exit status 0).
pub fn run_node<F, E>(role: F) -> Result<()>
where
    F: std::future::Future<Output = std::result::Result<(), E>>,
    E: std::error::Error + Send + Sync + 'static,
{
    node_runtime()?.block_on(async {
        tokio::select! {
            r = role => r.map_err(anyhow::Error::from),
            signal = stop_signal() => {
                tracing::info!("stopping on {signal}");
                // Rendering threads may be waiting on this runtime; dropping it under them
                // would make them panic, so the process ends here, as the signal asked.
                std::process::exit(0)
            }
        }
    })
}

/// A single-threaded async runtime for a node's networking (rendering runs on its own
/// threads), as many processes share few cores.
pub fn node_runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}
