//! `experiment all`: every experiment at its default size, one after the other, and one
//! `report.md` that holds them all, each beside the paper's sentence it tests, with the
//! machine it ran on and when.
//!
//! Each experiment runs as its own `magg-host experiment NAME` process (as a user would run
//! it, with its own defaults), its output kept in `NAME/output.txt`; one that fails is
//! reported as failed with its error, and the others still run.

use std::{
    path::{Path, PathBuf},
    process::Command,
    time::Instant,
};

/// One experiment of the report.
struct Part {
    name: &'static str,
    title: &'static str,
    /// Flags besides `--out`.
    args: &'static [&'static str],
}

/// The paper's sentences that `experiment links` tests.
const LINKS_QUOTE: &str = "\"In the NP network, transmitting time T (us) is approximately 310 + drow x 234 + dcol x 300 (drow, dcol: distance between NPs), on condition that the 84 bytes packet transmitted under no other process works except the communication process.\" ... \"It can be seen from this figure that the number of GPU has only a little effect on the average transfer time.\"";

const PARTS: &[Part] = &[
    Part {
        name: "links",
        title: "Transfer times by serial link and DMA (figures 1.5 and 1.6)",
        args: &[],
    },
    Part {
        name: "overhead",
        title: "The cluster's own cost (no delay model)",
        args: &[],
    },
    Part {
        name: "cache",
        title: "Shape-cache size: bytes fetched and hit rate",
        args: &[],
    },
    Part {
        name: "load-balance",
        title: "Load balancing (figure 1.10)",
        args: &[],
    },
    Part {
        name: "subscreens",
        title: "Rendering time against the number of subscreens (figure 1.11)",
        args: &[],
    },
    Part {
        name: "speedup",
        title: "Parallel processing performance (figures 1.12 to 1.15)",
        args: &[],
    },
    Part {
        name: "validate",
        title: "The simulator against real renders",
        args: &[],
    },
    Part {
        name: "error",
        title: "Run time against error, beside other renderers",
        args: &[],
    },
];

/// How one experiment went.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PartResult {
    pub name: String,
    pub seconds: f64,
    pub ok: bool,
}

/// Runs every experiment into `dir/NAME`, draws the timeline of the load-balance experiment's
/// dynamic render, and writes `dir/report.md`. `only` limits the run to the named
/// experiments (all when empty).
pub fn all(
    program: &Path,
    dir: &Path,
    only: &[String],
) -> Result<Vec<PartResult>, crate::LabError> {
    // A name that is no experiment ran nothing and reported success.
    if let Some(unknown) = only
        .iter()
        .find(|o| PARTS.iter().all(|p| p.name != o.as_str()))
    {
        let names: Vec<&str> = PARTS.iter().map(|p| p.name).collect();
        return Err(crate::LabError::Settings(format!(
            "--only {unknown:?} is no experiment; the experiments are {}",
            names.join(", ")
        )));
    }
    std::fs::create_dir_all(dir).map_err(crate::LabError::folder(dir))?;
    let started = Instant::now();
    let load_before = load_average();
    let mut results = Vec::new();
    let mut sections = String::new();
    for part in PARTS
        .iter()
        .filter(|p| only.is_empty() || only.iter().any(|o| o == p.name))
    {
        let out = dir.join(part.name);
        std::fs::create_dir_all(&out).map_err(crate::LabError::folder(&out))?;
        tracing::info!("experiment {}", part.name);
        let t = Instant::now();
        let o = run_quietly(
            Command::new(program)
                .arg("experiment")
                .arg(part.name)
                .arg("--out")
                .arg(&out)
                .args(part.args),
            program,
        )?;
        let seconds = t.elapsed().as_secs_f64();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        let output_path = out.join("output.txt");
        scene_io::image_io::write_atomic(&output_path, text.as_bytes())?;
        let ok = o.status.success();
        sections += &section(part, &out, &text, ok, seconds);
        results.push(PartResult {
            name: part.name.into(),
            seconds,
            ok,
        });
    }
    // The timeline and tinted image of one cluster render.
    let stats = dir.join("load-balance").join("dynamic.json");
    let mut timeline = String::new();
    if stats.is_file() {
        let o = run_quietly(Command::new(program).arg("plot").arg(&stats), program)?;
        if o.status.success() {
            timeline = "## A render's timeline\n\n\
                 The load-balance experiment's dynamic render (`magg-host plot \
                 load-balance/dynamic.json`): a row per render node, a bar per subscreen, \
                 darker the more it fetched; and the image tinted by the node that rendered \
                 each subscreen.\n\n\
                 ![timeline](load-balance/dynamic.timeline.png)\n\n\
                 ![who rendered what](load-balance/dynamic.nodes.png)\n\n"
                .to_string();
        }
    }
    let mut report = format!(
        "# The paper's experiments on this machine\n\n\
         Made by `magg-host experiment all` ({:.0} s in all). {}\n\n\
         | experiment | time (s) | ran |\n|---|---:|---|\n",
        started.elapsed().as_secs_f64(),
        machine(load_before),
    );
    for r in &results {
        report += &format!(
            "| [{}](#{}) | {:.0} | {} |\n",
            r.name,
            r.name,
            r.seconds,
            if r.ok { "yes" } else { "failed" }
        );
    }
    report += "\n";
    report += &sections;
    report += &timeline;
    let path = dir.join("report.md");
    scene_io::image_io::write_atomic(&path, report.as_bytes())?;
    Ok(results)
}

/// Runs `command` (of `program`) to its end with warnings only in its log.
fn run_quietly(
    command: &mut Command,
    program: &Path,
) -> Result<std::process::Output, crate::LabError> {
    Ok(command
        .env("MAGG_LOG", "warn")
        .output()
        .map_err(|source| crate::runs::RunError::Start {
            program: program.to_path_buf(),
            source,
        })?)
}

/// One experiment's part of the report: its own report with its links made relative to the
/// top folder, or, for the experiments that print tables, its output and plots.
fn section(part: &Part, out: &Path, output: &str, ok: bool, seconds: f64) -> String {
    let command = format!("`magg-host experiment {}` ({seconds:.0} s)\n\n", part.name);
    let mut s = format!("<a id=\"{}\"></a>\n\n", part.name);
    let own = std::fs::read_to_string(out.join("report.md"))
        .ok()
        .filter(|_| ok);
    let Some(own) = own else {
        s += &format!("## {}\n\n{command}", part.title);
        if !ok {
            let tail: Vec<&str> = output.lines().rev().take(10).collect();
            s += "**It failed:**\n\n```text\n";
            for l in tail.iter().rev() {
                s += l;
                s += "\n";
            }
            s += "```\n\n";
            return s;
        }
        s += "```text\n";
        s += output.trim_end();
        s += "\n```\n\n";
        for png in pngs(out) {
            s += &format!("![{png}]({}/{png})\n\n", part.name);
        }
        return s;
    };
    // Its own headings one level down, the command under the first, its files found from
    // the top folder.
    let mut first = true;
    for line in own.lines() {
        if line.starts_with('#') {
            s += &format!("#{line}\n");
            if first {
                s += "\n";
                s += &command;
                first = false;
            }
        } else {
            s += &relink(line, part.name);
            s += "\n";
        }
    }
    s += "\n";
    s
}

/// `experiment links`'s `report.md`: the paper's sentences, whether the one-packet times
/// follow its formula, the tables and both figures.
pub fn write_links_report(dir: &Path, tables: &str) -> Result<(), crate::LabError> {
    let mut s = format!(
        "# Transfer times by serial link and DMA (the paper's figures 1.5 and 1.6)\n\n> {LINKS_QUOTE}\n\n"
    );
    if let Some(verdict) = formula_verdict(tables) {
        s += &verdict;
    }
    if let Some(verdict) = gpu_count_verdict(tables) {
        s += &verdict;
    }
    s += tables.trim_end();
    s += "\n\n![figure 1.5: one node active](fig1.5-one-node.png)\n\n\
          ![figure 1.6: 16 or 80 nodes at once](fig1.6-many-nodes.png)\n";
    let path = dir.join("report.md");
    scene_io::image_io::write_atomic(&path, s.as_bytes())?;
    Ok(())
}

/// For `experiment links`: whether 80 nodes at once on five cards take about what 16 at once on
/// one card take (the paper: "the number of GPU has only a little effect"), from the mean
/// DMA times of the two rows, size by size.
fn gpu_count_verdict(tables: &str) -> Option<String> {
    let row = |prefix: &str| -> Option<Vec<f64>> {
        let line = tables
            .lines()
            .find(|l| l.starts_with(prefix) && l.contains("| Dma |"))?;
        Some(
            line.split('|')
                .skip(3)
                .filter_map(|c| c.trim().parse::<f64>().ok())
                .collect(),
        )
    };
    let (one, five) = (row("| 16 nodes")?, row("| 80 nodes")?);
    if one.is_empty() || one.len() != five.len() {
        return None;
    }
    let ratios: Vec<f64> = one.iter().zip(&five).map(|(a, b)| b / a).collect();
    let worst = ratios.iter().fold(1.0f64, |w, r| w.max(*r).max(1.0 / r));
    Some(format!(
        "**Finding (the number of cards): {}.** By DMA, 80 render nodes at once on five cards \
         took {} the time of 16 at once on one card, size by size (a little effect read as \
         within 1.5x).\n\n",
        if worst <= 1.5 {
            "reproduced"
        } else {
            "not reproduced"
        },
        ratios
            .iter()
            .map(|r| format!("{r:.2}x"))
            .collect::<Vec<_>>()
            .join(", "),
    ))
}

/// For `experiment links`: whether the one-packet times follow the paper's formula, from the
/// error column of its table (`| d_row | d_col | measured | formula | error |`).
fn formula_verdict(output: &str) -> Option<String> {
    let errors: Vec<f64> = output
        .lines()
        .filter(|l| l.starts_with("| ") && l.trim_end().ends_with("% |"))
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            (cells.len() == 7)
                .then(|| cells[5].trim_end_matches('%').parse::<f64>().ok())
                .flatten()
        })
        .collect();
    if errors.is_empty() {
        return None;
    }
    let worst = errors.iter().fold(0.0f64, |a, e| a.max(e.abs()));
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    Some(format!(
        "**Finding (the one-packet formula): {}.** Over {} routes the measured one-packet time \
         is {mean:+.1}% off the formula on average, {worst:.1}% at worst (the processes add \
         their own time on each hop; 86 of them share this machine's cores).\n\n",
        if worst <= 25.0 {
            "reproduced within 25%"
        } else {
            "not reproduced within 25%"
        },
        errors.len(),
    ))
}

/// `](file)` links made relative to the folder above `name`.
fn relink(line: &str, name: &str) -> String {
    let mut out = String::new();
    let mut rest = line;
    while let Some(i) = rest.find("](") {
        out += &rest[..i + 2];
        rest = &rest[i + 2..];
        let external = rest.starts_with("http") || rest.starts_with('#') || rest.starts_with('/');
        if !external {
            out += name;
            out += "/";
        }
    }
    out + rest
}

fn pngs(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".png"))
        .collect();
    v.sort();
    v
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "unknown".into())
}

/// The date, the processor, its cores and memory, and the load before and after.
fn machine(load_before: String) -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "an unknown processor".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let memory = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("MemTotal"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|k| k.parse::<f64>().ok())
        })
        .map_or("unknown".to_string(), |kib| {
            format!("{:.0} GiB", kib / 1048576.0)
        });
    format!(
        "Finished {} UTC on {cpu}, {cores} cores, {memory} of memory; load average {load_before} \
         before and {} after. Build `{}`.",
        utc_now(),
        load_average(),
        protocol::build_id(),
    )
}

/// The current UTC time as `YYYY-MM-DD HH:MM` (days to a civil date, proleptic Gregorian).
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rest) = (secs.div_euclid(86400), secs.rem_euclid(86400));
    let (y, m, d) = civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}",
        rest / 3600,
        rest % 3600 / 60
    )
}

fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

/// The default folder of `experiment all`.
pub fn default_dir() -> PathBuf {
    crate::runs::out_dir("all")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--only` with a name that is no experiment is refused with the names there are,
    /// before anything runs or any folder is made.
    #[test]
    fn only_an_experiment_that_is_not_one_is_refused() {
        let dir = std::env::temp_dir().join(format!("magg-all-only-{}", std::process::id()));
        let e = all(Path::new("/nonexistent"), &dir, &["bogus".into()]).unwrap_err();
        assert!(
            e.to_string().contains(r#"--only "bogus" is no experiment"#),
            "{e}"
        );
        assert!(e.to_string().contains("links, overhead"), "{e}");
        assert!(!dir.exists());
    }

    #[test]
    fn civil_dates() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(20_789), (2026, 12, 2));
        assert_eq!(civil_from_days(11_016), (2000, 2, 29));
    }

    #[test]
    fn the_formula_verdict_reads_the_error_column() {
        let out = "| d_row | d_col | measured (us) | formula (us) | error |\n\
                   | 0 | 1 | 758 ± 275 | 610 | +24.3% |\n\
                   | 3 | 3 | 2012 ± 42 | 1912 | +5.2% |\n";
        let v = formula_verdict(out).unwrap();
        assert!(
            v.contains("reproduced within 25%") && v.contains("24.3%"),
            "{v}"
        );
        assert!(formula_verdict("nothing").is_none());
    }

    #[test]
    fn the_card_count_verdict_compares_16_and_80_nodes() {
        let t = "| 16 nodes at once (card 0) | Dma | 2894 | 31460 |\n\
                 | 80 nodes at once (all) | Dma | 12085 | 31442 |\n";
        let v = gpu_count_verdict(t).unwrap();
        assert!(
            v.contains("not reproduced") && v.contains("4.18x, 1.00x"),
            "{v}"
        );
    }

    #[test]
    fn links_are_made_relative_to_the_top_folder() {
        assert_eq!(
            relink("![a](a.png) and [b](http://x) and ![c](c.png)", "sub"),
            "![a](sub/a.png) and [b](http://x) and ![c](sub/c.png)"
        );
    }
}
