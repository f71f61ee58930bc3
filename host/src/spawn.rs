//! A local cluster: the host starting the fork and render nodes as processes of this
//! machine. No process outlives the host: children are told to die with it, and are killed
//! when the cluster is dropped.

use std::{
    path::PathBuf,
    process::{Child, Command, Stdio},
    time::{Duration, Instant},
};

use protocol::{Role, Secret};

pub struct LocalCluster {
    children: Vec<(Role, Child)>,
}

/// Where the node binaries are: `MAGG_BIN_DIR` if set, else beside this executable.
pub fn node_binary(role: Role) -> PathBuf {
    let name = match role {
        Role::Fork => "magg-fork-node",
        _ => "magg-render-node",
    };
    if let Some(dir) = std::env::var_os("MAGG_BIN_DIR") {
        return PathBuf::from(dir).join(name);
    }
    let exe = std::env::current_exe().unwrap_or_default();
    exe.parent()
        .map(|d| d.join(name))
        .unwrap_or_else(|| PathBuf::from(name))
}

impl LocalCluster {
    /// Starts `forks` fork nodes and `renders` render nodes that join `host`. The secret goes
    /// by environment, never on the command line (where `ps` would show it).
    pub fn spawn(
        forks: usize,
        renders: usize,
        host: &str,
        secret: &Secret,
        cluster_id: &str,
        log: &str,
    ) -> std::io::Result<LocalCluster> {
        let mut cluster = LocalCluster {
            children: Vec::new(),
        };
        let me = std::process::id().to_string();
        for role in
            std::iter::repeat_n(Role::Fork, forks).chain(std::iter::repeat_n(Role::Render, renders))
        {
            let bin = node_binary(role);
            let child = Command::new(&bin)
                .args([
                    "--join",
                    host,
                    "--listen",
                    "127.0.0.1:0",
                    "--cluster-id",
                    cluster_id,
                    "--die-with-parent",
                    &me,
                ])
                .env("MAGG_SECRET", secret.expose())
                .env("MAGG_LOG", log)
                .env_remove("MAGG_JOIN")
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::inherit())
                .spawn()
                .map_err(|e| {
                    std::io::Error::new(e.kind(), format!("starting {}: {e}", bin.display()))
                })?;
            cluster.children.push((role, child));
        }
        Ok(cluster)
    }

    pub fn pids(&self) -> Vec<u32> {
        self.children.iter().map(|(_, c)| c.id()).collect()
    }

    /// Waits up to `timeout` for every child to exit; true if they all did.
    pub fn wait(&mut self, timeout: Duration) -> bool {
        let until = Instant::now() + timeout;
        loop {
            let running = self
                .children
                .iter_mut()
                .filter_map(|(_, c)| matches!(c.try_wait(), Ok(None)).then_some(()))
                .count();
            if running == 0 {
                return true;
            }
            if Instant::now() > until {
                return false;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn kill(&mut self) {
        for (_, c) in &mut self.children {
            let _ = c.kill();
        }
        for (_, c) in &mut self.children {
            let _ = c.wait();
        }
    }

    /// Kills one child (for fault tests); returns its pid.
    pub fn kill_one(&mut self, index: usize) -> Option<u32> {
        let (_, c) = self.children.get_mut(index)?;
        let pid = c.id();
        let _ = c.kill();
        let _ = c.wait();
        Some(pid)
    }
}

impl Drop for LocalCluster {
    fn drop(&mut self) {
        self.kill();
    }
}
