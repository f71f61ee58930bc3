//! `experiment load-balance`, the paper's figure 1.10 ("Effectiveness of load balancing"):
//! the same image on the same cluster three ways, and how each render node spent the render.
//!
//! * static: one subscreen per render node, the division fixed before anyone starts;
//! * dynamic: many subscreens handed out on request (the paper's "simple dynamic load
//!   balancing": "a number of subscreens sufficiently greater than the number of NPs");
//! * adaptive: the same, and idle nodes take the unbegun half of a busy node's subscreen
//!   (the redivision the paper announces at its end).
//!
//! Each render node's busy, waiting (for data) and idle seconds come from the cluster's
//! `--stats`; the figure is one stacked bar per node, a panel per run. The finding tested:
//! dynamic division leaves less idle time than static, and the whole render is faster.

use std::{io::Write, path::Path};

use plotters::prelude::*;
use serde::Serialize;

use crate::runs::{RunError, render_run};

/// How one render node spent one render.
#[derive(Clone, Debug, Serialize)]
pub struct NodeTimes {
    pub node: u64,
    pub subscreens: u64,
    pub busy_s: f64,
    pub waiting_s: f64,
    pub idle_s: f64,
}

/// One way of dividing the image, rendered once.
#[derive(Clone, Debug, Serialize)]
pub struct BalanceRun {
    pub name: String,
    pub subscreens: u64,
    pub adaptive: bool,
    pub wall_s: f64,
    pub render_s: f64,
    /// Idle seconds over all render nodes' busy + waiting + idle seconds.
    pub idle_share: f64,
    /// The busiest node's busy seconds over the mean: 1 is perfect balance.
    pub busy_max_over_mean: f64,
    pub identical: bool,
    pub nodes: Vec<NodeTimes>,
}

#[derive(Clone, Debug, Serialize)]
pub struct BalanceReport {
    pub render_nodes: usize,
    pub runs: Vec<BalanceRun>,
    /// Dynamic division left a smaller idle share than static and rendered faster.
    pub finding_holds: bool,
}

/// The render nodes' times in a cluster render's stats, by node id.
pub fn node_times(stats: &serde_json::Value) -> Vec<NodeTimes> {
    let mut nodes: Vec<NodeTimes> = stats["nodes"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|n| n["role"] == "Render")
        .map(|n| NodeTimes {
            node: n["node"].as_u64().unwrap_or(0),
            subscreens: n["subscreens"].as_u64().unwrap_or(0),
            busy_s: n["busy_s"].as_f64().unwrap_or(0.0),
            waiting_s: n["waiting_s"].as_f64().unwrap_or(0.0),
            idle_s: n["idle_s"].as_f64().unwrap_or(0.0),
        })
        .collect();
    nodes.sort_by_key(|n| n.node);
    nodes
}

fn summarise(name: &str, adaptive: bool, stats: &serde_json::Value, identical: bool) -> BalanceRun {
    let nodes = node_times(stats);
    let total: f64 = nodes
        .iter()
        .map(|n| n.busy_s + n.waiting_s + n.idle_s)
        .sum();
    let idle: f64 = nodes.iter().map(|n| n.idle_s).sum();
    let mean_busy = nodes.iter().map(|n| n.busy_s).sum::<f64>() / nodes.len().max(1) as f64;
    let max_busy = nodes.iter().map(|n| n.busy_s).fold(0.0, f64::max);
    BalanceRun {
        name: name.to_string(),
        subscreens: stats["subscreen_count"].as_u64().unwrap_or(0),
        adaptive,
        wall_s: stats["seconds"]["total"].as_f64().unwrap_or(f64::NAN),
        render_s: stats["seconds"]["render"].as_f64().unwrap_or(f64::NAN),
        idle_share: if total > 0.0 { idle / total } else { 0.0 },
        busy_max_over_mean: if mean_busy > 0.0 {
            max_busy / mean_busy
        } else {
            1.0
        },
        identical,
        nodes,
    }
}

/// Renders `render_args` on `cluster_args` three ways (static: one subscreen per render node;
/// dynamic: `dynamic_subscreens`; adaptive: the same with `--adaptive`), writes the stats,
/// `load-balance.csv`, `load-balance.png` and `report.md` into `dir`.
pub fn load_balance(
    program: &Path,
    render_args: &[String],
    cluster_args: &[String],
    dynamic_subscreens: u32,
    dir: &Path,
) -> Result<BalanceReport, crate::LabError> {
    std::fs::create_dir_all(dir).map_err(crate::LabError::folder(dir))?;
    let base = [render_args, cluster_args].concat();
    // A first dynamic run tells how many render nodes the cluster has.
    let run = |name: &str, extra: &[String]| -> Result<(serde_json::Value, Vec<u8>), RunError> {
        let out = dir.join(format!("{name}.pfm"));
        tracing::info!("load-balance: {name}");
        let stats = render_run(
            program,
            &[&base[..], extra].concat(),
            &out,
            &dir.join(format!("{name}.json")),
        )?;
        Ok((stats, std::fs::read(&out)?))
    };
    let dynamic_args = ["--subscreens".to_string(), dynamic_subscreens.to_string()];
    let (dynamic, reference) = run("dynamic", &dynamic_args)?;
    let render_nodes = node_times(&dynamic).len();
    let static_args = ["--subscreens".to_string(), render_nodes.max(1).to_string()];
    let (fixed, fixed_image) = run("static", &static_args)?;
    let adaptive_args = [&dynamic_args[..], &["--adaptive".to_string()]].concat();
    let (adaptive, adaptive_image) = run("adaptive", &adaptive_args)?;

    let runs = vec![
        summarise("static", false, &fixed, fixed_image == reference),
        summarise("dynamic", false, &dynamic, true),
        summarise("adaptive", true, &adaptive, adaptive_image == reference),
    ];
    let finding_holds = runs[1].idle_share < runs[0].idle_share && runs[1].wall_s < runs[0].wall_s;
    let report = BalanceReport {
        render_nodes,
        runs,
        finding_holds,
    };
    write_csv(&dir.join("load-balance.csv"), &report)?;
    bars_png(&dir.join("load-balance.png"), &report)?;
    scene_io::image_io::write_atomic(&dir.join("report.md"), report_md(&report).as_bytes())?;
    Ok(report)
}

fn write_csv(path: &Path, r: &BalanceReport) -> Result<(), crate::LabError> {
    let io = crate::LabError::folder(path);
    let mut f = Vec::new();
    writeln!(
        f,
        "run,subscreens,node,node_subscreens,busy_s,waiting_s,idle_s"
    )
    .map_err(io)?;
    for run in &r.runs {
        for n in &run.nodes {
            writeln!(
                f,
                "{},{},{},{},{:.4},{:.4},{:.4}",
                run.name, run.subscreens, n.node, n.subscreens, n.busy_s, n.waiting_s, n.idle_s
            )
            .map_err(io)?;
        }
    }
    scene_io::image_io::write_atomic(path, &f)?;
    Ok(())
}

/// The table the command prints and the report holds.
pub fn table(r: &BalanceReport) -> String {
    let mut s = String::from(
        "| run | subscreens | wall (s) | render (s) | idle share | busiest / mean busy | same image |\n\
         |---|---:|---:|---:|---:|---:|---|\n",
    );
    for run in &r.runs {
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.1}% | {:.2} | {} |\n",
            run.name,
            run.subscreens,
            run.wall_s,
            run.render_s,
            100.0 * run.idle_share,
            run.busy_max_over_mean,
            if run.identical { "yes" } else { "NO" }
        ));
    }
    s
}

fn report_md(r: &BalanceReport) -> String {
    let (fixed, dynamic, adaptive) = (&r.runs[0], &r.runs[1], &r.runs[2]);
    format!(
        "# Load balancing (the paper's figure 1.10)\n\n\
         > \"HP subdivides a screen area into a number of subscreens sufficiently greater than \
         the number of NPs. These subscreens are assigned via serial links according to NPs' \
         requests in order to balance the load of each NP (simple dynamic load balancing).\"\n\n\
         ![busy, waiting and idle time per render node](load-balance.png)\n\n{}\n\
         **Finding: {}.** With one subscreen per render node ({} nodes) the nodes sat idle for \
         {:.1}% of their time and the busiest was busy {:.2}x the mean; with {} subscreens \
         handed out on request, {:.1}% and {:.2}x, and the render took {:.2} s instead of \
         {:.2} s. Adaptive redivision (the paper's last section: \"an adaptive redivision of \
         subscreens should be effective\"): idle {:.1}%, {:.2} s.\n\n\
         Times are wall-clock seconds of each node's rendering threads, measured on this \
         machine's cores, which every render node shares: a node's busy time includes time \
         its threads waited for a core.\n",
        table(r),
        if r.finding_holds {
            "reproduced"
        } else {
            "not reproduced"
        },
        r.render_nodes,
        100.0 * fixed.idle_share,
        fixed.busy_max_over_mean,
        dynamic.subscreens,
        100.0 * dynamic.idle_share,
        dynamic.busy_max_over_mean,
        dynamic.wall_s,
        fixed.wall_s,
        100.0 * adaptive.idle_share,
        adaptive.wall_s,
    )
}

/// One panel per run: a stacked bar per render node (busy, waiting, idle).
fn bars_png(path: &Path, r: &BalanceReport) -> Result<(), crate::LabError> {
    let (w, h) = (1400u32, 300 * r.runs.len() as u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let labels = crate::plot::ensure_font();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(crate::LabError::draw)?;
        let longest = r
            .runs
            .iter()
            .flat_map(|run| run.nodes.iter())
            .map(|n| n.busy_s + n.waiting_s + n.idle_s)
            .fold(0.0, f64::max)
            .max(1e-6);
        let colours = [
            RGBColor(40, 90, 170),
            RGBColor(230, 150, 40),
            RGBColor(200, 200, 200),
        ];
        for (panel, run) in root.split_evenly((r.runs.len(), 1)).iter().zip(&r.runs) {
            let mut builder = ChartBuilder::on(panel);
            builder
                .margin(10)
                .x_label_area_size(if labels { 35 } else { 5 })
                .y_label_area_size(if labels { 60 } else { 5 });
            if labels {
                builder.caption(
                    format!(
                        "{}: {} subscreens, wall {:.2} s, idle {:.1}% (blue busy, orange waiting, grey idle)",
                        run.name,
                        run.subscreens,
                        run.wall_s,
                        100.0 * run.idle_share
                    ),
                    ("sans-serif", 18),
                );
            }
            let n = run.nodes.len().max(1) as f64;
            let mut chart = builder
                .build_cartesian_2d(0.0..n, 0.0..longest * 1.05)
                .map_err(crate::LabError::draw)?;
            let mut mesh = chart.configure_mesh();
            mesh.disable_x_mesh();
            if labels {
                mesh.x_desc("render node").y_desc("seconds");
            } else {
                mesh.disable_x_axis().disable_y_axis();
            }
            mesh.draw().map_err(crate::LabError::draw)?;
            for (i, node) in run.nodes.iter().enumerate() {
                let x = i as f64;
                let mut y = 0.0;
                for (part, colour) in [node.busy_s, node.waiting_s, node.idle_s]
                    .iter()
                    .zip(colours)
                {
                    chart
                        .draw_series(std::iter::once(Rectangle::new(
                            [(x + 0.1, y), (x + 0.9, y + part)],
                            colour.filled(),
                        )))
                        .map_err(crate::LabError::draw)?;
                    y += part;
                }
            }
        }
        root.present().map_err(crate::LabError::draw)?;
    }
    crate::plot::write_png(path, w, h, &buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(idle: &[f64]) -> serde_json::Value {
        let nodes: Vec<serde_json::Value> = idle
            .iter()
            .enumerate()
            .map(|(i, &idle)| {
                serde_json::json!({"node": i + 2, "role": "Render", "subscreens": 1,
                    "busy_s": 2.0 - idle, "waiting_s": 0.0, "idle_s": idle})
            })
            .chain(std::iter::once(
                serde_json::json!({"node": 1, "role": "Fork", "busy_s": 9.0}),
            ))
            .collect();
        serde_json::json!({"nodes": nodes, "subscreen_count": idle.len(), "seconds": {"total": 2.0, "render": 2.0}})
    }

    #[test]
    fn only_render_nodes_count_and_shares_add_up() {
        let run = summarise("static", false, &stats(&[0.0, 1.0]), true);
        assert_eq!(run.nodes.len(), 2, "the fork node is not a render node");
        assert!((run.idle_share - 0.25).abs() < 1e-12);
        // Busy 2 and 1, mean 1.5: the busiest is 4/3 of the mean.
        assert!((run.busy_max_over_mean - 4.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn the_chart_and_table_are_written() {
        let dir = std::env::temp_dir().join(format!("magg-balance-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let report = BalanceReport {
            render_nodes: 2,
            runs: vec![
                summarise("static", false, &stats(&[0.0, 1.0]), true),
                summarise("dynamic", false, &stats(&[0.1, 0.1]), true),
                summarise("adaptive", true, &stats(&[0.0, 0.05]), true),
            ],
            finding_holds: true,
        };
        bars_png(&dir.join("b.png"), &report).unwrap();
        assert!(std::fs::metadata(dir.join("b.png")).unwrap().len() > 1000);
        let md = report_md(&report);
        assert!(md.contains("| static | 2 |"), "{md}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
