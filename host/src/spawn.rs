//! A local cluster: the host starting the fork and render nodes as processes of this
//! machine. No process outlives the host: children are told to die with it, and are killed
//! when the cluster is dropped.

use std::{
    ffi::{OsStr, OsString},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    time::{Duration, Instant},
};

use protocol::{Role, Secret};

pub struct LocalCluster {
    program: PathBuf,
    children: Vec<(Role, Child)>,
}

/// The glibc tunable that gives a process's heap 2 MiB pages (transparent huge pages, on
/// kernels that offer them on request; elsewhere, and on C libraries without it, nothing).
const HEAP_IN_LARGE_PAGES: &str = "glibc.malloc.hugetlb=1";

/// `GLIBC_TUNABLES` for a fork node, given the host's own (`existing`): its heap in large
/// pages, besides whatever else is set; a `glibc.malloc.hugetlb` chosen already is kept.
///
/// Fork nodes take in the scene's shares (the first fork node prepares the whole scene,
/// about 240 MB of heap for 1 M triangles; the others, where their shares come over a socket
/// rather than in a segment the first one wrote, about 28 MB each): every fresh 4 KiB
/// page costs a fault and a clearing, about 1.9 us on a virtual machine, against 0.42 us per
/// 4 KiB in a 2 MiB page. Render nodes keep small pages: their heaps are a few MB, which
/// large pages would round up (their caches' walking forms get large pages of their own,
/// see `render_node::cache`).
fn fork_node_tunables(existing: Option<&OsStr>) -> OsString {
    match existing {
        Some(t) if t.to_string_lossy().contains("glibc.malloc.hugetlb=") => t.to_os_string(),
        Some(t) if !t.is_empty() => {
            let mut all = t.to_os_string();
            all.push(":");
            all.push(HEAP_IN_LARGE_PAGES);
            all
        }
        _ => OsString::from(HEAP_IN_LARGE_PAGES),
    }
}

/// The subcommand that runs a `magg-host` executable in a node role.
fn role_subcommand(role: Role) -> &'static str {
    match role {
        Role::Fork => "fork-node",
        _ => "render-node",
    }
}

/// What to do when the node executable cannot run, for error messages.
const REBUILD: &str = "rebuild it (`cargo build --release`) and run the host again";

impl LocalCluster {
    /// Starts `forks` fork nodes and `renders` render nodes that join `host`, each one
    /// `program` (the host's own executable, so that every process is the same build) in its
    /// role. The secret goes by environment, never on the command line (where `ps` would
    /// show it).
    pub fn spawn(
        program: &Path,
        forks: usize,
        renders: usize,
        host: &str,
        secret: &Secret,
        cluster_id: &str,
        log: &str,
    ) -> std::io::Result<LocalCluster> {
        let mut cluster = LocalCluster {
            program: program.to_path_buf(),
            children: Vec::new(),
        };
        let me = std::process::id().to_string();
        let fork_tunables = fork_node_tunables(std::env::var_os("GLIBC_TUNABLES").as_deref());
        for role in
            std::iter::repeat_n(Role::Fork, forks).chain(std::iter::repeat_n(Role::Render, renders))
        {
            let mut command = Command::new(program);
            if role == Role::Fork {
                command.env("GLIBC_TUNABLES", &fork_tunables);
            }
            let child = command
                .args([
                    role_subcommand(role),
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
                    std::io::Error::new(
                        e.kind(),
                        format!(
                            "cannot start {} `{}`: {e}; {REBUILD}",
                            program.display(),
                            role_subcommand(role),
                        ),
                    )
                })?;
            cluster.children.push((role, child));
        }
        Ok(cluster)
    }

    /// The first child that has already exited, as a sentence that says what to do, if any.
    /// A node exits before the cluster has formed only when it cannot run at all.
    pub fn exited_early(&mut self) -> Option<String> {
        for (role, c) in &mut self.children {
            if let Ok(Some(status)) = c.try_wait() {
                return Some(format!(
                    "a spawned {role} (`{} {}`, pid {}) exited before the cluster formed ({status}; \
                     its own error, if any, is above); if the executable is damaged or was \
                     replaced, {REBUILD}",
                    self.program.display(),
                    role_subcommand(*role),
                    c.id()
                ));
            }
        }
        None
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
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    pub fn kill(&mut self) {
        for (_, c) in &mut self.children {
            let _ = c.kill();
        }
        for (_, c) in &mut self.children {
            let _ = c.wait();
        }
        // A fork node killed here could not remove its card's shared-memory segment.
        fabric::shm::remove_stale(std::path::Path::new(fabric::shm::SHM_DIR));
    }

    /// Kills the child whose process id is `pid`, if this cluster started one; whether it
    /// did.
    pub fn kill_child(&mut self, pid: u32) -> bool {
        let Some((_, c)) = self.children.iter_mut().find(|(_, c)| c.id() == pid) else {
            return false;
        };
        let _ = c.kill();
        let _ = c.wait();
        true
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fork_nodes_get_their_heap_in_large_pages_besides_what_else_is_tuned() {
        assert_eq!(
            fork_node_tunables(None),
            OsString::from(HEAP_IN_LARGE_PAGES)
        );
        assert_eq!(
            fork_node_tunables(Some(OsStr::new(""))),
            OsString::from(HEAP_IN_LARGE_PAGES)
        );
        assert_eq!(
            fork_node_tunables(Some(OsStr::new("glibc.malloc.arena_max=2"))),
            OsString::from("glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1")
        );
        // A choice made already stands, whichever it is.
        for chosen in [
            "glibc.malloc.hugetlb=0",
            "glibc.malloc.tcache_count=0:glibc.malloc.hugetlb=2",
        ] {
            assert_eq!(
                fork_node_tunables(Some(OsStr::new(chosen))),
                OsString::from(chosen)
            );
        }
    }
}
