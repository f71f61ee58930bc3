//! `magg-host plot STATS.json`: pictures of one render from the per-subscreen records of its
//! `--stats` file. A timeline (a row per render node, a bar per subscreen from when it was
//! handed out to when its last pixels arrived, darker the more bytes were fetched for it)
//! shows who waited and who was busy; the final image with each subscreen tinted in its
//! node's colour shows where the work went. Both read only the stats file and the image it
//! names, so any render, in one process or on a cluster, can be looked at afterwards.

use std::path::{Path, PathBuf};

use host::stats::SubscreenRecord;
use plotters::prelude::*;
use serde::Deserialize;

use crate::{
    LabError,
    plot::{ensure_font, write_png},
};

/// The part of a `--stats` file the plots need.
#[derive(Debug, Deserialize)]
pub struct RenderRecords {
    /// The image the render wrote.
    pub output: String,
    pub width: u32,
    pub height: u32,
    #[serde(default)]
    pub mode: String,
    pub subscreens: Vec<SubscreenRecord>,
}

impl RenderRecords {
    pub fn read(path: &Path) -> Result<RenderRecords, LabError> {
        let bad = |reason: String| LabError::Stats {
            path: path.to_path_buf(),
            reason,
        };
        let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
        let records: RenderRecords = serde_json::from_slice(&bytes).map_err(|e| {
            bad(format!(
                "not the --stats file of a render with per-subscreen records: {e}"
            ))
        })?;
        if records.subscreens.is_empty() {
            return Err(bad("it holds no subscreen records".into()));
        }
        // As a render's image is: one pixel to MAX_IMAGE_SIDE a side.
        let sides = 1..=renderer::MAX_IMAGE_SIDE;
        if !sides.contains(&records.width) || !sides.contains(&records.height) {
            return Err(bad(format!(
                "its image is {}x{}: no render has that size",
                records.width, records.height
            )));
        }
        Ok(records)
    }

    /// Render node ids (thread indices in one process), ascending: the timeline's rows.
    pub fn nodes(&self) -> Vec<u32> {
        let mut nodes: Vec<u32> = self.subscreens.iter().map(|r| r.node).collect();
        nodes.sort_unstable();
        nodes.dedup();
        nodes
    }
}

/// The files `plot` wrote.
#[derive(Debug)]
pub struct Plots {
    pub timeline: PathBuf,
    pub tinted: PathBuf,
}

/// Draws the timeline and the tinted image of the render whose stats are at `stats`, into
/// `out_dir` (the stats file's folder when `None`), named after the stats file.
pub fn plot(stats: &Path, out_dir: Option<&Path>) -> Result<Plots, LabError> {
    let records = RenderRecords::read(stats)?;
    let dir = match out_dir {
        Some(d) => d.to_path_buf(),
        None => match stats.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        },
    };
    // `-o` names a folder; a file there said only "File exists (os error 17)".
    if dir.exists() && !dir.is_dir() {
        return Err(LabError::Settings(format!(
            "{}: not a folder (plot -o names the folder its PNG files go to)",
            dir.display()
        )));
    }
    std::fs::create_dir_all(&dir).map_err(|source| LabError::Folder {
        path: dir.clone(),
        source,
    })?;
    let stem = stats
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    let stem = stem.strip_suffix(".json").unwrap_or(&stem);
    let plots = Plots {
        timeline: dir.join(format!("{stem}.timeline.png")),
        tinted: dir.join(format!("{stem}.nodes.png")),
    };
    // The image is named as the render saw it: relative to where it ran, or absolute. Where
    // that name finds nothing from here, a relative one is looked for beside the stats file
    // (a render run in its folder writes both there; plotted from the folder above, the name
    // alone found nothing). Read before anything is drawn, so that a missing image leaves no
    // half of the pictures behind.
    let recorded = Path::new(&records.output);
    let beside = match stats.parent() {
        Some(d) if recorded.is_relative() && !recorded.exists() => d.join(recorded),
        _ => recorded.to_path_buf(),
    };
    let image = scene_io::read_image(&beside).map_err(|e| match e {
        scene_io::ImageError::Io { source, .. } if beside != recorded => scene_io::ImageError::Io {
            path: format!(
                "{} (the image {} names, looked for here and beside it as {})",
                records.output,
                stats.display(),
                beside.display()
            )
            .into(),
            source,
        },
        other => other,
    })?;
    timeline_png(&plots.timeline, &records)?;
    tinted_png(&plots.tinted, &records, &image)?;
    Ok(plots)
}

/// A node's colour, the same in both pictures.
fn node_colour(nodes: &[u32], node: u32) -> RGBColor {
    let i = nodes.binary_search(&node).unwrap_or(0);
    let c = Palette99::pick(i).to_rgba();
    RGBColor(c.0, c.1, c.2)
}

/// The Gantt chart: one row per node, a bar per subscreen, darker the more it fetched.
pub fn timeline_png(path: &Path, records: &RenderRecords) -> Result<(), LabError> {
    let nodes = records.nodes();
    let rows = nodes.len();
    let (w, h) = (1400u32, (160 + 28 * rows as u32).clamp(400, 2400));
    let end = records
        .subscreens
        .iter()
        .map(|r| r.end_s)
        .fold(0.0f64, f64::max)
        .max(1e-6);
    let most_fetched = records
        .subscreens
        .iter()
        .map(|r| r.fetched_bytes)
        .max()
        .unwrap_or(0);
    let labels = ensure_font();
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(LabError::draw)?;
        let mut builder = ChartBuilder::on(&root);
        builder
            .margin(20)
            .x_label_area_size(if labels { 50 } else { 10 })
            .y_label_area_size(if labels { 90 } else { 10 });
        if labels {
            let fetched = if most_fetched > 0 {
                format!(
                    "; darker: more fetched (most {:.1} KiB)",
                    most_fetched as f64 / 1024.0
                )
            } else {
                String::new()
            };
            builder.caption(
                format!(
                    "{} subscreens on {rows} {}{fetched}",
                    records.subscreens.len(),
                    if records.mode == "in-process" {
                        "threads"
                    } else {
                        "render nodes"
                    }
                ),
                ("sans-serif", 24),
            );
        }
        let mut chart = builder
            .build_cartesian_2d(0.0..end * 1.02, -0.5..rows as f64 - 0.5)
            .map_err(LabError::draw)?;
        let mut mesh = chart.configure_mesh();
        let row_name = |y: &f64| {
            let i = y.round();
            if (y - i).abs() < 1e-6 && i >= 0.0 {
                nodes
                    .get(i as usize)
                    .map(|n| n.to_string())
                    .unwrap_or_default()
            } else {
                String::new()
            }
        };
        if labels {
            mesh.x_desc("seconds since rendering began")
                .y_desc(if records.mode == "in-process" {
                    "thread"
                } else {
                    "render node"
                })
                .y_labels(rows.min(40))
                .y_label_formatter(&row_name)
                .disable_y_mesh();
        } else {
            mesh.disable_x_axis().disable_y_axis();
        }
        mesh.draw().map_err(LabError::draw)?;
        let bars = records.subscreens.iter().map(|r| {
            let row = nodes.binary_search(&r.node).unwrap_or(0) as f64;
            let base = node_colour(&nodes, r.node);
            // The share of the most any subscreen fetched darkens the bar up to 70%.
            let share = if most_fetched > 0 {
                r.fetched_bytes as f64 / most_fetched as f64
            } else {
                0.0
            };
            let shade = |c: u8| (c as f64 * (1.0 - 0.7 * share)) as u8;
            let colour = RGBColor(shade(base.0), shade(base.1), shade(base.2));
            Rectangle::new(
                [(r.start_s, row - 0.4), (r.end_s.max(r.start_s), row + 0.4)],
                colour.filled(),
            )
        });
        chart.draw_series(bars).map_err(LabError::draw)?;
        // Outlines keep back-to-back subscreens of one node apart.
        let outlines = records.subscreens.iter().map(|r| {
            let row = nodes.binary_search(&r.node).unwrap_or(0) as f64;
            Rectangle::new(
                [(r.start_s, row - 0.4), (r.end_s.max(r.start_s), row + 0.4)],
                BLACK.stroke_width(1),
            )
        });
        chart.draw_series(outlines).map_err(LabError::draw)?;
        root.present().map_err(LabError::draw)?;
    }
    write_png(path, w, h, &buf)
}

/// The image with each subscreen washed in its node's colour and outlined, enlarged (by whole
/// pixels) to at least 512 pixels across so that small renders can be seen.
pub fn tinted_png(
    path: &Path,
    records: &RenderRecords,
    image: &renderer::Image,
) -> Result<(), LabError> {
    if (image.width, image.height) != (records.width, records.height) {
        return Err(LabError::Stats {
            path: PathBuf::from(&records.output),
            reason: format!(
                "the image is {}x{}, the stats say {}x{}",
                image.width, image.height, records.width, records.height
            ),
        });
    }
    let nodes = records.nodes();
    let (iw, ih) = (image.width as usize, image.height as usize);
    let mut rgb: Vec<[u8; 3]> = image
        .pixels
        .iter()
        .map(|p| p.map(scene_io::image_io::to_srgb8))
        .collect();
    for r in &records.subscreens {
        let c = node_colour(&nodes, r.node);
        let c = [c.0, c.1, c.2];
        let (x1, y1) = (
            r.x.saturating_add(r.width).min(image.width) as usize,
            r.y.saturating_add(r.height).min(image.height) as usize,
        );
        for y in r.y as usize..y1 {
            for x in r.x as usize..x1 {
                let edge = x == r.x as usize || y == r.y as usize || x + 1 == x1 || y + 1 == y1;
                let p = &mut rgb[y * iw + x];
                let keep = if edge { 0.0 } else { 0.55 };
                for k in 0..3 {
                    p[k] = (p[k] as f32 * keep + c[k] as f32 * (1.0 - keep)).round() as u8;
                }
            }
        }
    }
    let scale = 512usize.div_ceil(iw.max(ih)).max(1);
    let (w, h) = (iw * scale, ih * scale);
    let mut out = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            out.extend_from_slice(&rgb[(y / scale) * iw + x / scale]);
        }
    }
    write_png(path, w as u32, h as u32, &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(node: u32, x: u32, start_s: f64, end_s: f64, fetched_bytes: u64) -> SubscreenRecord {
        SubscreenRecord {
            node,
            x,
            y: 0,
            width: 8,
            height: 16,
            start_s,
            end_s,
            fetched_bytes,
            ..Default::default()
        }
    }

    fn records() -> RenderRecords {
        RenderRecords {
            output: String::new(),
            width: 16,
            height: 16,
            mode: "cluster".into(),
            subscreens: vec![record(3, 0, 0.0, 0.5, 0), record(5, 8, 0.1, 0.9, 4096)],
        }
    }

    /// Pixels that are neither white nor one of the node colours' shades: anti-aliased text.
    fn grey_pixels(png: &Path) -> usize {
        let img = image::open(png).unwrap().to_rgb8();
        img.pixels()
            .filter(|p| {
                let [r, g, b] = p.0;
                let grey = r.abs_diff(g) < 8 && g.abs_diff(b) < 8;
                grey && r > 40 && r < 190
            })
            .count()
    }

    /// A stats file whose image has no pixels (or more than a render can have) is refused
    /// when read: plotting a 0x0 image divided by zero.
    #[test]
    fn stats_of_an_image_no_render_has_are_refused() {
        let dir = std::env::temp_dir().join(format!("magg-records-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("zero.json");
        for (w, h) in [(0, 0), (16, 0), (40_000, 16)] {
            let json = serde_json::json!({
                "output": "z.pfm",
                "width": w,
                "height": h,
                "subscreens": [record(3, 0, 0.0, 0.5, 0)],
            });
            std::fs::write(&path, json.to_string()).unwrap();
            let e = RenderRecords::read(&path).unwrap_err().to_string();
            assert!(e.contains(&format!("its image is {w}x{h}")), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_timeline_has_labels_from_the_built_in_font() {
        // No font file is consulted: the embedded bytes register on their own.
        assert!(ensure_font(), "the built-in font registers");
        let dir = std::env::temp_dir().join(format!("magg-timeline-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("t.png");
        timeline_png(&path, &records()).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        // Node 3 fetched nothing: its bar is its plain colour. Node 5 fetched the most: its
        // bar is the darkest shade of its colour.
        let c3 = node_colour(&[3, 5], 3);
        let c5 = node_colour(&[3, 5], 5);
        let dark = |c: u8| (c as f64 * 0.3) as u8;
        assert!(img.pixels().any(|p| p.0 == [c3.0, c3.1, c3.2]));
        assert!(
            img.pixels()
                .any(|p| p.0 == [dark(c5.0), dark(c5.1), dark(c5.2)])
        );
        // Text was drawn: anti-aliased glyph edges, greys darker than the grid lines.
        assert!(grey_pixels(&path) > 200, "labels drawn");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_tinted_image_marks_every_subscreen_in_its_node_colour() {
        let dir = std::env::temp_dir().join(format!("magg-tinted-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("n.png");
        let image = renderer::Image::new(16, 16);
        tinted_png(&path, &records(), &image).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.width(), 16 * 32, "small images are enlarged");
        let c3 = node_colour(&[3, 5], 3);
        let c5 = node_colour(&[3, 5], 5);
        // Outline pixels carry the node colour exactly; the left half is node 3's.
        assert_eq!(img.get_pixel(0, 0).0, [c3.0, c3.1, c3.2]);
        assert_eq!(img.get_pixel(16 * 32 - 1, 0).0, [c5.0, c5.1, c5.2]);
        let wrong = RenderRecords {
            width: 17,
            ..records()
        };
        assert!(tinted_png(&path, &wrong, &image).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
