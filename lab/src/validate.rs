//! `experiment validate`: the simulator's predictions against real renders this machine can
//! run honestly. Two cores cannot show 80 processors computing at once, so the cases are
//! those where the cores do not distort the measurement: one and two render nodes of one
//! thread each, and the 86-process cluster with the paper's link model at its real time
//! scale, where link time dominates computing. Each render is simulated from its own
//! per-subscreen records; the two-node render is also predicted from the one-node render's
//! records, which is what the simulator is for (a machine that was not measured).

use std::{io::Write, path::Path};

use serde::Serialize;

use crate::{
    runs::render_run,
    simulate::{Overrides, measure_overheads, predict},
};

/// The part of a case's name after its colon: "demand 40%" of the cluster cases.
fn short(name: &str) -> &str {
    name.rsplit(": paper links and ").next().unwrap_or(name)
}

/// One prediction against one measurement.
#[derive(Clone, Debug, Serialize)]
pub struct ValidationRow {
    pub case: String,
    pub predicted_from: String,
    pub measured_s: f64,
    pub predicted_s: f64,
    pub error_percent: f64,
}

struct Case {
    name: &'static str,
    args: Vec<String>,
}

fn strings(a: &[&str]) -> Vec<String> {
    a.iter().map(|s| s.to_string()).collect()
}

fn measured(stats: &serde_json::Value) -> f64 {
    stats["seconds"]["render"].as_f64().unwrap_or(f64::NAN)
}

fn row(case: &str, from: &str, measured_s: f64, predicted_s: f64) -> ValidationRow {
    ValidationRow {
        case: case.into(),
        predicted_from: from.into(),
        measured_s,
        predicted_s,
        error_percent: 100.0 * (predicted_s - measured_s) / measured_s,
    }
}

/// Renders each case, simulates it, writes `validate.csv` and `report.md` into `dir`.
/// `scene` is rendered at `width` x `height` with `spp` samples for the compute-bound cases.
pub fn validate(
    program: &Path,
    scene: &Path,
    size: (u32, u32, u32),
    dir: &Path,
) -> Result<Vec<ValidationRow>, crate::LabError> {
    let folder = crate::LabError::folder(dir);
    std::fs::create_dir_all(dir).map_err(folder)?;
    let (w, h, spp) = (size.0.to_string(), size.1.to_string(), size.2.to_string());
    let image = |w: &str, h: &str, spp: &str| {
        [
            vec![scene.display().to_string()],
            strings(&["--width", w, "--height", h, "--spp", spp, "--threads", "1"]),
        ]
        .concat()
    };
    let compute = image(&w, &h, &spp);
    // Link-bound: a small image at 1 spp, the paper's link model at the paper's own times.
    let links = [
        image("64", "48", "1"),
        strings(&[
            "--spawn",
            "magg",
            "--link-model",
            "paper",
            "--time-scale",
            "1",
        ]),
    ]
    .concat();
    let cases = [
        Case {
            name: "1 render node",
            args: [compute.clone(), strings(&["--spawn", "grid:1x1x1"])].concat(),
        },
        Case {
            name: "2 render nodes",
            args: [compute.clone(), strings(&["--spawn", "grid:1x1x2"])].concat(),
        },
        Case {
            name: "86 processes: paper links and demand 40%",
            args: [
                links.clone(),
                strings(&["--transfer", "demand", "--cache", "40"]),
            ]
            .concat(),
        },
        Case {
            name: "86 processes: paper links and batch",
            args: [links.clone(), strings(&["--transfer", "batch"])].concat(),
        },
    ];
    let mut rows = Vec::new();
    let mut texts = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        tracing::info!("validate: {}", case.name);
        let stats_path = dir.join(format!("case-{i}.json"));
        let stats = render_run(
            program,
            &case.args,
            &dir.join(format!("case-{i}.pfm")),
            &stats_path,
        )?;
        let text = std::fs::read_to_string(&stats_path).map_err(folder)?;
        let p = predict(&text, &Overrides::default())?;
        rows.push(row(
            case.name,
            "its own records",
            measured(&stats),
            p.predicted_s,
        ));
        texts.push((text, measured(&stats)));
    }
    // The two-node render predicted from the one-node render's records.
    let two_nodes = Overrides {
        topology: Some("grid:1x1x2".into()),
        ..Overrides::default()
    };
    let p = predict(&texts[0].0, &two_nodes)?;
    rows.push(row(
        "2 render nodes",
        "the 1-node render's records",
        texts[1].1,
        p.predicted_s,
    ));
    // The cluster cases again with the real costs beyond the models, measured on this
    // machine: from the render's own records, and from the other cluster render's.
    let measured_overheads = [
        measure_overheads(&texts[2].0)?.overheads,
        measure_overheads(&texts[3].0)?.overheads,
    ];
    for (case, other) in [(2, 3), (3, 2)] {
        for (source, from) in [(case, "its own records and overheads"), (other, "")] {
            let from = if source == case {
                from.to_string()
            } else {
                format!(
                    "its own records with the overheads of the {} render",
                    short(cases[other].name)
                )
            };
            let with = Overrides {
                overheads: Some(measured_overheads[source - 2]),
                ..Overrides::default()
            };
            let p = predict(&texts[case].0, &with)?;
            rows.push(row(cases[case].name, &from, texts[case].1, p.predicted_s));
        }
    }
    let mut f = Vec::new();
    writeln!(
        f,
        "case,predicted_from,measured_s,predicted_s,error_percent"
    )
    .map_err(folder)?;
    for r in &rows {
        writeln!(
            f,
            "{},{},{:.4},{:.4},{:.2}",
            r.case, r.predicted_from, r.measured_s, r.predicted_s, r.error_percent
        )
        .map_err(folder)?;
    }
    scene_io::image_io::write_atomic(&dir.join("validate.csv"), &f)?;
    scene_io::image_io::write_atomic(&dir.join("report.md"), report_md(&rows).as_bytes())?;
    Ok(rows)
}

/// The table the command prints and the report holds.
pub fn table(rows: &[ValidationRow]) -> String {
    let mut s = String::from(
        "| case | predicted from | measured render (s) | predicted (s) | error |\n\
         |---|---|---:|---:|---:|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {:+.1}% |\n",
            r.case, r.predicted_from, r.measured_s, r.predicted_s, r.error_percent
        ));
    }
    s
}

fn report_md(rows: &[ValidationRow]) -> String {
    let worst = rows
        .iter()
        .map(|r| r.error_percent.abs())
        .fold(0.0, f64::max);
    format!(
        "# The simulator against real renders\n\n\
         Each render ran on this machine; the simulator replayed its per-subscreen records \
         (thread CPU time, chunks and tiles touched) on the same topology, link model, \
         transfer and scheduling. Render time is the host's, from the first subscreen handed \
         out to the last pixels in.\n\n{}\n\
         The rows with overheads add the real costs per hop and before the start read off \
         a recorded cluster render (`lab::simulate::measure_overheads`): from the render \
         itself (not independent) or from the other cluster render (a cross-check).\n\n\
         Largest error: {:.1}% (the aim is 15%). Two cores run the host, the fork nodes and the \
         render nodes, so the two-node case also measures how the host and fork node share the \
         cores with the renderers; the link-bound cases at the paper's time scale spend most \
         of their time in modelled link delays, which the cores do not stretch.\n",
        table(rows),
        worst
    )
}
