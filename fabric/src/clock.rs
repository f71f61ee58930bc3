//! Time for the delay model.
//!
//! Model timestamps are CLOCK_MONOTONIC nanoseconds, the clock every process on one machine
//! shares; frames crossing machines are converted with a per-link offset. The async runtime's
//! timer only resolves whole milliseconds, far coarser than the paper's 234 us hops, so waits
//! for model deadlines go to a timer thread with minimal timer slack, which sleeps to the
//! earliest deadline and wakes its waiter within tens of microseconds.

use std::{
    cmp::Reverse,
    collections::BinaryHeap,
    sync::{Arc, Condvar, Mutex},
    time::Duration,
};

use tokio::sync::oneshot;

/// CLOCK_MONOTONIC in nanoseconds.
pub fn now_ns() -> u64 {
    let t = clock(libc::CLOCK_MONOTONIC);
    t.as_secs() * 1_000_000_000 + u64::from(t.subsec_nanos())
}

/// CPU time this thread has spent, the cost of work measured apart from waits and from
/// the other processes sharing the cores (which wall time cannot tell apart).
pub fn thread_cpu_time() -> Duration {
    clock(libc::CLOCK_THREAD_CPUTIME_ID)
}

/// A clock read through the C library rather than rustix: rustix finds `clock_gettime` by
/// parsing the vDSO, which crashes under valgrind (rustix issue 1559), and instruction counts
/// under callgrind are how this project measures speed on a shared machine; every node
/// process reads the monotonic clock, so one rustix read kept them all from running there.
fn clock(id: libc::clockid_t) -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec to write to; the clock ids are constants the kernel
    // knows (and if one were not, the call fails and leaves `t` at zero).
    let rc = unsafe { libc::clock_gettime(id, &mut t) };
    if rc != 0 {
        return Duration::ZERO;
    }
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

/// This machine's boot id: processes with the same one share CLOCK_MONOTONIC.
pub fn boot_id() -> String {
    std::fs::read_to_string("/proc/sys/kernel/random/boot_id")
        .map(|s| s.trim().to_string())
        .unwrap_or_default()
}

struct State {
    heap: BinaryHeap<Reverse<(u64, u64)>>,
    waiters: std::collections::HashMap<u64, oneshot::Sender<()>>,
    next_id: u64,
    stop: bool,
}

/// A timer thread for precise waits on model deadlines.
#[derive(Clone)]
pub struct PreciseTimer {
    shared: Arc<(Mutex<State>, Condvar)>,
}

impl Default for PreciseTimer {
    fn default() -> Self {
        PreciseTimer::new()
    }
}

impl PreciseTimer {
    pub fn new() -> PreciseTimer {
        let shared = Arc::new((
            Mutex::new(State {
                heap: BinaryHeap::new(),
                waiters: Default::default(),
                next_id: 0,
                stop: false,
            }),
            Condvar::new(),
        ));
        let s = shared.clone();
        std::thread::Builder::new()
            .name("magg-timer".into())
            .spawn(move || timer_thread(s))
            .expect("spawn the timer thread");
        PreciseTimer { shared }
    }

    /// Waits until CLOCK_MONOTONIC reaches `deadline_ns`.
    pub async fn sleep_until(&self, deadline_ns: u64) {
        let now = now_ns();
        if deadline_ns <= now {
            return;
        }
        // Long waits sleep on the runtime's timer first, then hand the last stretch over.
        let remaining = deadline_ns - now;
        if remaining > 3_000_000 {
            tokio::time::sleep(Duration::from_nanos(remaining - 2_000_000)).await;
        }
        let (tx, rx) = oneshot::channel();
        {
            let (lock, cv) = &*self.shared;
            let mut st = lock.lock().expect("timer lock");
            let id = st.next_id;
            st.next_id += 1;
            st.heap.push(Reverse((deadline_ns, id)));
            st.waiters.insert(id, tx);
            cv.notify_one();
        }
        let _ = rx.await;
    }

    pub fn stop(&self) {
        let (lock, cv) = &*self.shared;
        lock.lock().expect("timer lock").stop = true;
        cv.notify_one();
    }
}

fn timer_thread(shared: Arc<(Mutex<State>, Condvar)>) {
    // The kernel may otherwise defer a wake-up by 50 us to batch it with others.
    let _ = rustix::thread::set_current_timer_slack(std::num::NonZeroU64::new(1));
    let (lock, cv) = &*shared;
    let mut st = lock.lock().expect("timer lock");
    loop {
        if st.stop {
            return;
        }
        let now = now_ns();
        while let Some(&Reverse((deadline, id))) = st.heap.peek() {
            if deadline > now {
                break;
            }
            st.heap.pop();
            if let Some(tx) = st.waiters.remove(&id) {
                let _ = tx.send(());
            }
        }
        st = match st.heap.peek() {
            Some(&Reverse((deadline, _))) => {
                let wait = Duration::from_nanos(deadline.saturating_sub(now_ns()));
                cv.wait_timeout(st, wait).expect("timer lock").0
            }
            None => cv.wait(st).expect("timer lock"),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(flavor = "current_thread")]
    async fn waits_end_close_to_the_deadline() {
        let t = PreciseTimer::new();
        // The runtime's millisecond timer alone would end a median wait about half a
        // millisecond late. Other tests share the cores, so a round may be descheduled as a
        // whole: the best of several rounds is what tells the precise timer from the coarse.
        let mut best_median = u64::MAX;
        for _round in 0..5 {
            let mut late = Vec::new();
            for i in 0..20u64 {
                let deadline = now_ns() + 300_000 + i * 10_000;
                t.sleep_until(deadline).await;
                let now = now_ns();
                assert!(now >= deadline, "woke before the deadline");
                late.push(now - deadline);
            }
            late.sort_unstable();
            best_median = best_median.min(late[10]);
            if best_median < 250_000 {
                break;
            }
        }
        assert!(best_median < 250_000, "median lateness {best_median} ns");
        t.stop();
    }
}
