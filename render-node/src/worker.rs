//! The rendering threads of a render node: ask the host for a subscreen, render it scan line
//! by scan line, send each line to the fork node, ask again. They run apart from the
//! node's networking, which keeps forwarding other nodes' packets meanwhile.

use std::{
    collections::HashMap,
    sync::{
        Arc, Mutex,
        atomic::{AtomicU32, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::{Fabric, Route};
use protocol::{JobSpec, Message, NodeId, Rect, SubscreenWork};
use renderer::{
    SceneHeader, render::render_pixel, source::Touched, trace::TraceStats, trace::Tracer,
};

use crate::cache::{DemandCache, Reader};

/// Why a rendering thread stopped before the host ran out of work.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("asking the host for work: {0}")]
    Ask(#[source] fabric::RequestError),
    #[error("unexpected answer to a subscreen request: {0}")]
    Answer(String),
    #[error("rendering subscreen {id}: {source}")]
    Render {
        id: u32,
        #[source]
        source: RenderError,
    },
}

/// What stops one subscreen: data that could not be had, or pixels that could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Data(#[from] renderer::DataError),
    #[error("sending pixels: {0}")]
    Send(#[from] fabric::SendError),
}

/// A subscreen being rendered: rows `next_row..end_row` (relative to `rect`) are still to do.
/// The host may ask to have the tail back; `end_row` then moves up.
pub struct Active {
    pub rect: Rect,
    pub next_row: AtomicU32,
    pub end_row: AtomicU32,
}

impl Active {
    /// Gives back the unbegun second half of the remaining rows; returns the first row given
    /// back (the end, when there is nothing to give).
    pub fn give_back(&self) -> u32 {
        let next = self.next_row.load(Ordering::SeqCst);
        let end = self.end_row.load(Ordering::SeqCst);
        if end <= next + 1 {
            return end;
        }
        let mid = next + (end - next).div_ceil(2);
        match self
            .end_row
            .compare_exchange(end, mid, Ordering::SeqCst, Ordering::SeqCst)
        {
            Ok(_) => mid,
            Err(now) => now,
        }
    }
}

#[derive(Default)]
pub struct WorkStats {
    pub subscreens: AtomicU32,
    /// Most private resident memory seen after a subscreen.
    pub peak_private: AtomicU64,
    pub rows: AtomicU64,
    pub pixels: AtomicU64,
    pub samples: AtomicU64,
    pub rays: AtomicU64,
    pub camera_rays: AtomicU64,
    pub secondary_rays: AtomicU64,
    pub shadow_rays: AtomicU64,
    pub bad_samples: AtomicU64,
    pub render_ns: AtomicU64,
    pub idle_ns: AtomicU64,
    /// What each subscreen cost, for the host's per-subscreen records (one push per
    /// subscreen, never per pixel).
    pub records: Mutex<Vec<SubscreenWork>>,
}

pub type ActiveMap = Arc<Mutex<HashMap<u32, Arc<Active>>>>;

pub struct Worker {
    pub fabric: Fabric,
    pub runtime: tokio::runtime::Handle,
    pub scene: Arc<SceneHeader>,
    pub job: Arc<JobSpec>,
    pub cache: Arc<DemandCache>,
    pub fork: NodeId,
    pub active: ActiveMap,
    pub stats: Arc<WorkStats>,
}

/// A request for work waits as long as the render lasts: an idle node is held until the end,
/// in case a lost node's work comes back. (A lost host is noticed on the control connection.)
const ASK_TIMEOUT: Duration = Duration::from_secs(7 * 24 * 3600);

impl Worker {
    /// Renders subscreens until the host has no more; returns an error message on failure.
    pub fn run(&self) -> Result<(), WorkerError> {
        let mut reader = self.cache.reader();
        let touched = Touched::new(self.scene.chunks.len(), self.scene.tile_count as usize);
        let mut finished = None;
        loop {
            let t0 = Instant::now();
            let f = self.fabric.clone();
            let reply = self
                .runtime
                .block_on(async move {
                    f.request(
                        0,
                        &Message::SubscreenRequest { finished },
                        Box::new([]),
                        Route::Mesh,
                        ASK_TIMEOUT,
                    )
                    .await
                })
                .map_err(WorkerError::Ask)?;
            self.stats
                .idle_ns
                .fetch_add(t0.elapsed().as_nanos() as u64, Ordering::Relaxed);
            let (id, rect) = match reply.message() {
                Ok(Message::Subscreen { id, rect }) => (id, rect),
                Ok(Message::NoMoreWork) => break,
                other => return Err(WorkerError::Answer(format!("{other:?}"))),
            };
            let t1 = Instant::now();
            let active = Arc::new(Active {
                rect,
                next_row: AtomicU32::new(0),
                end_row: AtomicU32::new(rect.height),
            });
            self.active
                .lock()
                .expect("active lock")
                .insert(id, active.clone());
            let cpu0 = fabric::clock::thread_cpu_time();
            // This subscreen's counts alone: its record, then the node's totals.
            let mut trace_stats = TraceStats::default();
            let result =
                self.render_subscreen(&mut reader, &touched, id, &active, &mut trace_stats);
            self.active.lock().expect("active lock").remove(&id);
            result.map_err(|source| WorkerError::Render { id, source })?;
            let record = record(id, rect, &trace_stats, &reader, &touched, cpu0);
            self.stats
                .records
                .lock()
                .expect("records lock")
                .push(record);
            self.stats
                .render_ns
                .fetch_add(t1.elapsed().as_nanos() as u64, Ordering::Relaxed);
            self.stats.subscreens.fetch_add(1, Ordering::Relaxed);
            self.stats
                .peak_private
                .fetch_max(fabric::private_rss_bytes(), Ordering::Relaxed);
            // The node's totals include this subscreen before it asks for the next one: the
            // host collects figures as soon as the last request has come in.
            self.add_totals(&trace_stats);
            finished = Some(id);
        }
        Ok(())
    }

    /// Adds one subscreen's rays and samples to the node's totals.
    fn add_totals(&self, t: &TraceStats) {
        for (counter, n) in [
            (&self.stats.rays, t.rays()),
            (&self.stats.samples, t.samples),
            (&self.stats.camera_rays, t.camera_rays),
            (&self.stats.secondary_rays, t.secondary_rays),
            (&self.stats.shadow_rays, t.shadow_rays),
            (&self.stats.bad_samples, t.bad_samples),
        ] {
            counter.fetch_add(n, Ordering::Relaxed);
        }
    }

    fn render_subscreen(
        &self,
        reader: &mut Reader,
        touched: &Touched,
        id: u32,
        active: &Active,
        trace_stats: &mut renderer::trace::TraceStats,
    ) -> Result<(), RenderError> {
        let rect = active.rect;
        let settings = &self.job.settings;
        let mut line: Vec<[f32; 3]> = Vec::with_capacity(rect.width as usize);
        loop {
            let row = active.next_row.fetch_add(1, Ordering::SeqCst);
            if row >= active.end_row.load(Ordering::SeqCst) {
                return Ok(());
            }
            let y = rect.y + row;
            line.clear();
            // Between scan lines this thread holds nothing of the cache: evicted data it
            // used may be freed.
            reader.refresh();
            let data = touched.watching(&*reader);
            let tracer = Tracer::new(&self.scene, &data);
            for x in rect.x..rect.x + rect.width {
                reader.tick();
                let px = render_pixel(&tracer, &self.job.camera, settings, x, y, trace_stats)?;
                line.push(px);
            }
            let t = tracer.stats();
            trace_stats.camera_rays += t.camera_rays;
            trace_stats.secondary_rays += t.secondary_rays;
            trace_stats.shadow_rays += t.shadow_rays;
            let words: Box<[u32]> = bytemuck::cast_slice::<[f32; 3], u32>(&line).into();
            let msg = Message::Pixels {
                subscreen: id,
                y,
                x: rect.x,
                width: rect.width,
            };
            // To the fork node serving this node now: another card's, once its own is lost.
            let fork = self
                .fabric
                .serving_fork(self.fabric.me())
                .unwrap_or(self.fork);
            self.fabric.send(fork, &msg, words, 0)?;
            self.stats.rows.fetch_add(1, Ordering::Relaxed);
            self.stats
                .pixels
                .fetch_add(rect.width as u64, Ordering::Relaxed);
        }
    }
}

/// What subscreen `id` cost this thread: its `counts`, the ids its rays touched,
/// what it fetched, and the thread's CPU time since `cpu0`.
fn record(
    id: u32,
    rect: Rect,
    counts: &TraceStats,
    reader: &Reader,
    touched: &Touched,
    cpu0: Duration,
) -> SubscreenWork {
    let pixels = counts.pixels;
    let (chunks, tiles) = touched.take();
    let (fetches, fetched_bytes) = reader.take_fetched();
    SubscreenWork {
        subscreen: id,
        // Rows are rendered in order from the top, so what was rendered is a prefix.
        rect: Rect {
            height: (pixels / rect.width.max(1) as u64) as u32,
            ..rect
        },
        cpu_s: fabric::clock::thread_cpu_time()
            .saturating_sub(cpu0)
            .as_secs_f64(),
        pixels,
        samples: counts.samples,
        rays: counts.rays(),
        chunks,
        tiles,
        fetched_bytes,
        fetches,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn give_back_halves_the_rest_and_never_the_row_in_hand() {
        let a = Active {
            rect: Rect {
                x: 0,
                y: 0,
                width: 4,
                height: 10,
            },
            next_row: AtomicU32::new(2),
            end_row: AtomicU32::new(10),
        };
        assert_eq!(a.give_back(), 6);
        assert_eq!(a.end_row.load(Ordering::SeqCst), 6);
        a.next_row.store(5, Ordering::SeqCst);
        assert_eq!(a.give_back(), 6, "one row left: nothing to give");
    }
}
