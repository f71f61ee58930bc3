//! Experiments made of whole renders: each run is a fresh `magg-host render` process (so
//! its memory and time are its own), and the figures come from the `--stats` files.
//!
//! * `overhead`: the same image in one process and on a cluster with no delay model; wall
//!   times, their ratio, peak memory, and whether the bytes are equal.
//! * `cache`: one scene on a cluster for several shape-cache sizes, with the paper's link
//!   model: bytes fetched, hit rate and wall time per size (the paper's figure 1.11 axis).

use std::{io::Write, path::PathBuf, process::Command};

use serde::Serialize;

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("starting {}: {source}", program.display())]
    Start {
        program: PathBuf,
        source: std::io::Error,
    },
    #[error("render {args} failed: {stderr}")]
    RenderFailed { args: String, stderr: String },
    #[error("reading the statistics {}: {source}", path.display())]
    Stats {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Write(#[from] scene_io::ImageError),
}

/// Runs `PROGRAM render ARGS --stats FILE -o OUT` (PROGRAM is `magg-host`; the caller names
/// it, usually its own executable) and returns the parsed stats.
///
/// A cluster render puts every render node to work (`--at-work all`) unless ARGS say
/// otherwise: the experiments study the paper's machine, whose nodes each had a processor,
/// and the simulator they are compared with models it so, however few CPUs this machine has.
pub fn render_run(
    program: &std::path::Path,
    args: &[String],
    out: &std::path::Path,
    stats: &std::path::Path,
) -> Result<serde_json::Value, RunError> {
    let has = |flag: &str| args.iter().any(|a| a == flag);
    let every_node = (!has("--in-process") && !has("--at-work")).then_some(["--at-work", "all"]);
    let o = Command::new(program)
        .arg("render")
        .args(args)
        .args(every_node.iter().flatten())
        .arg("--quiet")
        .arg("-o")
        .arg(out)
        .arg("--stats")
        .arg(stats)
        .env("MAGG_LOG", "warn")
        .output()
        .map_err(|source| RunError::Start {
            program: program.to_path_buf(),
            source,
        })?;
    if !o.status.success() {
        // The render's own "error: " would follow this command's ("error: render ... failed:
        // error: ...").
        let said = String::from_utf8_lossy(&o.stderr);
        let lines: Vec<&str> = said
            .trim()
            .lines()
            .map(|l| l.strip_prefix("error: ").unwrap_or(l))
            .collect();
        return Err(RunError::RenderFailed {
            args: args.join(" "),
            stderr: lines.join("\n"),
        });
    }
    let text = std::fs::read(stats)?;
    serde_json::from_slice(&text).map_err(|source| RunError::Stats {
        path: stats.to_path_buf(),
        source,
    })
}

#[derive(Clone, Debug, Serialize)]
pub struct OverheadReport {
    pub scene: String,
    pub in_process_s: f64,
    pub in_process_render_s: f64,
    pub in_process_peak_mib: f64,
    pub cluster_s: f64,
    pub cluster_render_s: f64,
    pub cluster_peak_mib: f64,
    pub processes: u64,
    pub ratio_total: f64,
    pub ratio_render: f64,
    pub identical: bool,
}

/// In-process against a cluster, same image.
pub fn overhead(
    program: &std::path::Path,
    scene_args: &[String],
    cluster_args: &[String],
    dir: &std::path::Path,
) -> Result<OverheadReport, RunError> {
    std::fs::create_dir_all(dir)?;
    let (a, b) = (dir.join("in-process.pfm"), dir.join("cluster.pfm"));
    let sa = render_run(
        program,
        &[scene_args, &["--in-process".to_string()]].concat(),
        &a,
        &dir.join("in-process.json"),
    )?;
    let sb = render_run(
        program,
        &[scene_args, cluster_args].concat(),
        &b,
        &dir.join("cluster.json"),
    )?;
    let f = |v: &serde_json::Value, k: &str| v["seconds"][k].as_f64().unwrap_or(f64::NAN);
    let identical = std::fs::read(&a)? == std::fs::read(&b)?;
    Ok(OverheadReport {
        scene: sa["scene"].as_str().unwrap_or("").to_string(),
        in_process_s: f(&sa, "total"),
        in_process_render_s: f(&sa, "render"),
        in_process_peak_mib: sa["peak_rss_bytes"].as_f64().unwrap_or(0.0) / (1 << 20) as f64,
        cluster_s: f(&sb, "total"),
        cluster_render_s: f(&sb, "render"),
        cluster_peak_mib: sb["cluster_peak_rss_bytes"].as_f64().unwrap_or(0.0) / (1 << 20) as f64,
        processes: sb["processes"].as_u64().unwrap_or(0),
        ratio_total: f(&sb, "total") / f(&sa, "total"),
        ratio_render: f(&sb, "render") / f(&sa, "render"),
        identical,
    })
}

#[derive(Clone, Debug, Serialize)]
pub struct CacheRow {
    pub cache_percent: f64,
    pub cache_bytes: u64,
    pub bytes_fetched: u64,
    pub fetched_per_node: f64,
    pub hits: u64,
    pub misses: u64,
    pub evictions: u64,
    pub hit_rate: f64,
    pub wall_s: f64,
    pub render_s: f64,
    pub waiting_s: f64,
    pub identical: bool,
}

/// One cluster render per cache size; the first is also the reference for equality.
pub fn cache_sweep(
    program: &std::path::Path,
    base: &[String],
    caches: &[f64],
    dir: &std::path::Path,
) -> Result<Vec<CacheRow>, RunError> {
    std::fs::create_dir_all(dir)?;
    let mut rows = Vec::new();
    let mut reference: Option<Vec<u8>> = None;
    for &c in caches {
        let out = dir.join(format!("cache-{c}.pfm"));
        let args = [base, &["--cache".to_string(), c.to_string()]].concat();
        tracing::info!("cache {c}%");
        let v = render_run(program, &args, &out, &dir.join(format!("cache-{c}.json")))?;
        let t = &v["totals"];
        let g = |k: &str| t[k].as_u64().unwrap_or(0);
        let fetched = g("bytes_fetched_dma") + g("bytes_fetched_serial");
        let renderers = v["nodes"]
            .as_array()
            .map_or(1, |n| n.iter().filter(|x| x["role"] == "Render").count())
            .max(1);
        let bytes = std::fs::read(&out)?;
        let identical = match &reference {
            None => {
                reference = Some(bytes);
                true
            }
            Some(r) => *r == bytes,
        };
        let (hits, misses) = (g("cache_hits"), g("cache_misses"));
        rows.push(CacheRow {
            cache_percent: c,
            cache_bytes: v["cache_bytes"].as_u64().unwrap_or(0),
            bytes_fetched: fetched,
            fetched_per_node: fetched as f64 / renderers as f64,
            hits,
            misses,
            evictions: g("cache_evictions"),
            hit_rate: hits as f64 / (hits + misses).max(1) as f64,
            wall_s: v["seconds"]["total"].as_f64().unwrap_or(f64::NAN),
            render_s: v["seconds"]["render"].as_f64().unwrap_or(f64::NAN),
            waiting_s: t["waiting_s"].as_f64().unwrap_or(0.0),
            identical,
        });
    }
    let mut f = Vec::new();
    writeln!(
        f,
        "cache_percent,cache_bytes,bytes_fetched,fetched_per_node,hits,misses,evictions,hit_rate,wall_s,render_s,waiting_s,identical"
    )?;
    for r in &rows {
        writeln!(
            f,
            "{},{},{},{:.0},{},{},{},{:.6},{:.3},{:.3},{:.3},{}",
            r.cache_percent,
            r.cache_bytes,
            r.bytes_fetched,
            r.fetched_per_node,
            r.hits,
            r.misses,
            r.evictions,
            r.hit_rate,
            r.wall_s,
            r.render_s,
            r.waiting_s,
            r.identical
        )?;
    }
    scene_io::image_io::write_atomic(&dir.join("cache.csv"), &f)?;
    Ok(rows)
}

pub fn overhead_table(r: &OverheadReport) -> String {
    format!(
        "| run | wall time (s) | render (s) | peak memory (MiB) |\n|---|---:|---:|---:|\n\
         | in-process | {:.2} | {:.2} | {:.1} |\n\
         | cluster, {} processes | {:.2} | {:.2} | {:.1} (all processes) |\n\
         | ratio | {:.2} | {:.2} | {:.1} |\n\nimages identical: {}\n",
        r.in_process_s,
        r.in_process_render_s,
        r.in_process_peak_mib,
        r.processes,
        r.cluster_s,
        r.cluster_render_s,
        r.cluster_peak_mib,
        r.ratio_total,
        r.ratio_render,
        r.cluster_peak_mib / r.in_process_peak_mib.max(1e-9),
        r.identical
    )
}

pub fn cache_table(rows: &[CacheRow]) -> String {
    let mut s = String::from(
        "| cache | budget per node | bytes fetched (all nodes) | per node | hit rate | evictions | wall time (s) | render (s) | same image |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {}% | {:.2} MiB | {:.1} MiB | {:.2} MiB | {:.4} | {} | {:.2} | {:.2} | {} |\n",
            r.cache_percent,
            r.cache_bytes as f64 / (1 << 20) as f64,
            r.bytes_fetched as f64 / (1 << 20) as f64,
            r.fetched_per_node / (1 << 20) as f64,
            r.hit_rate,
            r.evictions,
            r.wall_s,
            r.render_s,
            if r.identical { "yes" } else { "NO" }
        ));
    }
    s
}

/// The default place for experiment outputs.
pub fn out_dir(name: &str) -> PathBuf {
    PathBuf::from("out").join(name)
}
