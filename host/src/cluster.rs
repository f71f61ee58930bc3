//! Starting a cluster from the host: spawning it locally, or waiting for nodes started by
//! hand (or by containers) to join, then stopping it cleanly.

use std::{
    path::PathBuf,
    sync::atomic::{AtomicBool, Ordering},
    time::Duration,
};

use fabric::{
    Topology,
    cluster::{Formed, form},
    model::LinkModelKind,
};
use protocol::{Message, Secret};
use tokio::net::TcpListener;

use crate::spawn::LocalCluster;

#[derive(Clone, Debug)]
pub enum ClusterMode {
    /// Start the nodes as local processes.
    Spawn,
    /// Listen at this address for nodes started elsewhere.
    Listen(String),
}

#[derive(Clone, Debug)]
pub struct ClusterConfig {
    pub mode: ClusterMode,
    pub topology: Topology,
    pub secret: Secret,
    pub join_timeout: Duration,
    /// Log level of spawned nodes.
    pub node_log: String,
    /// The executable spawned nodes run (in their role's subcommand): the host's own, so
    /// that every process of a local cluster is the same build.
    pub node_program: PathBuf,
    /// Where to write the secret (a generated one) for nodes started by hand, readable only
    /// by this user: once the host listens, so that a host that cannot (its port taken)
    /// neither leaves a file nor replaces the one a running host's nodes read.
    pub write_secret: Option<PathBuf>,
}

impl ClusterConfig {
    /// The topology's link model and time scale, but for those given (`None` keeps the
    /// topology's: a topology file's `[model]`, or a preset's defaults).
    pub fn with_model(
        mut self,
        link: Option<LinkModelKind>,
        time_scale: Option<f64>,
    ) -> ClusterConfig {
        if let Some(l) = link {
            self.topology.model.link = l;
        }
        if let Some(s) = time_scale {
            self.topology.model.time_scale = s;
        }
        self
    }
}

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("cannot listen at {addr}: {source}")]
    Listen {
        addr: String,
        source: std::io::Error,
    },
    #[error("cannot write the cluster secret to {path}: {source}")]
    SecretFile {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{0}")]
    Spawn(std::io::Error),
    #[error("{0}")]
    NodeExited(String),
    #[error("the cluster did not form: {0}")]
    Form(#[from] fabric::cluster::ClusterError),
    #[error("stopped before the cluster formed")]
    Stopped,
}

pub struct Cluster {
    pub formed: Formed,
    pub local: Option<LocalCluster>,
}

/// Binds the host's port: loopback for a spawned cluster, the given address otherwise.
pub async fn bind(config: &ClusterConfig) -> Result<TcpListener, StartError> {
    let addr = match &config.mode {
        ClusterMode::Spawn => "127.0.0.1:0".to_string(),
        ClusterMode::Listen(a) => a.clone(),
    };
    let listener = TcpListener::bind(&addr)
        .await
        .map_err(|source| StartError::Listen { addr, source })?;
    if let Some(path) = &config.write_secret {
        write_secret_file(path, &config.secret).map_err(|source| StartError::SecretFile {
            path: path.clone(),
            source,
        })?;
        tracing::info!(
            "generated a cluster secret in {} (readable only by you): give nodes --secret-file {}",
            path.display(),
            path.display()
        );
    }
    Ok(listener)
}

fn write_secret_file(path: &std::path::Path, secret: &Secret) -> std::io::Result<()> {
    use std::{io::Write, os::unix::fs::OpenOptionsExt};
    std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(path)?
        .write_all(secret.expose().as_bytes())
}

/// Binds the host's port and forms the cluster on it; see [`start_on`].
pub async fn start(
    config: &ClusterConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<Cluster, StartError> {
    let listener = bind(config).await?;
    start_on(listener, config, progress, cancel).await
}

/// How often a start looks at what the formation cannot see itself: whether `cancel` was
/// set, whether a spawned node exited.
const WATCH_EVERY: Duration = Duration::from_millis(100);

/// Forms the cluster on an already bound port (spawning the nodes first in spawn mode).
/// Setting `cancel` ends the wait (`StartError::Stopped`): the nodes that joined are told to
/// stop, and spawned ones that have not exited by then are killed.
pub async fn start_on(
    listener: TcpListener,
    config: &ClusterConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<Cluster, StartError> {
    let bound = listener.local_addr().map_err(|source| StartError::Listen {
        addr: "?".into(),
        source,
    })?;
    let mut local = match config.mode {
        ClusterMode::Spawn => {
            let (f, r) = config.topology.counts();
            Some(
                LocalCluster::spawn(
                    &config.node_program,
                    f,
                    r,
                    &bound.to_string(),
                    &config.secret,
                    &config.topology.cluster_id,
                    &config.node_log,
                )
                .map_err(StartError::Spawn)?,
            )
        }
        ClusterMode::Listen(_) => {
            tracing::info!(
                "waiting for {} to join at {bound}",
                config.topology.summary()
            );
            None
        }
    };
    let forming = form(
        listener,
        config.topology.clone(),
        config.secret.clone(),
        &config.topology.cluster_id,
        config.join_timeout,
        progress,
        matches!(config.mode, ClusterMode::Listen(_)),
        async {
            while !cancel.load(Ordering::Relaxed) {
                tokio::time::sleep(WATCH_EVERY).await;
            }
        },
    );
    tokio::pin!(forming);
    let formed = loop {
        tokio::select! {
            formed = &mut forming => match formed {
                Ok(formed) => break formed,
                // Ctrl-C in a terminal reaches the spawned nodes too, which exit at once:
                // what their exits did to the formation is the stop, not a failure.
                Err(_) if cancel.load(Ordering::Relaxed) => return Err(StartError::Stopped),
                Err(e) => return Err(e.into()),
            },
            _ = tokio::time::sleep(WATCH_EVERY) => {
                if cancel.load(Ordering::Relaxed) {
                    continue;
                }
                // A spawned node that cannot run exits at once; say so then, not at the
                // join timeout.
                if let Some(why) = local.as_mut().and_then(LocalCluster::exited_early) {
                    return Err(StartError::NodeExited(why));
                }
            }
        }
    };
    Ok(Cluster { formed, local })
}

impl Cluster {
    /// Tells every node to stop and waits for local processes to exit (killing stragglers);
    /// those of nodes declared lost are killed at once. Whether every live node exited when
    /// told.
    pub async fn shutdown(mut self, reason: &str) -> bool {
        for m in &self.formed.members {
            let _ = self.formed.fabric.send_control(
                m.node,
                &Message::Shutdown {
                    reason: reason.into(),
                },
            );
        }
        match self.local.take() {
            Some(mut l) => {
                // A node declared lost may be hung (stopped, swapped out) and would not obey
                // the Shutdown: waiting for it only delayed the exit, by the whole wait below.
                let lost: Vec<_> = self
                    .formed
                    .members
                    .iter()
                    .filter(|m| !self.formed.fabric.is_alive(m.node))
                    .map(|m| (m.role, m.node, m.pid))
                    .collect();
                // Nodes wait for the host to hang up before they exit. Hanging up closes each
                // connection once the frames queued on it (the Shutdown above) are written,
                // so nothing needs to wait for them here.
                self.formed.fabric.hang_up();
                tokio::task::spawn_blocking(move || {
                    for (role, node, pid) in lost {
                        if l.kill_child(pid) {
                            tracing::info!("killed lost {role} {node} (pid {pid})");
                        }
                    }
                    let ok = l.wait(Duration::from_secs(10));
                    l.kill();
                    ok
                })
                .await
                .unwrap_or(false)
            }
            // Nodes elsewhere see the host's connections end when this process exits, after
            // the host, so that whoever watches (compose) takes the host's exit status.
            None => {
                // This process exits soon after, ending its writers: give the frames a
                // moment to leave first.
                tokio::time::sleep(Duration::from_millis(50)).await;
                self.formed.fabric.begin_shutdown();
                true
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use super::*;

    fn spawning(program: &str) -> ClusterConfig {
        ClusterConfig {
            mode: ClusterMode::Spawn,
            topology: Topology::resolve("tiny").unwrap(),
            secret: Secret::new("spawn test secret").unwrap(),
            join_timeout: Duration::from_secs(60),
            node_log: "error".into(),
            node_program: program.into(),
            write_secret: None,
        }
    }

    async fn start_error(config: &ClusterConfig) -> String {
        match start(config, &|_, _| {}, &AtomicBool::new(false)).await {
            Ok(_) => panic!("the cluster should not form"),
            Err(e) => e.to_string(),
        }
    }

    #[tokio::test]
    async fn a_missing_node_executable_names_the_fix() {
        let err = start_error(&spawning("/nonexistent/magg-host")).await;
        assert!(err.contains("/nonexistent/magg-host"), "{err}");
        assert!(err.contains("cargo build --release"), "{err}");
    }

    #[tokio::test]
    async fn a_node_executable_that_cannot_run_is_reported_at_once() {
        let began = Instant::now();
        let err = start_error(&spawning("/bin/false")).await;
        assert!(err.contains("exited before the cluster formed"), "{err}");
        assert!(err.contains("cargo build --release"), "{err}");
        assert!(began.elapsed() < Duration::from_secs(30), "{err}");
    }
}
