//! Plots of experiment results as PNG files.
//!
//! Text is drawn with DejaVu Sans, built into the binary (`lab/fonts/`, Bitstream Vera
//! licence beside it), so plots have their labels wherever the binary runs, the `FROM
//! scratch` container image included, which has no fonts. `MAGG_FONT` names another
//! TrueType file to use instead.

use std::{path::Path, sync::OnceLock};

use plotters::prelude::*;

use crate::experiment::LinksReport;

/// The font every label is drawn in unless `MAGG_FONT` names another.
pub const EMBEDDED_FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

static HAVE_FONT: OnceLock<bool> = OnceLock::new();

/// Registers the font for text, once: `MAGG_FONT` if it names a usable TrueType file, else
/// the embedded one. False only if neither registers (plots are then drawn without labels).
pub fn ensure_font() -> bool {
    *HAVE_FONT.get_or_init(|| {
        if let Some(path) = std::env::var_os("MAGG_FONT") {
            match std::fs::read(&path) {
                Ok(bytes) => {
                    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                    if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                        .is_ok()
                    {
                        return true;
                    }
                    tracing::warn!(
                        "MAGG_FONT={}: not a TrueType font; using the built-in one",
                        Path::new(&path).display()
                    );
                }
                Err(e) => tracing::warn!(
                    "MAGG_FONT={}: {e}; using the built-in font",
                    Path::new(&path).display()
                ),
            }
        }
        let ok =
            plotters::style::register_font("sans-serif", FontStyle::Normal, EMBEDDED_FONT).is_ok();
        if !ok {
            tracing::warn!("the built-in font did not load; plots have no labels");
        }
        ok
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
    log_log_marked_png(path, title, x_label, y_label, series, &[])
}

/// Whether `v` can be placed on a log axis whose ends lie a quarter beyond the values: from
/// 1e-300 to 1e300, so that the ends are finite and not subnormal (an axis ending at infinity,
/// or at 1e-311, was drawn without end).
fn on_log_axis(v: f64) -> bool {
    (1e-300..=1e300).contains(&v)
}

/// [`log_log_png`] with a second kind of series drawn as marks only (measured points beside
/// simulated curves); the i-th mark series takes the colour of the i-th line, so a measured
/// set and its simulated curve match.
pub fn log_log_marked_png(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
    marks: &[(String, Vec<(f64, f64)>)],
) -> Result<(), crate::LabError> {
    let (w, h) = (1200u32, 800u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let labels = ensure_font();
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(crate::LabError::draw)?;
        let pts: Vec<(f64, f64)> = series
            .iter()
            .chain(marks)
            .flat_map(|s| s.1.iter().copied())
            .filter(|p| on_log_axis(p.0) && on_log_axis(p.1))
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
        for (i, (name, points)) in marks.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let s = chart
                .draw_series(
                    points
                        .iter()
                        .map(|&p| Cross::new(p, 9, color.stroke_width(3))),
                )
                .map_err(crate::LabError::draw)?;
            if labels {
                s.label(name.clone())
                    .legend(move |(x, y)| Cross::new((x + 10, y), 6, color.stroke_width(3)));
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A point too large or too small to give its axis a finite, normal end (a peer's wall
    /// time of 1e308 s, a relMSE of 1e-320) is left out; the plot of the others is drawn (it
    /// hung), and a plot of no plottable point says so.
    #[test]
    fn points_no_log_axis_can_hold_are_left_out() {
        let dir = std::env::temp_dir().join(format!("magg-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.png");
        let series = vec![(
            "a".to_string(),
            vec![
                (1.0, 0.5),
                (2.0, 0.25),
                (1e308, 0.1),
                (f64::INFINITY, 0.1),
                (1.5, 1e-320),
                (1e-311, 0.3),
            ],
        )];
        log_log_png(&path, "t", "x", "y", &series).unwrap();
        assert!(path.exists());
        let none = vec![("a".to_string(), vec![(1e308, 0.5), (-1.0, f64::NAN)])];
        assert!(matches!(
            log_log_png(&path, "t", "x", "y", &none),
            Err(crate::LabError::NothingToPlot)
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
