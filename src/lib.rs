//! Shared plumbing of the three binaries: logging, the cluster secret, and the flags every
//! node takes. The roles themselves live in the `host`, `fork-node` and `render-node` crates.

pub mod fuzzing;

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;

/// What this build is (see `build.rs`): every process of a cluster must show the same.
pub const BUILD_ID: &str = env!("MAGG_BUILD_ID");

/// Makes this process show [`BUILD_ID`] at handshakes. The binaries do it first thing; a test
/// that runs a role in its own process beside the binaries does it too.
pub fn stamp_build_id() {
    protocol::stamp_build_id(BUILD_ID);
}

/// A line for the user on stderr that cannot end the process: `eprintln!` panics when stderr
/// is gone (`magg-host render ... 2>&1 | head -1`, a full disk), which lost the render it
/// reported on. What does not reach a closed stderr is dropped; the work goes on.
#[macro_export]
macro_rules! say {
    ($($arg:tt)*) => {
        $crate::write_stderr(::std::format_args!($($arg)*))
    };
}

/// A line of results on stdout (tables, paths written). Where stdout is gone the command
/// goes on, writing its files (some print their tables before they write them): a reader
/// that stops early (`| head -1`, as scripts read the first line) is no failure, and
/// another failure to write is said once on stderr and makes the command's exit status 1
/// ([`stdout_failed`]). `println!` panicked either way, and an exit at the first failed
/// line lost the files written after it.
#[macro_export]
macro_rules! put {
    ($($arg:tt)*) => {
        $crate::write_stdout(::std::format_args!($($arg)*), true)
    };
}

/// [`put!`] without the line end.
#[macro_export]
macro_rules! put_raw {
    ($($arg:tt)*) => {
        $crate::write_stdout(::std::format_args!($($arg)*), false)
    };
}

#[doc(hidden)]
pub fn write_stderr(args: std::fmt::Arguments) {
    use std::io::Write;
    let mut err = std::io::stderr().lock();
    let _ = err.write_fmt(args).and_then(|()| err.write_all(b"\n"));
}

/// What became of stdout: written to so far, its reader gone, or another failure.
static STDOUT: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(STDOUT_OK);
const STDOUT_OK: u8 = 0;
const STDOUT_CLOSED: u8 = 1;
const STDOUT_FAILED: u8 = 2;

#[doc(hidden)]
pub fn write_stdout(args: std::fmt::Arguments, line: bool) {
    use std::{io::Write, sync::atomic::Ordering};
    if STDOUT.load(Ordering::SeqCst) != STDOUT_OK {
        return;
    }
    let mut out = std::io::stdout().lock();
    let written = out
        .write_fmt(args)
        .and_then(|()| if line { out.write_all(b"\n") } else { Ok(()) })
        .and_then(|()| out.flush());
    match written {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {
            STDOUT.store(STDOUT_CLOSED, Ordering::SeqCst);
        }
        Err(e) => {
            STDOUT.store(STDOUT_FAILED, Ordering::SeqCst);
            write_stderr(format_args!(
                "error: writing the results to standard output: {e}"
            ));
        }
    }
}

/// Whether a [`put!`] failed for another reason than its reader going away: the command,
/// its work done, then exits with status 1.
pub fn stdout_failed() -> bool {
    STDOUT.load(std::sync::atomic::Ordering::SeqCst) == STDOUT_FAILED
}

/// Parses the command line; a mistake is one line on stderr and exit code 2 (help and
/// version print as usual).
pub fn parse_args<T: clap::Parser>() -> T {
    parse_command_line(T::command())
}

/// [`parse_args`] for a command line described at run time: `command` is `T`'s, renamed or
/// reworded.
fn parse_command_line<T: clap::FromArgMatches>(mut command: clap::Command) -> T {
    // Every binary parses its command line first, so this stamps the identity before any
    // handshake and sets up the allocator before the first big block.
    stamp_build_id();
    keep_freed_blocks();
    let parsed = command
        .try_get_matches_from_mut(std::env::args_os())
        .and_then(|mut matches| {
            T::from_arg_matches_mut(&mut matches).map_err(|e| e.format(&mut command))
        });
    match parsed {
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
            let mut lines = text.lines().skip_while(|l| l.trim().is_empty());
            let mut first = lines
                .next()
                .unwrap_or("error: invalid command line")
                .trim_end()
                .to_string();
            // "the following required arguments were not provided:" names them on the
            // lines after it, indented: they belong on the one line.
            if first.ends_with(':') {
                let named: Vec<&str> = lines
                    .take_while(|l| l.starts_with("  "))
                    .map(str::trim)
                    .collect();
                first = format!("{first} {}", named.join(", "));
            }
            say!("{} (see --help)", first.trim_end());
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

/// Makes the allocator keep freed blocks of a chunk's or a frame's size for reuse instead of
/// handing them back to the kernel. With glibc's defaults a block over 128 KiB is mapped
/// afresh and the heap's free top returned once it passes twice that, so every chunk frame a
/// node received over TCP (about 140 KiB) faulted in and zeroed new pages and unmapped them
/// again: page faults and unmapping were a quarter of a TCP-only cluster's CPU time. Blocks up
/// to 32 MiB now come from the heap, and up to 64 MiB of free heap is kept.
fn keep_freed_blocks() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets allocator parameters; it is called before this process has
    // started a thread.
    unsafe {
        // 32 MiB is the most glibc takes here (half its arena's size).
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 64 << 20);
    }
}

/// Makes a render node's threads share one heap. Its rendering thread frees the chunks its
/// network thread received and allocates their walking forms; with a heap per thread, the
/// holes each kept resident held a render node at cache 5% over TCP about 1 MiB further above
/// its budget (MetalRoughSpheresNoTextures, 320x240, 64 spp: own memory at most 15.9 MiB,
/// 14.8 with one heap, for a budget of 6.5 MiB). Its threads allocate little while
/// rendering, so they do not queue for the heap.
fn one_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets allocator parameters.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

/// Starts logging to stderr at `filter` (a level or RUST_LOG syntax).
pub fn init_logging(filter: &str) {
    let (parsed, refused) = match tracing_subscriber::EnvFilter::try_new(filter) {
        Ok(f) => (f, None),
        Err(e) => (tracing_subscriber::EnvFilter::new("info"), Some(e)),
    };
    let _ = tracing_subscriber::fmt()
        .with_env_filter(parsed)
        .with_writer(std::io::stderr)
        .with_target(false)
        // Its own report of a failed write goes through `eprint!`, which panics where
        // stderr is gone: a log line that cannot be written is dropped instead.
        .log_internal_errors(false)
        .try_init();
    // Said once logging is up, so that a mistyped --log or MAGG_LOG is not silently `info`.
    if let Some(e) = refused {
        tracing::warn!("the log filter {filter:?} is not one ({e}): logging at info");
    }
}

/// How a process learns the cluster secret: a file, the environment, or (discouraged, it
/// shows in process listings) a flag.
#[derive(Args, Clone, Debug)]
pub struct SecretArgs {
    /// The cluster secret (visible in process listings: prefer MAGG_SECRET or --secret-file).
    #[arg(long, hide_env_values = true, conflicts_with = "secret_file")]
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

/// The longest wait a flag may ask for: a year. Longer ones (a typing slip) overflowed the
/// clock's deadline and ended the process in a panic.
pub const MOST_WAIT_SECONDS: u64 = 365 * 24 * 3600;

/// The most threads a flag may ask for (more than any machine's cores; far more would only
/// fail to start, or take the memory of their bookkeeping).
pub const MOST_THREADS: usize = 4096;

/// Parses `s` as a number of `unit` from `lo` to `hi` (`note` said after the range), or says
/// which it is not: what every bounded flag of the binaries takes.
pub fn number_in<T>(s: &str, unit: &str, lo: T, hi: T, note: &str) -> Result<T, String>
where
    T: std::str::FromStr + PartialOrd + std::fmt::Display,
{
    let v: T = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number of {unit}"))?;
    // Written so that NaN, which compares false, is outside too.
    if !(lo <= v && v <= hi) {
        return Err(format!("{s} {unit}: give {lo} to {hi}{note}"));
    }
    Ok(v)
}

/// Parses whole seconds to wait, 0 to [`MOST_WAIT_SECONDS`].
pub fn wait_seconds(s: &str) -> Result<u64, String> {
    number_in(s, "seconds", 0, MOST_WAIT_SECONDS, " (a year)")
}

/// Parses seconds, possibly fractional, 0 to [`MOST_WAIT_SECONDS`].
pub fn fractional_seconds(s: &str) -> Result<f64, String> {
    number_in(s, "seconds", 0.0, MOST_WAIT_SECONDS as f64, " (a year)")
}

/// Parses a number of threads, 1 to [`MOST_THREADS`].
pub fn thread_count(s: &str) -> Result<usize, String> {
    number_in(s, "threads", 1, MOST_THREADS, "")
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
    #[arg(long, default_value_t = 120, value_parser = wait_seconds)]
    pub timeout: u64,
    /// Exit when the process that started this one exits (set by the host when it spawns).
    #[arg(long, hide = true)]
    pub die_with_parent: Option<u32>,
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
    let (name, number) = tokio::select! {
        _ = term.recv() => ("SIGTERM", 15),
        _ = int.recv() => ("SIGINT", 2),
    };
    STOPPED_BY.store(number, std::sync::atomic::Ordering::SeqCst);
    name
}

/// The signal [`stop_signal`] last saw, as its number (0 before any).
static STOPPED_BY: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

/// The exit status of a render stopped by a signal: 128 plus its number, as shells report a
/// process the signal ended (130 for Ctrl-C, 143 for SIGTERM, what `docker stop` and service
/// managers send; it said 130 for both).
pub fn stopped_exit_code() -> i32 {
    match STOPPED_BY.load(std::sync::atomic::Ordering::SeqCst) {
        0 => 130,
        n => 128 + n,
    }
}

/// The command line of `magg-fork-node` and `magg-render-node`: the node flags and a log level.
#[derive(clap::Parser)]
#[command(version = BUILD_ID)]
pub struct NodeCli {
    #[command(flatten)]
    pub node: NodeArgs,
    /// Log level filter.
    #[arg(long, env = "MAGG_LOG", default_value = "info")]
    pub log: String,
}

/// The whole of `magg-fork-node` and `magg-render-node`, which differ only in their role
/// and how they introduce themselves: parse the command line, start logging, run the node;
/// a failure is one line on stderr and exit status 1.
pub fn node_binary_main(role: protocol::Role, name: &'static str, about: &'static str) {
    let command = <NodeCli as clap::CommandFactory>::command()
        .name(name)
        .about(about)
        .long_about(None);
    let cli: NodeCli = parse_command_line(command);
    init_logging(&cli.log);
    if let Err(e) = node_main(role, &cli.node) {
        say!("error: {}", report(&e));
        std::process::exit(1);
    }
}

/// A fork or render node's whole life: dies with a spawning parent, joins the host, serves
/// its role until the render ends or a stop signal comes. `magg-fork-node`,
/// `magg-render-node` and `magg-host fork-node|render-node` all run this.
pub fn node_main(role: protocol::Role, args: &NodeArgs) -> Result<()> {
    args.arm_parent_death();
    if role == protocol::Role::Render {
        one_heap();
    }
    let join = args.join_config(role)?;
    match role {
        protocol::Role::Fork => run_node(fork_node::run(fork_node::Config { join })),
        protocol::Role::Render => run_node(render_node::run(render_node::Config { join })),
        protocol::Role::Host => bail!("the host is not a node role"),
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

/// A single-threaded async runtime for the networking of a node or of the cluster's host
/// (rendering runs on its own threads, heavy work in the blocking pool), as many processes
/// share few cores.
pub fn node_runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// The instruction set check every binary runs before anything else (see
/// [`check_cpu_at_start!`]).
#[cfg(target_arch = "x86_64")]
pub mod cpu {
    /// Exits with a sentence, instead of dying of an illegal instruction later, when this
    /// processor lacks an instruction-set feature the build was compiled to use
    /// (`.cargo/config.toml` builds for x86-64-v3). It runs from `.init_array`, before the
    /// Rust runtime starts, so it uses only integer code, `cpuid` and raw system calls.
    pub extern "C" fn check_at_start() {
        use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
        // SAFETY: `cpuid` exists on every x86-64 processor; leaf 7 is read only when the
        // processor reports it; `xgetbv` only when OSXSAVE says the OS enabled it.
        let ok = unsafe {
            let max_leaf = __cpuid(0).eax;
            let l1 = __cpuid(1);
            let l7 = if max_leaf >= 7 {
                __cpuid_count(7, 0).ebx
            } else {
                0
            };
            let ext = __cpuid(0x8000_0001).ecx;
            let bit = |word: u32, b: u32| word & (1 << b) != 0;
            // AVX state must also be enabled by the operating system (XCR0 bits 1 and 2).
            let os_avx = bit(l1.ecx, 27) && (_xgetbv(0) & 0b110) == 0b110;
            let need = |wanted: bool, present: bool| !wanted || present;
            need(cfg!(target_feature = "avx"), bit(l1.ecx, 28) && os_avx)
                && need(cfg!(target_feature = "avx2"), bit(l7, 5) && os_avx)
                && need(cfg!(target_feature = "fma"), bit(l1.ecx, 12) && os_avx)
                && need(cfg!(target_feature = "f16c"), bit(l1.ecx, 29))
                && need(cfg!(target_feature = "movbe"), bit(l1.ecx, 22))
                && need(cfg!(target_feature = "bmi1"), bit(l7, 3))
                && need(cfg!(target_feature = "bmi2"), bit(l7, 8))
                && need(cfg!(target_feature = "lzcnt"), bit(ext, 5))
        };
        if !ok {
            let _ = rustix::io::write(
                // SAFETY: file descriptor 2 is standard error for the whole process.
                unsafe { rustix::fd::BorrowedFd::borrow_raw(2) },
                b"error: this processor lacks instructions this build of magg uses (it was built \
                  for x86-64-v3: AVX2, FMA, BMI2). Build it for this machine instead: \
                  RUSTFLAGS=\"-C target-cpu=native\" cargo build --release\n",
            );
            std::process::exit(1);
        }
    }
}

/// Puts [`cpu::check_at_start`] into the binary's start-up code (`.init_array`), so that it
/// runs before `main` and before any code compiled for the wider instruction set.
#[macro_export]
macro_rules! check_cpu_at_start {
    () => {
        #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
        #[used]
        #[unsafe(link_section = ".init_array")]
        static CHECK_CPU_AT_START: extern "C" fn() = $crate::cpu::check_at_start;
    };
}
