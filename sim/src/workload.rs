//! What rendering an image costs, piece by piece: the simulator's input.
//!
//! A render's `--stats` file records, per subscreen, the thread CPU time it took, its pixels
//! and the chunks and texture tiles its rays touched ([`Workload::from_stats_json`]). That
//! is enough to replay the render on another machine, but only in the same subscreens. To
//! ask what another division would do, [`Workload::divided`] cuts the image as the host
//! would (`host::distributed::subscreens`) and carries the recorded costs over, under two
//! stated assumptions:
//!
//! * **cost is spread evenly over a recorded subscreen's pixels**: a new subscreen pays, for
//!   each recorded one it overlaps, that one's CPU time times the share of its area overlapped;
//! * **a recorded subscreen's items are touched by any part of it**: every row of a new
//!   subscreen needs every item of every recorded subscreen it overlaps on that row.
//!
//! Both hold better the finer the recording, so record with at least as many subscreens as
//! you simulate (a coarser division is then a union of recorded ones and loses nothing).
//! A new subscreen keeps its rows' structure as [`Band`]s: runs of rows that overlap the same
//! recorded subscreens, rendered one after the other, so a small cache can lose a band's
//! items to the next band of the same subscreen, as it does in a real render.

use std::collections::BTreeSet;

use protocol::Rect;
use renderer::MAX_IMAGE_SIDE;
use serde::{Deserialize, Serialize};

/// Rows of one subscreen that need the same items: rendered in order, each row costing
/// `cpu_s / rows`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Band {
    pub rows: u32,
    /// Thread CPU seconds for all of the band's rows.
    pub cpu_s: f64,
    /// Chunk ids its rays touch, ascending.
    pub chunks: Vec<u32>,
    /// Texture tile ids its rays touch, ascending.
    pub tiles: Vec<u32>,
}

/// One piece of work the host hands out.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Subscreen {
    pub rect: Rect,
    /// Top to bottom; their rows add up to `rect.height`.
    pub bands: Vec<Band>,
}

impl Subscreen {
    /// A subscreen whose every row needs the same items.
    pub fn single(rect: Rect, cpu_s: f64, chunks: Vec<u32>, tiles: Vec<u32>) -> Subscreen {
        Subscreen {
            rect,
            bands: vec![Band {
                rows: rect.height,
                cpu_s,
                chunks,
                tiles,
            }],
        }
    }

    pub fn cpu_s(&self) -> f64 {
        self.bands.iter().map(|b| b.cpu_s).sum()
    }

    /// The band row `row` (relative to the top) belongs to, and the row's place in it.
    pub fn band_of(&self, row: u32) -> Option<(usize, u32)> {
        let mut top = 0;
        for (i, b) in self.bands.iter().enumerate() {
            if row < top + b.rows {
                return Some((i, row - top));
            }
            top += b.rows;
        }
        None
    }

    /// Cuts off the rows from `row` on (relative to the top) as a subscreen of their own, as
    /// adaptive redivision does; a band cut in two splits its cost by rows.
    pub fn split_off(&mut self, row: u32) -> Option<Subscreen> {
        if row == 0 || row >= self.rect.height {
            return None;
        }
        let (at, within) = self.band_of(row)?;
        let mut tail: Vec<Band> = self.bands.split_off(at);
        if within > 0 {
            let whole = &mut tail[0];
            let head_cost = whole.cpu_s * within as f64 / whole.rows as f64;
            self.bands.push(Band {
                rows: within,
                cpu_s: head_cost,
                ..whole.clone()
            });
            whole.rows -= within;
            whole.cpu_s -= head_cost;
        }
        let r = self.rect;
        self.rect.height = row;
        Some(Subscreen {
            rect: Rect {
                x: r.x,
                y: r.y + row,
                width: r.width,
                height: r.height - row,
            },
            bands: tail,
        })
    }
}

/// A render's costs: the image, its subscreens in the order the host hands them out, and the
/// size of every item of the scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Workload {
    pub width: u32,
    pub height: u32,
    pub subscreens: Vec<Subscreen>,
    /// Bytes of each chunk, by id.
    pub chunk_bytes: Vec<u64>,
    /// Bytes of each texture tile, by id.
    pub tile_bytes: Vec<u64>,
}

/// Why a workload cannot be read or used.
#[derive(Debug, thiserror::Error)]
pub enum WorkloadError {
    #[error("the stats file is not JSON of the expected shape: {0}")]
    Json(#[source] serde_json::Error),
    #[error(
        "the stats file has no per-subscreen records (a list under \"subscreens\" with chunk_bytes and tile_bytes beside it); it was written by a render that did not record them"
    )]
    NoRecords,
    #[error("the stats file has no subscreen records: nothing to simulate")]
    Empty,
    #[error("subscreen {index}: {reason}")]
    Subscreen { index: usize, reason: String },
    #[error("the image is {width}x{height}; it needs at least one pixel")]
    EmptyImage { width: u32, height: u32 },
    #[error("the image is {width}x{height}; a render is at most {MAX_IMAGE_SIDE} pixels a side")]
    TooLarge { width: u32, height: u32 },
}

/// One subscreen as a render's stats record it (the fields the simulator reads; the others
/// are there to compare with).
#[derive(Clone, Debug, Deserialize)]
struct Record {
    x: u32,
    y: u32,
    width: u32,
    height: u32,
    cpu_s: f64,
    #[serde(default)]
    chunks: Vec<u32>,
    #[serde(default)]
    tiles: Vec<u32>,
}

#[derive(Deserialize)]
struct StatsFile {
    width: Option<u32>,
    height: Option<u32>,
    subscreens: Vec<Record>,
    chunk_bytes: Vec<u64>,
    tile_bytes: Vec<u64>,
}

impl Workload {
    /// Reads the per-subscreen records of a render's `--stats` JSON. The image size is the
    /// file's `width` and `height` when it has them, else the records' bounding box. The
    /// subscreens are put in the host's plan order (top to bottom, left to right), whatever
    /// order the file lists them in: a render without adaptive redivision or lost nodes
    /// records each pixel once, and that is the render this replays.
    pub fn from_stats_json(text: &str) -> Result<Workload, WorkloadError> {
        let value: serde_json::Value = serde_json::from_str(text).map_err(WorkloadError::Json)?;
        let has_records = value.get("subscreens").is_some_and(|s| s.is_array())
            && value.get("chunk_bytes").is_some()
            && value.get("tile_bytes").is_some();
        if !has_records {
            return Err(WorkloadError::NoRecords);
        }
        let file: StatsFile = serde_json::from_value(value).map_err(WorkloadError::Json)?;
        if file.subscreens.is_empty() {
            return Err(WorkloadError::Empty);
        }
        let width = file.width.unwrap_or_else(|| {
            file.subscreens
                .iter()
                .map(|r| r.x.saturating_add(r.width))
                .max()
                .unwrap_or(0)
        });
        let height = file.height.unwrap_or_else(|| {
            file.subscreens
                .iter()
                .map(|r| r.y.saturating_add(r.height))
                .max()
                .unwrap_or(0)
        });
        // The records come in the order they finished; the host hands subscreens out in
        // its plan's order, which cuts the image row by row, left to right.
        let mut records = file.subscreens;
        records.sort_by_key(|r| (r.y, r.x));
        let subscreens = records
            .into_iter()
            .map(|r| {
                let mut chunks = r.chunks;
                chunks.sort_unstable();
                chunks.dedup();
                let mut tiles = r.tiles;
                tiles.sort_unstable();
                tiles.dedup();
                let rect = Rect {
                    x: r.x,
                    y: r.y,
                    width: r.width,
                    height: r.height,
                };
                Subscreen::single(rect, r.cpu_s, chunks, tiles)
            })
            .collect();
        let w = Workload {
            width,
            height,
            subscreens,
            chunk_bytes: file.chunk_bytes,
            tile_bytes: file.tile_bytes,
        };
        w.check()?;
        Ok(w)
    }

    /// Bytes of every chunk and tile together: what a cache percentage is a share of.
    pub fn scene_bytes(&self) -> u64 {
        self.chunk_bytes.iter().chain(&self.tile_bytes).sum()
    }

    /// The largest chunk or tile: a demand cache smaller than it cannot work.
    pub fn largest_item(&self) -> u64 {
        self.chunk_bytes
            .iter()
            .chain(&self.tile_bytes)
            .copied()
            .max()
            .unwrap_or(0)
    }

    /// CPU seconds of the whole image on one thread.
    pub fn cpu_s(&self) -> f64 {
        self.subscreens.iter().map(Subscreen::cpu_s).sum()
    }

    /// Checks what the simulator relies on: subscreens inside the image, bands that add up
    /// to their subscreen, finite costs, item ids the scene has.
    pub fn check(&self) -> Result<(), WorkloadError> {
        if self.width == 0 || self.height == 0 {
            return Err(WorkloadError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        // What no render can have made: a stats file of a billion rows is not simulated
        // with a list per row.
        if self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE {
            return Err(WorkloadError::TooLarge {
                width: self.width,
                height: self.height,
            });
        }
        if self.subscreens.is_empty() {
            return Err(WorkloadError::Empty);
        }
        for (index, s) in self.subscreens.iter().enumerate() {
            let bad = |reason: String| Err(WorkloadError::Subscreen { index, reason });
            let r = s.rect;
            if r.width == 0 || r.height == 0 {
                return bad(format!("{}x{} has no pixels", r.width, r.height));
            }
            if r.x as u64 + r.width as u64 > self.width as u64
                || r.y as u64 + r.height as u64 > self.height as u64
            {
                return bad(format!(
                    "{}x{} at ({}, {}) reaches past the {}x{} image",
                    r.width, r.height, r.x, r.y, self.width, self.height
                ));
            }
            let rows: u64 = s.bands.iter().map(|b| b.rows as u64).sum();
            if rows != r.height as u64 || s.bands.iter().any(|b| b.rows == 0) {
                return bad(format!(
                    "its bands cover {rows} rows, not its {} (or one is empty)",
                    r.height
                ));
            }
            for b in &s.bands {
                if !(b.cpu_s.is_finite() && b.cpu_s >= 0.0) {
                    return bad(format!("CPU time {} is not a time", b.cpu_s));
                }
                if let Some(c) = b
                    .chunks
                    .iter()
                    .find(|&&c| c as usize >= self.chunk_bytes.len())
                {
                    return bad(format!(
                        "touches chunk {c}, but the scene has {} chunks",
                        self.chunk_bytes.len()
                    ));
                }
                if let Some(t) = b
                    .tiles
                    .iter()
                    .find(|&&t| t as usize >= self.tile_bytes.len())
                {
                    return bad(format!(
                        "touches tile {t}, but the scene has {} tiles",
                        self.tile_bytes.len()
                    ));
                }
            }
        }
        Ok(())
    }

    /// The same image cut into about `n` subscreens as the host cuts it, the costs carried
    /// over as the module docs say. Fails only on a workload that fails [`Workload::check`].
    pub fn divided(&self, n: u32) -> Result<Workload, WorkloadError> {
        self.check()?;
        // Every band of every subscreen is a cell of known cost and items.
        struct Cell<'a> {
            x: u32,
            width: u32,
            cost_per_pixel: f64,
            band: &'a Band,
        }
        let mut cells = Vec::new();
        // For each image row, the cells covering it, ordered by x.
        let mut rows: Vec<Vec<usize>> = vec![Vec::new(); self.height as usize];
        for s in &self.subscreens {
            let mut top = s.rect.y;
            for b in &s.bands {
                let id = cells.len();
                cells.push(Cell {
                    x: s.rect.x,
                    width: s.rect.width,
                    cost_per_pixel: b.cpu_s / (b.rows as f64 * s.rect.width as f64),
                    band: b,
                });
                for y in top..top + b.rows {
                    rows[y as usize].push(id);
                }
                top += b.rows;
            }
        }
        for row in &mut rows {
            row.sort_by_key(|&c| (cells[c].x, c));
        }
        let rects = host::distributed::subscreens(self.width, self.height, n);
        let subscreens = rects
            .into_iter()
            .map(|rect| {
                let (x0, x1) = (rect.x, rect.x + rect.width);
                let overlapping = |y: u32| -> Vec<usize> {
                    rows[y as usize]
                        .iter()
                        .copied()
                        .filter(|&c| cells[c].x < x1 && cells[c].x + cells[c].width > x0)
                        .collect()
                };
                let mut bands: Vec<Band> = Vec::new();
                let mut current: Option<(Vec<usize>, Band)> = None;
                for y in rect.y..rect.y + rect.height {
                    let over = overlapping(y);
                    let cost: f64 = over
                        .iter()
                        .map(|&c| {
                            let cell = &cells[c];
                            let w = x1.min(cell.x + cell.width) - x0.max(cell.x);
                            cell.cost_per_pixel * w as f64
                        })
                        .sum();
                    match &mut current {
                        Some((same, band)) if *same == over => {
                            band.rows += 1;
                            band.cpu_s += cost;
                        }
                        _ => {
                            if let Some((_, done)) = current.take() {
                                bands.push(done);
                            }
                            let chunks: BTreeSet<u32> = over
                                .iter()
                                .flat_map(|&c| cells[c].band.chunks.iter().copied())
                                .collect();
                            let tiles: BTreeSet<u32> = over
                                .iter()
                                .flat_map(|&c| cells[c].band.tiles.iter().copied())
                                .collect();
                            let band = Band {
                                rows: 1,
                                cpu_s: cost,
                                chunks: chunks.into_iter().collect(),
                                tiles: tiles.into_iter().collect(),
                            };
                            current = Some((over, band));
                        }
                    }
                }
                if let Some((_, done)) = current {
                    bands.push(done);
                }
                Subscreen { rect, bands }
            })
            .collect();
        Ok(Workload {
            width: self.width,
            height: self.height,
            subscreens,
            chunk_bytes: self.chunk_bytes.clone(),
            tile_bytes: self.tile_bytes.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rect(x: u32, y: u32, width: u32, height: u32) -> Rect {
        Rect {
            x,
            y,
            width,
            height,
        }
    }

    const STATS: &str = r#"{
        "width": 4, "height": 2, "spp": 1,
        "subscreens": [
            {"node": 5, "x": 0, "y": 0, "width": 2, "height": 2, "start_s": 0.0, "end_s": 1.0,
             "cpu_s": 2.0, "pixels": 4, "samples": 4, "rays": 9, "chunks": [3, 1, 1], "tiles": [],
             "fetched_bytes": 30, "fetches": 2, "fetched_via": "dma"},
            {"node": 6, "x": 2, "y": 0, "width": 2, "height": 2, "start_s": 0.0, "end_s": 1.0,
             "cpu_s": 4.0, "pixels": 4, "samples": 4, "rays": 9, "chunks": [0], "tiles": [1],
             "fetched_bytes": 30, "fetches": 2, "fetched_via": "mesh"}
        ],
        "chunk_bytes": [10, 20, 30, 40], "tile_bytes": [5, 6]
    }"#;

    #[test]
    fn reads_the_records_of_a_stats_file() {
        let w = Workload::from_stats_json(STATS).unwrap();
        assert_eq!((w.width, w.height), (4, 2));
        assert_eq!(w.subscreens.len(), 2);
        assert_eq!(
            w.subscreens[0].bands[0].chunks,
            vec![1, 3],
            "sorted, once each"
        );
        assert_eq!(w.subscreens[1].bands[0].tiles, vec![1]);
        // Listed in the order they finished, read in the order they were planned.
        let swapped = STATS.replace(r#""x": 0, "y": 0"#, r#""x": 9, "y": 9"#);
        let swapped = swapped.replacen(r#""x": 2, "y": 0"#, r#""x": 0, "y": 0"#, 1);
        let swapped = swapped.replace(r#""x": 9, "y": 9"#, r#""x": 2, "y": 0"#);
        let w2 = Workload::from_stats_json(&swapped).unwrap();
        assert_eq!(w2.subscreens[0].rect, rect(0, 0, 2, 2));
        assert_eq!(w2.subscreens[0].bands[0].chunks, vec![0]);
        assert_eq!(w.scene_bytes(), 111);
        assert_eq!(w.largest_item(), 40);
        assert_eq!(w.cpu_s(), 6.0);
    }

    #[test]
    fn bad_stats_files_say_what_is_wrong() {
        let cases = [
            ("not json", "not JSON"),
            (
                r#"{"subscreens": 3, "chunk_bytes": [], "tile_bytes": []}"#,
                "no per-subscreen",
            ),
            (r#"{"width": 4}"#, "no per-subscreen"),
            (
                r#"{"subscreens": [], "chunk_bytes": [], "tile_bytes": []}"#,
                "nothing to simulate",
            ),
            (
                r#"{"width": 2, "height": 2, "subscreens": [{"x": 1, "y": 0, "width": 2, "height": 1, "cpu_s": 1}], "chunk_bytes": [], "tile_bytes": []}"#,
                "reaches past",
            ),
            (
                r#"{"subscreens": [{"x": 0, "y": 0, "width": 2, "height": 1, "cpu_s": 1, "chunks": [4]}], "chunk_bytes": [1], "tile_bytes": []}"#,
                "touches chunk 4",
            ),
            (
                r#"{"subscreens": [{"x": 0, "y": 0, "width": 2, "height": 1, "cpu_s": -1}], "chunk_bytes": [1], "tile_bytes": []}"#,
                "not a time",
            ),
            // Refused before the simulator makes a list per row (48 GB for this one).
            (
                r#"{"width": 2, "height": 2000000000, "subscreens": [{"x": 0, "y": 0, "width": 2, "height": 1, "cpu_s": 1}], "chunk_bytes": [], "tile_bytes": []}"#,
                "at most 32768 pixels a side",
            ),
            // Records reaching past u32 without an image size: refused, not wrapped.
            (
                r#"{"subscreens": [{"x": 4294967295, "y": 0, "width": 2, "height": 1, "cpu_s": 1}], "chunk_bytes": [], "tile_bytes": []}"#,
                "at most 32768 pixels a side",
            ),
        ];
        for (text, needle) in cases {
            let e = Workload::from_stats_json(text).unwrap_err().to_string();
            assert!(e.contains(needle), "{e:?} should mention {needle:?}");
        }
    }

    #[test]
    fn dividing_keeps_the_total_cost_and_the_items_of_each_region() {
        let w = Workload::from_stats_json(STATS).unwrap();
        // One subscreen over the whole image: both recorded ones, in one band.
        let one = w.divided(1).unwrap();
        assert_eq!(one.subscreens.len(), 1);
        assert_eq!(one.subscreens[0].rect, rect(0, 0, 4, 2));
        assert_eq!(one.subscreens[0].bands.len(), 1);
        assert_eq!(one.subscreens[0].bands[0].chunks, vec![0, 1, 3]);
        assert!((one.cpu_s() - 6.0).abs() < 1e-12);
        // Eight single pixels: each pays its recorded subscreen's cost per pixel.
        let eight = w.divided(8).unwrap();
        assert_eq!(eight.subscreens.len(), 8);
        assert!((eight.cpu_s() - 6.0).abs() < 1e-12);
        let right = eight
            .subscreens
            .iter()
            .find(|s| s.rect == rect(3, 1, 1, 1))
            .unwrap();
        assert_eq!(right.bands[0].cpu_s, 1.0);
        assert_eq!(right.bands[0].chunks, vec![0]);
        assert_eq!(right.bands[0].tiles, vec![1]);
        eight.check().unwrap();
    }

    #[test]
    fn rows_over_different_recorded_subscreens_become_bands() {
        let w = Workload {
            width: 2,
            height: 4,
            subscreens: vec![
                Subscreen::single(rect(0, 0, 2, 1), 1.0, vec![0], vec![]),
                Subscreen::single(rect(0, 1, 2, 3), 3.0, vec![1], vec![]),
            ],
            chunk_bytes: vec![1, 1],
            tile_bytes: vec![],
        };
        let one = w.divided(1).unwrap();
        let bands = &one.subscreens[0].bands;
        assert_eq!(bands.len(), 2);
        assert_eq!((bands[0].rows, bands[0].chunks.clone()), (1, vec![0]));
        assert_eq!((bands[1].rows, bands[1].cpu_s), (3, 3.0));
        // A workload built by hand that reaches past its image is refused, not indexed.
        let mut bad = w;
        bad.height = 3;
        assert!(
            bad.divided(2)
                .unwrap_err()
                .to_string()
                .contains("reaches past")
        );
    }

    #[test]
    fn splitting_a_subscreen_splits_its_bands_and_cost_by_rows() {
        let mut s = Subscreen {
            rect: rect(0, 0, 2, 6),
            bands: vec![
                Band {
                    rows: 2,
                    cpu_s: 2.0,
                    chunks: vec![0],
                    tiles: vec![],
                },
                Band {
                    rows: 4,
                    cpu_s: 8.0,
                    chunks: vec![1],
                    tiles: vec![],
                },
            ],
        };
        let tail = s.split_off(3).unwrap();
        assert_eq!(s.rect, rect(0, 0, 2, 3));
        assert_eq!(tail.rect, rect(0, 3, 2, 3));
        assert_eq!(s.cpu_s(), 4.0);
        assert_eq!(tail.cpu_s(), 6.0);
        assert_eq!(s.bands[1].chunks, vec![1]);
        assert_eq!(s.band_of(2), Some((1, 0)));
        assert!(s.split_off(0).is_none() && s.split_off(3).is_none());
    }
}
