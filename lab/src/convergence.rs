//! `experiment error`: run time against error, the measure of a renderer that the brief asks
//! for ("fast and accurate: benchmark run time against error"). One scene is rendered at
//! 1, 2, 4 ... samples per pixel, each a whole `magg-host render --in-process` as a user waits
//! for it; each image's relative mean squared error against a reference gives one point of a
//! log-log curve. Curves of other renderers join it from `bench/peers/`' results when those
//! were run (Mitsuba 3's `mitsuba-results.json`, Blender Cycles' `cycles-results.json`, both
//! optional: a fresh clone has neither); the time each needs to reach relMSE 1e-2 and 1e-3 is
//! read off the curves by log-log interpolation.

use std::{
    io::Write,
    path::{Path, PathBuf},
};

use serde::Serialize;

use crate::runs::render_run;

/// One render of the sweep (or one peer's point).
#[derive(Clone, Debug, Serialize)]
pub struct ErrorPoint {
    pub spp: u32,
    pub wall_s: f64,
    pub render_s: f64,
    pub rel_mse: f64,
}

/// A renderer's curve.
#[derive(Clone, Debug, Serialize)]
pub struct Curve {
    pub name: String,
    pub points: Vec<ErrorPoint>,
}

#[derive(Clone, Debug, Serialize)]
pub struct ErrorReport {
    pub scene: PathBuf,
    pub reference: PathBuf,
    pub curves: Vec<Curve>,
    /// The peer result files the curves after magg's were read from.
    pub peer_files: Vec<PathBuf>,
    /// Per curve: wall seconds to relMSE 1e-2 and 1e-3 (None when the curve cannot say).
    pub time_to: Vec<(String, Option<f64>, Option<f64>)>,
}

/// What the sweep renders.
pub struct ErrorConfig {
    pub scene: PathBuf,
    pub reference: PathBuf,
    pub width: u32,
    pub height: u32,
    pub max_spp: u32,
    /// Extra render flags (threads, integrator...).
    pub render_args: Vec<String>,
    /// A `mitsuba-results.json` of `bench/peers/mitsuba.py`, when present; the other peers'
    /// results ([`PEER_RESULTS`]) are looked for in the same folder.
    pub peers: Option<PathBuf>,
}

/// The result files of the `bench/peers/` scripts that carry error curves, in the order
/// their curves are drawn: each is a JSON object whose `runs` rows have `renderer`,
/// `variant`, `spp`, `wall_s`, `render_s` and `rel_mse`.
pub const PEER_RESULTS: [&str; 2] = ["mitsuba-results.json", "cycles-results.json"];

/// The peer result files to read: `given` and the known ones beside it, those that exist,
/// each once. The command line names one file (Mitsuba's, by default); Cycles' sits next to
/// it because both scripts write to the same output folder.
pub fn peer_files(given: &Path) -> Vec<PathBuf> {
    let mut files = vec![given.to_path_buf()];
    for name in PEER_RESULTS {
        let beside = given.with_file_name(name);
        if !files.contains(&beside) {
            files.push(beside);
        }
    }
    files.retain(|f| f.is_file());
    files
}

/// Each curve's name and its wall time to relMSE 1e-2 and 1e-3 ([`time_to_reach`]).
fn times_to_targets(curves: &[Curve]) -> Vec<(String, Option<f64>, Option<f64>)> {
    curves
        .iter()
        .map(|c| {
            let pts: Vec<(f64, f64)> = c.points.iter().map(|p| (p.wall_s, p.rel_mse)).collect();
            (
                c.name.clone(),
                time_to_reach(&pts, 1e-2),
                time_to_reach(&pts, 1e-3),
            )
        })
        .collect()
}

/// Seconds to reach `target` relMSE: log(time) interpolated linearly in log(relMSE) between
/// the two consecutive points that bracket it; None when no two points do (no extrapolation:
/// a figure read off the curve must lie on it).
pub fn time_to_reach(points: &[(f64, f64)], target: f64) -> Option<f64> {
    let pts: Vec<(f64, f64)> = points
        .iter()
        .copied()
        .filter(|&(t, e)| t > 0.0 && e > 0.0 && t.is_finite() && e.is_finite())
        .collect();
    pts.windows(2).find_map(|w| {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        if e0 == e1 || target < e0.min(e1) || target > e0.max(e1) {
            return None;
        }
        let f = (target.ln() - e0.ln()) / (e1.ln() - e0.ln());
        Some((t0.ln() + f * (t1.ln() - t0.ln())).exp())
    })
}

/// Renders the sweep, reads the peers' curves, writes `error.csv`, `error.png`, `report.md`.
pub fn error_sweep(
    program: &Path,
    config: &ErrorConfig,
    dir: &Path,
) -> Result<ErrorReport, crate::LabError> {
    let folder = crate::LabError::folder(dir);
    std::fs::create_dir_all(dir).map_err(folder)?;
    let reference = scene_io::image_io::read_image(&config.reference)?;
    if (reference.width, reference.height) != (config.width, config.height) {
        return Err(crate::LabError::Compare {
            path: config.reference.clone(),
            source: crate::compare::SizeMismatch(
                config.width,
                config.height,
                reference.width,
                reference.height,
            ),
        });
    }
    let mut points = Vec::new();
    let mut spp = 1;
    while spp <= config.max_spp {
        let out = dir.join(format!("magg-{spp}.pfm"));
        let args: Vec<String> = [
            config.scene.display().to_string(),
            "--in-process".into(),
            "--width".into(),
            config.width.to_string(),
            "--height".into(),
            config.height.to_string(),
            "--spp".into(),
            spp.to_string(),
        ]
        .into_iter()
        .chain(config.render_args.iter().cloned())
        .collect();
        tracing::info!("error: {spp} spp");
        let stats = render_run(program, &args, &out, &dir.join(format!("magg-{spp}.json")))?;
        let image = scene_io::image_io::read_image(&out)?;
        let c = crate::compare::compare(&image, &reference).map_err(|source| {
            crate::LabError::Compare {
                path: out.clone(),
                source,
            }
        })?;
        points.push(ErrorPoint {
            spp,
            wall_s: stats["seconds"]["total"].as_f64().unwrap_or(f64::NAN),
            render_s: stats["seconds"]["render"].as_f64().unwrap_or(f64::NAN),
            rel_mse: c.rel_mse,
        });
        spp *= 2;
    }
    let mut curves = vec![Curve {
        name: "magg (in-process)".into(),
        points,
    }];
    let peer_files = config.peers.as_deref().map(peer_files).unwrap_or_default();
    for file in &peer_files {
        curves.extend(peer_curves(file)?);
    }
    let time_to = times_to_targets(&curves);
    let report = ErrorReport {
        scene: config.scene.clone(),
        reference: config.reference.clone(),
        curves,
        peer_files,
        time_to,
    };
    let mut f = Vec::new();
    writeln!(f, "renderer,spp,wall_s,render_s,rel_mse").map_err(folder)?;
    for c in &report.curves {
        for p in &c.points {
            writeln!(
                f,
                "{},{},{:.4},{:.4},{:.6e}",
                c.name, p.spp, p.wall_s, p.render_s, p.rel_mse
            )
            .map_err(folder)?;
        }
    }
    scene_io::image_io::write_atomic(&dir.join("error.csv"), &f)?;
    let series: Vec<(String, Vec<(f64, f64)>)> = report
        .curves
        .iter()
        .map(|c| {
            let pts = c.points.iter().map(|p| (p.wall_s, p.rel_mse)).collect();
            (c.name.clone(), pts)
        })
        .collect();
    crate::plot::log_log_png(
        &dir.join("error.png"),
        "relMSE against wall time (whole command)",
        "wall time (s)",
        "relMSE",
        &series,
    )?;
    scene_io::image_io::write_atomic(&dir.join("report.md"), report_md(&report).as_bytes())?;
    Ok(report)
}

/// The peers' rows of a `bench/peers/` script's results, a curve per renderer and variant;
/// the script's own magg rows are left out (the sweep's magg curve is this run's).
fn peer_curves(path: &Path) -> Result<Vec<Curve>, crate::LabError> {
    let text = std::fs::read(path).map_err(crate::LabError::folder(path))?;
    let v: serde_json::Value = serde_json::from_slice(&text)
        .map_err(|e| crate::LabError::Draw(format!("{}: {e}", path.display())))?;
    let mut curves: Vec<Curve> = Vec::new();
    for r in v["runs"].as_array().into_iter().flatten() {
        let renderer = r["renderer"].as_str().unwrap_or("?");
        if renderer == "magg" {
            continue;
        }
        let name = format!("{renderer} {}", r["variant"].as_str().unwrap_or(""));
        let point = ErrorPoint {
            spp: r["spp"].as_u64().unwrap_or(0) as u32,
            wall_s: r["wall_s"].as_f64().unwrap_or(f64::NAN),
            render_s: r["render_s"].as_f64().unwrap_or(f64::NAN),
            rel_mse: r["rel_mse"].as_f64().unwrap_or(f64::NAN),
        };
        match curves.iter_mut().find(|c| c.name == name) {
            Some(c) => c.points.push(point),
            None => curves.push(Curve {
                name,
                points: vec![point],
            }),
        }
    }
    for c in &mut curves {
        c.points.sort_by_key(|p| p.spp);
    }
    Ok(curves)
}

/// The table of time to each error, with ratios to magg's.
pub fn table(r: &ErrorReport) -> String {
    let f = |t: Option<f64>| t.map_or("-".to_string(), |t| format!("{t:.2}"));
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) => format!("{:.2}", a / b),
        _ => "-".into(),
    };
    let (_, m2, m3) = r.time_to[0].clone();
    let mut s = String::from(
        "| renderer | s to relMSE 1e-2 | s to relMSE 1e-3 | magg / it at 1e-2 | magg / it at 1e-3 |\n\
         |---|---:|---:|---:|---:|\n",
    );
    for (name, t2, t3) in &r.time_to {
        s.push_str(&format!(
            "| {name} | {} | {} | {} | {} |\n",
            f(*t2),
            f(*t3),
            ratio(m2, *t2),
            ratio(m3, *t3)
        ));
    }
    s
}

fn report_md(r: &ErrorReport) -> String {
    let peers = if r.peer_files.is_empty() {
        "No peer results were found (run `python3 bench/peers/mitsuba.py` or \
         `python3 bench/peers/cycles.py` first to add Mitsuba 3's or Blender Cycles' curves)."
            .to_string()
    } else {
        let files: Vec<String> = r
            .peer_files
            .iter()
            .map(|f| format!("`{}`", f.display()))
            .collect();
        format!(
            "Peer curves come from {} (each its script's own run on this machine, at its \
             own time: compare within a file, or re-run them together).",
            files.join(", ")
        )
    };
    format!(
        "# Run time against error\n\n\
         Scene `{}`, reference `{}`. Each point is a whole command (scene loading included); \
         a dash means the curve does not reach that error (no extrapolation).\n\n\
         ![relMSE against wall time](error.png)\n\n{}\n{}\n",
        r.scene.display(),
        r.reference.display(),
        table(r),
        peers
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_to_reach_interpolates_on_log_log_axes_and_never_extrapolates() {
        // relMSE proportional to 1/time: 1e-2 at 1 s, 1e-3 at 10 s.
        let pts = [(1.0, 1e-2), (10.0, 1e-3), (100.0, 1e-4)];
        assert!((time_to_reach(&pts, 1e-2).unwrap() - 1.0).abs() < 1e-9);
        let mid = time_to_reach(&pts, 10f64.powf(-2.5)).unwrap();
        assert!((mid - 10f64.sqrt()).abs() < 1e-9, "{mid}");
        assert_eq!(time_to_reach(&pts, 1e-5), None);
        assert_eq!(time_to_reach(&pts, 1e-1), None);
        assert_eq!(time_to_reach(&[(1.0, 1e-2)], 1e-2), None);
    }

    #[test]
    fn peer_rows_become_one_curve_per_variant_without_magg() {
        let dir = std::env::temp_dir().join(format!("magg-peers-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let json = serde_json::json!({"runs": [
            {"renderer": "mitsuba", "variant": "llvm_ad_rgb", "spp": 64, "wall_s": 3.0, "render_s": 2.0, "rel_mse": 2e-3},
            {"renderer": "mitsuba", "variant": "llvm_ad_rgb", "spp": 16, "wall_s": 1.0, "render_s": 0.5, "rel_mse": 1e-2},
            {"renderer": "mitsuba", "variant": "scalar_rgb", "spp": 16, "wall_s": 2.0, "render_s": 1.5, "rel_mse": 1e-2},
            {"renderer": "magg", "variant": "in-process", "spp": 16, "wall_s": 1.0, "render_s": 1.0, "rel_mse": 8e-3}
        ]});
        let path = dir.join("mitsuba-results.json");
        std::fs::write(&path, json.to_string()).unwrap();
        let curves = peer_curves(&path).unwrap();
        assert_eq!(curves.len(), 2);
        assert_eq!(curves[0].name, "mitsuba llvm_ad_rgb");
        assert_eq!(
            curves[0].points.iter().map(|p| p.spp).collect::<Vec<_>>(),
            [16, 64]
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn cycles_results_beside_mitsubas_add_a_curve_and_a_row_with_ratios() {
        let dir = std::env::temp_dir().join(format!("magg-peers-cycles-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mitsuba = dir.join("mitsuba-results.json");
        // A fresh clone: no peer results at all.
        assert!(peer_files(&mitsuba).is_empty());
        // Only Cycles was run: its file is found beside the (absent) Mitsuba one.
        let cycles = dir.join("cycles-results.json");
        let json = serde_json::json!({"runs": [
            {"renderer": "Cycles", "variant": "CPU 2 threads", "spp": 2, "wall_s": 4.0, "render_s": 1.0, "rel_mse": 1e-2},
            {"renderer": "magg", "variant": "in-process", "spp": 2, "wall_s": 1.0, "render_s": 0.5, "rel_mse": 1e-2},
            {"renderer": "Cycles", "variant": "CPU 2 threads", "spp": 1, "wall_s": 2.0, "render_s": 0.5, "rel_mse": 1e-1},
            {"renderer": "Cycles", "variant": "CPU 2 threads", "spp": 4, "wall_s": 8.0, "render_s": 2.0, "rel_mse": 1e-3}
        ]});
        std::fs::write(&cycles, json.to_string()).unwrap();
        assert_eq!(peer_files(&mitsuba), std::slice::from_ref(&cycles));
        // Both: Mitsuba's first, each file once even when the Cycles one is the given one.
        let json = serde_json::json!({"runs": [
            {"renderer": "Mitsuba", "variant": "llvm_ad_rgb", "spp": 16, "wall_s": 1.0, "render_s": 0.5, "rel_mse": 1e-2}
        ]});
        std::fs::write(&mitsuba, json.to_string()).unwrap();
        assert_eq!(peer_files(&mitsuba), [mitsuba.clone(), cycles.clone()]);
        assert_eq!(peer_files(&cycles), [cycles.clone(), mitsuba.clone()]);

        let curves = peer_curves(&cycles).unwrap();
        assert_eq!(
            curves.len(),
            1,
            "the script's own magg rows are not a peer curve"
        );
        assert_eq!(curves[0].name, "Cycles CPU 2 threads");
        assert_eq!(
            curves[0].points.iter().map(|p| p.spp).collect::<Vec<_>>(),
            [1, 2, 4]
        );
        let magg = Curve {
            name: "magg (in-process)".into(),
            points: vec![
                ErrorPoint {
                    spp: 1,
                    wall_s: 1.0,
                    render_s: 0.5,
                    rel_mse: 1e-2,
                },
                ErrorPoint {
                    spp: 4,
                    wall_s: 2.0,
                    render_s: 1.5,
                    rel_mse: 1e-3,
                },
            ],
        };
        let mut all = vec![magg];
        all.extend(curves);
        let time_to = times_to_targets(&all);
        let report = ErrorReport {
            scene: "s.gltf".into(),
            reference: "r.exr".into(),
            curves: all,
            peer_files: vec![cycles.clone()],
            time_to,
        };
        let t = table(&report);
        // Cycles: 4 s to 1e-2 and 8 s to 1e-3; magg 1 s and 2 s: ratios 0.25 both.
        assert!(
            t.contains("| Cycles CPU 2 threads | 4.00 | 8.00 | 0.25 | 0.25 |"),
            "{t}"
        );
        assert!(report_md(&report).contains("cycles-results.json"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
