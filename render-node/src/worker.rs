//! The rendering threads of a render node: ask the host for a subscreen, render it scan line
//! by scan line, send the lines to the fork node (a few at a time, of one subscreen or
//! several), ask again. They run apart from the node's networking, which keeps forwarding
//! other nodes' packets meanwhile.

use std::{
    collections::HashMap,
    sync::{
        Arc, Mutex,
        atomic::{AtomicU32, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::{Fabric, Route};
use protocol::{AskVia, CoherentRays, JobSpec, Message, NodeId, Rect, SubscreenWork, Transfer};
use renderer::{
    SceneHeader,
    render::{CoherenceStats, coherent_rows, paths_in_flight, render_pixel, render_rect_coherent},
    source::Touched,
    trace::{TraceStats, Tracer},
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
    #[error("sending the pixels of finished subscreens: {0}")]
    Send(#[from] fabric::SendError),
}

/// What stops one subscreen: data that could not be had, or pixels that could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Data(#[from] renderer::DataError),
    #[error("sending pixels: {0}")]
    Send(#[from] fabric::SendError),
}

/// A subscreen being rendered: which of its rows (relative to `rect`) are still to do. The
/// host may ask to have the tail back. The next row to begin and the end are one word, so
/// that taking rows and giving the tail back never overlap, however they interleave.
pub struct Active {
    pub rect: Rect,
    /// `next | end << 32`: rows `next..end` are still to do.
    rows: AtomicU64,
}

impl Active {
    pub fn new(rect: Rect) -> Active {
        Active {
            rect,
            rows: AtomicU64::new((rect.height as u64) << 32),
        }
    }

    fn split(w: u64) -> (u32, u32) {
        (w as u32, (w >> 32) as u32)
    }

    /// Takes up to `most` (at least one) of the rows still to do, from the top.
    pub fn take(&self, most: u32) -> Option<std::ops::Range<u32>> {
        let mut w = self.rows.load(Ordering::SeqCst);
        loop {
            let (next, end) = Self::split(w);
            if next >= end {
                return None;
            }
            let to = end.min(next.saturating_add(most.max(1)));
            match self.rows.compare_exchange(
                w,
                to as u64 | (end as u64) << 32,
                Ordering::SeqCst,
                Ordering::SeqCst,
            ) {
                Ok(_) => return Some(next..to),
                Err(now) => w = now,
            }
        }
    }

    /// Gives back the unbegun second half of the remaining rows; returns the first row given
    /// back (the end, when there is nothing to give).
    pub fn give_back(&self) -> u32 {
        let mut w = self.rows.load(Ordering::SeqCst);
        loop {
            let (next, end) = Self::split(w);
            if end <= next + 1 {
                return end;
            }
            let mid = next + (end - next).div_ceil(2);
            match self.rows.compare_exchange(
                w,
                next as u64 | (mid as u64) << 32,
                Ordering::SeqCst,
                Ordering::SeqCst,
            ) {
                Ok(_) => return mid,
                Err(now) => w = now,
            }
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
    /// Coherent rays: paths put aside for data, and items fetched for them.
    pub paths_deferred: AtomicU64,
    pub deferred_fetches: AtomicU64,
    pub render_ns: AtomicU64,
    pub idle: IdleClock,
    /// What each subscreen cost, for the host's per-subscreen records (one push per
    /// subscreen, never per pixel).
    pub records: Mutex<Vec<SubscreenWork>>,
}

/// Time the rendering threads spent waiting for work, with the waits still going on: the
/// host asks for figures as soon as the last request has come in, and a node held without
/// work all render may read its answer only after it has sent them.
#[derive(Default)]
pub struct IdleClock {
    inner: Mutex<Waits>,
}

#[derive(Default)]
struct Waits {
    ended: Duration,
    open: Vec<Instant>,
}

impl IdleClock {
    /// A wait begins now; hand what this returns to [`IdleClock::end`].
    pub fn begin(&self) -> Instant {
        let now = Instant::now();
        self.inner.lock().expect("idle lock").open.push(now);
        now
    }

    pub fn end(&self, began: Instant) {
        let mut w = self.inner.lock().expect("idle lock");
        if let Some(i) = w.open.iter().position(|&t| t == began) {
            w.open.swap_remove(i);
        }
        w.ended += began.elapsed();
    }

    /// Waits ended, and those still open up to now.
    pub fn total(&self) -> Duration {
        let w = self.inner.lock().expect("idle lock");
        let now = Instant::now();
        w.ended + w.open.iter().map(|&t| now - t).sum::<Duration>()
    }

    #[cfg(test)]
    pub fn with_ended(ended: Duration) -> Self {
        IdleClock {
            inner: Mutex::new(Waits {
                ended,
                open: Vec::new(),
            }),
        }
    }
}

pub type ActiveMap = Arc<Mutex<HashMap<u32, Arc<Active>>>>;

/// The host's answer to a request for work.
enum Next {
    Subscreen(u32, Arc<Active>),
    /// Only to a request ahead: ask again when the current subscreen is done.
    NothingAhead,
    Done,
}

/// A request for work on its way.
type Asked = tokio::task::JoinHandle<Result<Next, WorkerError>>;

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

/// Memory a render node's rendering threads share for their paths in flight (coherent
/// rays): a quarter of what the node may hold beyond its cache's budget (8 MiB). The rest
/// is its runtime, buffers and code, and the holes that fetching and evicting chunks leave
/// in its heap (4.4 MiB free in a heap of 14.0 at cache 5% over TCP). Over TCP with a small
/// cache nearly every path waits at once, each with what its queries found; spheres at cache
/// 5% over TCP, one thread: 4 MiB of paths held the node at 14.3 to 14.7 MiB for a budget
/// of 6.5, 2 MiB at 12.8 MiB, fetching 15% more for 5% more time.
const PATHS_MEMORY: usize = 2 << 20;

/// A request for work waits as long as the render lasts: an idle node is held until the end,
/// in case a lost node's work comes back. (A lost host is noticed on the control connection.)
const ASK_TIMEOUT: Duration = Duration::from_secs(7 * 24 * 3600);

impl Worker {
    /// Renders subscreens until the host has no more; returns an error message on failure.
    pub fn run(&self) -> Result<(), WorkerError> {
        let mut reader = self.cache.reader();
        let touched = Touched::new(self.scene.chunks.len(), self.scene.tile_count as usize);
        let mut finished = None;
        let mut ahead: Option<Asked> = None;
        let mut unsent = Unsent::new();
        loop {
            let t0 = self.stats.idle.begin();
            // Rows held must not wait on an answer that may wait for them (the host answers
            // the last requests once every row is in); a request asked now is sent below.
            if ahead.as_ref().is_some_and(|asked| !asked.is_finished()) {
                self.send_rows(&mut unsent)?;
            }
            // The answer to the request sent ahead, unless there was none or it had nothing.
            let next = match ahead.take().map(|asked| self.answer(asked)).transpose()? {
                Some(Next::NothingAhead) | None => {
                    self.send_rows(&mut unsent)?;
                    self.answer(self.ask(finished.take(), false))?
                }
                Some(next) => next,
            };
            self.stats.idle.end(t0);
            let (id, active) = match next {
                Next::Subscreen(id, active) => (id, active),
                Next::Done => {
                    self.send_rows(&mut unsent)?;
                    break;
                }
                Next::NothingAhead => {
                    return Err(WorkerError::Answer(
                        "nothing ahead, to a request that was not ahead".into(),
                    ));
                }
            };
            if self.job.ask_ahead {
                ahead = Some(self.ask(finished.take(), true));
            }
            let rect = active.rect;
            let t1 = Instant::now();
            let cpu0 = fabric::clock::thread_cpu_time();
            // This subscreen's counts alone: its record, then the node's totals.
            let mut trace_stats = TraceStats::default();
            let result = self.render_subscreen(
                &mut reader,
                &touched,
                id,
                &active,
                &mut unsent,
                &mut trace_stats,
            );
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

    /// Asks the host for a subscreen, on the node's runtime: the answer comes (through the
    /// mesh or over the node's own connection to the host, [`JobSpec::ask_via`]) while this
    /// thread goes on. A subscreen given is registered as in progress as
    /// soon as it arrives, so that the host can have its unbegun rows back before this
    /// thread begins it.
    fn ask(&self, finished: Option<u32>, ahead: bool) -> Asked {
        let f = self.fabric.clone();
        let active = self.active.clone();
        let route = match self.job.ask_via {
            AskVia::Mesh => Route::Mesh,
            AskVia::Control => Route::Control,
        };
        self.runtime.spawn(async move {
            let reply = f
                .request(
                    0,
                    &Message::SubscreenRequest { finished, ahead },
                    Box::new([]),
                    route,
                    ASK_TIMEOUT,
                )
                .await
                .map_err(WorkerError::Ask)?;
            match reply.message() {
                Ok(Message::Subscreen { id, rect }) => {
                    let a = Arc::new(Active::new(rect));
                    active.lock().expect("active lock").insert(id, a.clone());
                    Ok(Next::Subscreen(id, a))
                }
                Ok(Message::NoMoreWork) => Ok(Next::Done),
                Ok(Message::NothingAhead) if ahead => Ok(Next::NothingAhead),
                other => Err(WorkerError::Answer(format!("{other:?}"))),
            }
        })
    }

    /// Waits for the answer to a request.
    fn answer(&self, asked: Asked) -> Result<Next, WorkerError> {
        self.runtime
            .block_on(asked)
            .map_err(|e| WorkerError::Answer(format!("the request was lost: {e}")))?
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
        unsent: &mut Unsent,
        trace_stats: &mut renderer::trace::TraceStats,
    ) -> Result<(), RenderError> {
        let rect = active.rect;
        let settings = &self.job.settings;
        let mut pixels: Vec<[f32; 3]> = Vec::new();
        loop {
            // Coherent rays (the host asks for them only with a cache smaller than the scene)
            // want many paths in flight: as many rows are taken at once as fill a batch. One
            // at a time otherwise: rows not begun can be given back to idle nodes.
            let coherent = self.coherent();
            let paths = paths_in_flight(PATHS_MEMORY / self.job.render_threads.max(1) as usize);
            let rows_at_once = if coherent {
                coherent_rows(rect.width, settings.spp, paths)
            } else {
                1
            };
            let Some(rows) = active.take(rows_at_once) else {
                break;
            };
            let band = Rect {
                x: rect.x,
                y: rect.y + rows.start,
                width: rect.width,
                height: rows.end - rows.start,
            };
            if coherent {
                // Between batches of rows this thread holds nothing of the cache: evicted data
                // it used may be freed (and within a batch, at each fetch for waiting paths).
                reader.refresh();
                let data = touched.watching(&*reader);
                let tracer = Tracer::new(&self.scene, &data);
                let mut coherence = CoherenceStats::default();
                pixels = render_rect_coherent(
                    &tracer,
                    &self.job.camera,
                    settings,
                    band,
                    paths,
                    trace_stats,
                    &mut coherence,
                )?;
                self.stats
                    .paths_deferred
                    .fetch_add(coherence.deferrals, Ordering::Relaxed);
                self.stats
                    .deferred_fetches
                    .fetch_add(coherence.brings, Ordering::Relaxed);
                trace_stats.add(&tracer.stats());
            } else {
                pixels.clear();
                for x in rect.x..rect.x + rect.width {
                    // Between pixels this thread holds nothing of the cache: what it evicted
                    // may be freed, so a small cache that evicts at every fetch keeps no more
                    // than one pixel's worth waiting to be freed.
                    reader.refresh();
                    reader.tick();
                    // Deferral is never turned on here (only coherent batches do).
                    let data = touched.watching_fetched(&*reader);
                    let tracer = Tracer::new(&self.scene, &data);
                    let px =
                        render_pixel(&tracer, &self.job.camera, settings, x, band.y, trace_stats)?;
                    trace_stats.add(&tracer.stats());
                    pixels.push(px);
                }
            }
            unsent.add(id, rect, band.y, &pixels);
            if unsent.due() {
                self.send_rows(unsent)?;
            }
        }
        Ok(())
    }

    /// Whether the paths of this node's next rows may wait for data ([`CoherentRays`]). Asked
    /// again for each batch: segments announced late may be mapped by then.
    fn coherent(&self) -> bool {
        match self.job.coherent_rays {
            CoherentRays::Off => false,
            CoherentRays::On => true,
            CoherentRays::Auto => !self.reads_in_place(),
        }
    }

    /// Whether every demand fetch of this node is a read in place: DMA, through a mapped
    /// segment of every live card, with no delay model to charge it.
    fn reads_in_place(&self) -> bool {
        let topology = self.fabric.topology();
        let live_cards = (topology.fork_nodes().into_iter())
            .filter(|&n| self.fabric.is_alive(n))
            .count();
        self.job.demand_via == Transfer::Dma
            && topology.model.link == fabric::model::LinkModelKind::None
            && self.cache.shared_segments() as usize >= live_cards
    }

    /// Sends the rows rendered and not yet sent to the fork node: a frame for each
    /// subscreen's run of rows, queued together, so that they leave in one write and every
    /// process on their way wakes once for all of them.
    fn send_rows(&self, unsent: &mut Unsent) -> Result<(), fabric::SendError> {
        for run in unsent.take() {
            let rows = run.pixels.len() as u64 / run.rect.width.max(1) as u64;
            let words = || bytemuck::cast_slice::<[f32; 3], u32>(&run.pixels).into();
            let msg = Message::Pixels {
                subscreen: run.subscreen,
                y: run.y,
                x: run.rect.x,
                width: run.rect.width,
            };
            // To the fork node serving this node now: another card's, once its own is lost.
            // While a lost fork node's routes change, the one asked for may have just been
            // cut off; asked again, the serving fork node is one that can be reached.
            let fork = || {
                self.fabric
                    .serving_fork(self.fabric.me())
                    .unwrap_or(self.fork)
            };
            let mut sent = self.fabric.send(fork(), &msg, words(), 0);
            if matches!(sent, Err(fabric::SendError::NoRoute { .. })) {
                sent = self.fabric.send(fork(), &msg, words(), 0);
            }
            match sent {
                Ok(()) => {}
                Err(e @ fabric::SendError::NoRoute { .. }) => {
                    // Rows lost on their way, as with a fork node lost while they cross it:
                    // the host renders again the rows of this node's subscreens that never
                    // came.
                    tracing::warn!(
                        "rows {}.. of subscreen {} not sent ({e}); the host renders them again",
                        run.y,
                        run.subscreen
                    );
                    continue;
                }
                Err(e) => return Err(e),
            }
            self.stats.rows.fetch_add(rows, Ordering::Relaxed);
            self.stats
                .pixels
                .fetch_add(rows * run.rect.width as u64, Ordering::Relaxed);
        }
        Ok(())
    }
}

/// Rows rendered and not yet sent, of this subscreen and of those finished before it. They
/// go together (a few rows of a small subscreen are a few hundred bytes, and each sending
/// costs every process on the way a wake-up and a write; the paper's default of eight
/// subscreens a render node makes them small when few nodes work), but never wait long: the
/// host keeps what arrived when a render stops, and shows progress by it. A node lost with
/// rows unsent loses nothing: the host renders again the rows of its subscreens that never
/// came.
struct Unsent {
    runs: Vec<Run>,
    /// When the first unsent row was added.
    since: Option<Instant>,
}

/// Consecutive rows of one subscreen, from row `y`.
struct Run {
    subscreen: u32,
    rect: Rect,
    y: u32,
    pixels: Vec<[f32; 3]>,
}

/// Unsent rows go once they fill this many pixels...
const PIXELS_PER_FRAME: usize = 4096;
/// ...or once the first of them has waited this long.
const LONGEST_HOLD: Duration = Duration::from_millis(250);

impl Unsent {
    fn new() -> Unsent {
        Unsent {
            runs: Vec::new(),
            since: None,
        }
    }

    /// Adds rows from row `y` of `subscreen` (a subscreen's rows are rendered in order, top
    /// down: rows that follow its last run extend that run).
    fn add(&mut self, subscreen: u32, rect: Rect, y: u32, pixels: &[[f32; 3]]) {
        self.since.get_or_insert_with(Instant::now);
        if let Some(run) = self.runs.last_mut()
            && run.subscreen == subscreen
            && run.y + (run.pixels.len() / rect.width.max(1) as usize) as u32 == y
        {
            run.pixels.extend_from_slice(pixels);
            return;
        }
        self.runs.push(Run {
            subscreen,
            rect,
            y,
            pixels: pixels.to_vec(),
        });
    }

    fn due(&self) -> bool {
        self.runs.iter().map(|r| r.pixels.len()).sum::<usize>() >= PIXELS_PER_FRAME
            || self.since.is_some_and(|t| t.elapsed() >= LONGEST_HOLD)
    }

    /// The runs, in the order they were rendered; none are left.
    fn take(&mut self) -> Vec<Run> {
        self.since = None;
        std::mem::take(&mut self.runs)
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
    fn unsent_rows_of_several_subscreens_wait_until_full_or_the_first_has_waited_long() {
        let a = Rect {
            x: 0,
            y: 0,
            width: 100,
            height: 50,
        };
        let b = Rect { x: 100, ..a };
        let mut u = Unsent::new();
        assert!(!u.due(), "nothing to send");
        u.add(3, a, 7, &[[1.0; 3]; 100]);
        u.add(3, a, 8, &[[2.0; 3]; 200]);
        // Another subscreen, then rows of the first that do not follow its run.
        u.add(4, b, 0, &[[3.0; 3]; 100]);
        u.add(3, a, 20, &[[4.0; 3]; 100]);
        assert!(!u.due());
        let runs = u.take();
        let shape: Vec<_> = runs
            .iter()
            .map(|r| (r.subscreen, r.rect.x, r.y, r.pixels.len()))
            .collect();
        assert_eq!(
            shape,
            [(3, 0, 7, 300), (4, 100, 0, 100), (3, 0, 20, 100)],
            "runs in the order rendered, consecutive rows of one subscreen in one"
        );
        assert_eq!(runs[0].pixels[150], [2.0; 3]);
        assert!(!u.due() && u.take().is_empty(), "taken: nothing left");
        u.add(5, a, 0, &vec![[5.0; 3]; PIXELS_PER_FRAME]);
        assert!(u.due(), "full");
        u.take();
        u.add(5, a, 41, &[[6.0; 3]; 10]);
        assert!(!u.due());
        u.since = Some(Instant::now() - LONGEST_HOLD);
        assert!(u.due(), "waited long enough");
    }

    #[test]
    fn give_back_halves_the_rest_and_never_the_rows_in_hand() {
        let a = Active::new(Rect {
            x: 0,
            y: 0,
            width: 4,
            height: 10,
        });
        assert_eq!(a.take(2), Some(0..2));
        assert_eq!(a.give_back(), 6);
        assert_eq!(a.take(3), Some(2..5));
        assert_eq!(a.give_back(), 6, "one row left: nothing to give");
        assert_eq!(a.take(4), Some(5..6), "no row past the end given back");
        assert_eq!(a.take(1), None);
    }
}
