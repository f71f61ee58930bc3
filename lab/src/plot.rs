//! Plots of experiment results as PNG files.
//!
//! Text needs a font: the file named by `MAGG_FONT`, else the one fontconfig (`fc-match`)
//! picks for sans-serif, else the first of a few common DejaVu paths (Debian, Arch, Fedora).
//! Without one, the plot is drawn without labels and says so in the log; the CSV next to it
//! holds the numbers either way.

use std::{path::Path, sync::OnceLock};

use plotters::prelude::*;

use crate::experiment::LinksReport;

const FONT_FILES: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

static HAVE_FONT: OnceLock<bool> = OnceLock::new();

/// Font files to try, most specific first.
fn font_candidates() -> Vec<std::path::PathBuf> {
    let mut files: Vec<std::path::PathBuf> = std::env::var_os("MAGG_FONT")
        .into_iter()
        .map(Into::into)
        .collect();
    // fontconfig knows the machine's fonts wherever its distribution keeps them.
    if let Ok(o) = std::process::Command::new("fc-match")
        .args(["--format=%{file}", "sans-serif:style=Regular"])
        .output()
        && o.status.success()
        && let Ok(path) = String::from_utf8(o.stdout)
        && (path.ends_with(".ttf") || path.ends_with(".otf"))
    {
        files.push(path.into());
    }
    files.extend(FONT_FILES.iter().map(Into::into));
    files
}

/// Registers a font for text, once; false when the machine has none.
pub fn ensure_font() -> bool {
    *HAVE_FONT.get_or_init(|| {
        for f in font_candidates() {
            if let Ok(bytes) = std::fs::read(&f) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        tracing::warn!(
            "no TrueType font found ({}); plots have no labels",
            FONT_FILES.join(", ")
        );
        false
    })
}

/// Encodes an RGB buffer as PNG, atomically.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), crate::LabError> {
    let mut out = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut out),
        rgb,
        width,
        height,
        image::ExtendedColorType::Rgb8,
    )?;
    Ok(scene_io::image_io::write_atomic(path, &out)?)
}

/// Line plot of one or more series: `(label, points)`, log-log.
pub fn log_log_png(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), crate::LabError> {
    let (w, h) = (1200u32, 800u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let labels = ensure_font();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(crate::LabError::draw)?;
        let pts: Vec<(f64, f64)> = series
            .iter()
            .flat_map(|s| s.1.iter().copied())
            .filter(|p| p.0 > 0.0 && p.1 > 0.0 && p.1.is_finite())
            .collect();
        if pts.is_empty() {
            return Err(crate::LabError::NothingToPlot);
        }
        let (x0, x1) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.0), a.1.max(p.0)));
        let (y0, y1) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.1), a.1.max(p.1)));
        let mut builder = ChartBuilder::on(&root);
        builder
            .margin(20)
            .x_label_area_size(if labels { 50 } else { 10 })
            .y_label_area_size(if labels { 80 } else { 10 });
        if labels {
            builder.caption(title, ("sans-serif", 28));
        }
        let mut chart = builder
            .build_cartesian_2d(
                (x0 * 0.8..x1 * 1.25).log_scale(),
                (y0 * 0.8..y1 * 1.25).log_scale(),
            )
            .map_err(crate::LabError::draw)?;
        let mut mesh = chart.configure_mesh();
        if labels {
            mesh.x_desc(x_label).y_desc(y_label);
        } else {
            mesh.disable_x_axis().disable_y_axis();
        }
        mesh.draw().map_err(crate::LabError::draw)?;
        for (i, (name, points)) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(points.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(crate::LabError::draw)?;
            let s = chart
                .draw_series(LineSeries::new(
                    points.iter().copied(),
                    color.stroke_width(2),
                ))
                .map_err(crate::LabError::draw)?;
            if labels {
                s.label(name.clone()).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            }
        }
        if labels {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 16))
                .position(SeriesLabelPosition::UpperLeft)
                .draw()
                .map_err(crate::LabError::draw)?;
        }
        root.present().map_err(crate::LabError::draw)?;
    }
    write_png(path, w, h, &buf)
}

/// Figure 1.5 (one node active) or 1.6 (many at once): mean transfer time against data
/// size, a line per (who was active, transfer kind).
pub fn transfers_png(
    path: &Path,
    r: &LinksReport,
    many: bool,
    title: &str,
) -> Result<(), crate::LabError> {
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for t in r
        .transfers
        .iter()
        .filter(|t| t.active.starts_with("1 node") != many)
    {
        let name = format!("{}, {}", t.active, t.transfer);
        match series.iter_mut().find(|s| s.0 == name) {
            Some(s) => s.1.push((t.bytes as f64, t.mean_us)),
            None => series.push((name, vec![(t.bytes as f64, t.mean_us)])),
        }
    }
    log_log_png(path, title, "data size (bytes)", "time (us)", &series)
}
