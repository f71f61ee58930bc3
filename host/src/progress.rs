//! Progress for people: a bar on a terminal, a log line every tenth otherwise.

use std::{
    io::IsTerminal,
    sync::{
        Mutex,
        atomic::{AtomicU64, Ordering},
    },
    time::Instant,
};

use indicatif::{ProgressBar, ProgressStyle};

pub struct Progress {
    bar: Option<ProgressBar>,
    last_tenth: AtomicU64,
    start: Instant,
    label: Mutex<String>,
}

impl Progress {
    /// A progress display for `total` pixels; `enabled` false shows nothing at all.
    pub fn new(total: u64, enabled: bool) -> Progress {
        let bar = (enabled && std::io::stderr().is_terminal()).then(|| {
            let b = ProgressBar::new(total);
            b.set_style(
                ProgressStyle::with_template(
                    "{spinner} [{elapsed_precise}] [{bar:40}] {percent:>3}% {msg} (eta {eta})",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            b
        });
        Progress {
            bar,
            last_tenth: AtomicU64::new(if enabled { 0 } else { u64::MAX }),
            start: Instant::now(),
            label: Mutex::new(String::new()),
        }
    }

    pub fn set_message(&self, msg: &str) {
        if let Some(b) = &self.bar {
            b.set_message(msg.to_string());
        }
        if let Ok(mut l) = self.label.lock() {
            *l = msg.to_string();
        }
    }

    pub fn update(&self, done: u64, total: u64) {
        if let Some(b) = &self.bar {
            b.set_position(done);
            return;
        }
        let tenth = (done * 10).checked_div(total).unwrap_or(10);
        let prev = self.last_tenth.load(Ordering::Relaxed);
        if prev != u64::MAX
            && tenth > prev
            && self
                .last_tenth
                .compare_exchange(prev, tenth, Ordering::Relaxed, Ordering::Relaxed)
                .is_ok()
        {
            tracing::info!(
                "rendered {}% ({:.1} s)",
                tenth * 10,
                self.start.elapsed().as_secs_f64()
            );
        }
    }

    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}
