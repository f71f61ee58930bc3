//! Helpers shared by the cross-process tests.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// `tests/data`: the real scenes (written by others) and the reference image the tests
/// need, carried by the repository (`tests/data/README.md` lists them and their licences).
pub fn data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data")
}

/// `../shared` beside the repository, when it is there (CI puts it there): every scene of
/// the project's shared data, for the sweeps that go beyond `tests/data`. `None`, after one
/// line saying what is skipped, on a clone without it.
pub fn shared_if_present(what: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared");
    if p.join("scenes").is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: {what} (no ../shared beside the repository)");
        None
    }
}

pub fn host() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_magg-host"));
    c.env("MAGG_LOG", "warn");
    c
}

/// `magg-host render --quiet` on a `tiny` cluster it spawns, logging when pixels reach the
/// host (`MAGG_EVENT pixels node=`), so that a test can act once the render is under way.
pub fn render_on_spawned_tiny() -> Command {
    let mut c = host();
    c.args([
        "--log",
        "info,magg::event=debug",
        "render",
        "--quiet",
        "--spawn",
        "tiny",
    ]);
    c
}

/// A fresh empty folder for one test's files.
pub fn scratch(name: &str) -> PathBuf {
    let p = std::env::temp_dir().join(format!("magg-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&p);
    std::fs::create_dir_all(&p).unwrap();
    p
}

/// Runs `cmd` to its end. An executable a test has just written (a copy of the host) may
/// still be held open for writing by a child that another test thread forked meanwhile, until
/// that child's own exec; Linux refuses to run the file until then ("Text file busy"). That
/// race is the test harness's, not the program's, so the start is tried again while it lasts.
pub fn run(cmd: &mut Command) -> Output {
    let mut tries = 0;
    loop {
        match cmd.output() {
            Err(e) if e.kind() == std::io::ErrorKind::ExecutableFileBusy && tries < 50 => {
                tries += 1;
                std::thread::sleep(Duration::from_millis(20));
            }
            r => return r.expect("run binary"),
        }
    }
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The two files hold the same bytes (images compared exactly, not within a tolerance).
pub fn same_bytes(a: &Path, b: &Path) {
    let (x, y) = (std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    assert!(x == y, "{} and {} differ", a.display(), b.display());
}

/// Processes whose parent is `pid`.
pub fn children_of(pid: u32) -> Vec<u64> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(p) = e.file_name().to_string_lossy().parse::<u64>() else {
            continue;
        };
        if let Ok(stat) = std::fs::read_to_string(format!("/proc/{p}/stat")) {
            let after = stat.rsplit_once(')').map(|x| x.1).unwrap_or("");
            let ppid = after
                .split_whitespace()
                .nth(1)
                .and_then(|s| s.parse::<u32>().ok());
            if ppid == Some(pid) && !stat.contains(") Z ") {
                out.push(p);
            }
        }
    }
    out
}

/// Whether process `pid` has ended (gone, or a zombie its parent has not reaped).
pub fn exited(pid: u64) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Err(_) => true,
        Ok(s) => s.contains(") Z "),
    }
}

/// Sends `signal` to process `pid`.
pub fn signal(pid: u64, signal: rustix::process::Signal) {
    let _ = rustix::process::kill_process(
        rustix::process::Pid::from_raw(pid as i32).expect("a process id"),
        signal,
    );
}

/// Processes a test stopped (SIGSTOP) to play hung nodes: killed when it ends, pass or fail,
/// since a stopped process ignores the SIGTERM its parent's death sends it.
pub struct Held(pub Vec<u64>);

impl Held {
    pub fn hold(&mut self, pid: u64) {
        signal(pid, rustix::process::Signal::STOP);
        self.0.push(pid);
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        for &pid in &self.0 {
            if !exited(pid) {
                signal(pid, rustix::process::Signal::KILL);
            }
        }
    }
}

/// The node role process `pid` runs (a spawning host runs its own executable as each node:
/// `magg-host render-node`), once it runs it: `None` for other processes, and for a child
/// still between its fork and its exec (stopping that one would stop the host, which waits
/// for the exec).
pub fn node_role(pid: u64) -> Option<&'static str> {
    let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
    let argument = cmdline.split(|&b| b == 0).nth(1)?;
    ["fork-node", "render-node"]
        .into_iter()
        .find(|role| role.as_bytes() == argument)
}

/// The first child of `host` that runs as a render node.
pub fn render_node_child(host: u32) -> Option<u64> {
    children_of(host)
        .into_iter()
        .find(|&p| node_role(p) == Some("render-node"))
}

/// One cluster at a time within a test binary: tests that time how fast faults are noticed,
/// or start dozens of processes, would blur each other on two cores.
pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// Renders `args` (a scene and render flags) in one process into `dir`; the reference a
/// cluster's image must equal byte for byte.
pub fn in_process<S: AsRef<std::ffi::OsStr>>(dir: &Path, args: &[S]) -> PathBuf {
    in_process_to(&dir.join("one-process.png"), args)
}

/// As [`in_process`], into `out`.
pub fn in_process_to<S: AsRef<std::ffi::OsStr>>(out: &Path, args: &[S]) -> PathBuf {
    let o = run(host()
        .args(["render", "--quiet", "--in-process"])
        .args(args)
        .arg("-o")
        .arg(out));
    assert!(o.status.success(), "{}", stderr(&o));
    out.to_path_buf()
}

/// A fork node and a render node (a `grid:1x1x1` cluster's two) joining the host at `addr`
/// on loopback, each `magg-host ROLE` run by `command(role args)` (the binary itself, or it
/// under a tool), with the secret `secret` gives to each.
pub fn join_one_of_each(
    addr: &str,
    command: impl Fn(&[&str]) -> Command,
    secret: impl Fn(&mut Command) -> &mut Command,
) -> Vec<Logged> {
    ["fork-node", "render-node"]
        .into_iter()
        .map(|role| {
            let mut c = command(&[
                env!("CARGO_BIN_EXE_magg-host"),
                role,
                "--join",
                addr,
                "--listen",
                "127.0.0.1:0",
                "--log",
                "warn",
            ]);
            Logged::start(secret(&mut c))
        })
        .collect()
}

/// A process whose stderr is collected line by line as it runs.
pub struct Logged {
    pub child: Child,
    lines: Arc<Mutex<Vec<String>>>,
    /// Set once the whole of stderr has been read (the pipe closed).
    read_all: Arc<std::sync::atomic::AtomicBool>,
}

impl Logged {
    pub fn start(cmd: &mut Command) -> Logged {
        let mut child = cmd
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start process");
        let lines = Arc::new(Mutex::new(Vec::new()));
        let sink = lines.clone();
        let read_all = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let done = read_all.clone();
        let err = child.stderr.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(err).lines().map_while(Result::ok) {
                sink.lock().unwrap().push(line);
            }
            done.store(true, std::sync::atomic::Ordering::Release);
        });
        Logged {
            child,
            lines,
            read_all,
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn log(&self) -> String {
        self.lines.lock().unwrap().join("\n")
    }

    /// The first log line containing `needle`, waiting up to `limit` for it.
    pub fn wait_for(&self, needle: &str, limit: Duration) -> Option<String> {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(l) = self
                .lines
                .lock()
                .unwrap()
                .iter()
                .find(|l| l.contains(needle))
            {
                return Some(l.clone());
            }
            if Instant::now() > deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Where a host started with `--listen` waits for its nodes (its "to join at" line),
    /// waiting up to 30 s for it.
    pub fn join_address(&self) -> String {
        let line = self
            .wait_for("to join at ", Duration::from_secs(30))
            .unwrap_or_else(|| panic!("the host did not start listening: {}", self.log()));
        line.rsplit("to join at ")
            .next()
            .unwrap()
            .trim()
            .to_string()
    }

    /// The exit code, waiting up to `limit`; `None` if it is still running then.
    pub fn wait_exit(&mut self, limit: Duration) -> Option<Option<i32>> {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                self.wait_for_log_end(Duration::from_secs(5));
                return Some(s.code());
            }
            if Instant::now() > deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits until the reader has taken in everything the process wrote before it ended
    /// (clean-clone CI read a log that lacked the host's last lines, its error, right after
    /// the host had exited), or until `limit`: a child the process started may still hold
    /// the pipe open.
    fn wait_for_log_end(&self, limit: Duration) {
        let deadline = Instant::now() + limit;
        while !self.read_all.load(std::sync::atomic::Ordering::Acquire) && Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Logged {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
