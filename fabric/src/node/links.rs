//! The connections of a process once they are authenticated: a writer task that sends
//! heartbeats when there is nothing else to say, a reader task that hands every frame on and
//! reports the connection lost when it ends, and the sending side of each kind.
//!
//! A frame's model times are advanced here, as it crosses a mesh link, and converted for the
//! wire when the far end does not share this machine's clock. Which links a node has in a
//! topology ([`expected_direct`], [`dials`]) is decided here too, from the topology alone.

use std::{
    sync::{Arc, Mutex, atomic::Ordering},
    time::{Duration, SystemTime},
};

use protocol::{ConnectionKind, Frame, FrameReader, FrameWriter, Message, NodeId, Role};
use tokio::{sync::mpsc, time::Instant};

use super::{
    CONTROL_SILENCE_LIMIT, Delivery, FLAG_RELATIVE_TIMES, Fabric, HEARTBEAT_INTERVAL,
    LINK_SILENCE_LIMIT, Peer, SendError, Via,
};
use crate::{clock::now_ns, model::LinkClock, topology::Topology};

impl Fabric {
    /// Takes over an authenticated connection: starts its reader and writer.
    pub(crate) fn attach(
        &self,
        peer: NodeId,
        kind: ConnectionKind,
        reader: FrameReader<tokio::net::tcp::OwnedReadHalf>,
        writer: FrameWriter<tokio::net::tcp::OwnedWriteHalf>,
    ) {
        let (tx, rx) = mpsc::unbounded_channel::<Frame>();
        let same_clock = self.same_machine(peer);
        let p = Arc::new(Peer {
            tx,
            clock: Mutex::new(LinkClock::default()),
            same_clock,
        });
        self.inner.table(kind).lock().expect("lock").insert(peer, p);
        let me = self.inner.me;
        let heartbeat = Frame::new(me, peer, &Message::Heartbeat { node: me }, Box::new([]));
        let heartbeat_kind = heartbeat.header.kind;
        tokio::spawn(write_until_closed(writer, rx, heartbeat));
        tokio::spawn(
            self.clone()
                .read_until_closed(peer, kind, reader, heartbeat_kind),
        );
    }

    /// Hands on every frame that arrives from `peer` until the connection ends, then drops
    /// it from its table and (unless this process is closing) reports it lost.
    async fn read_until_closed(
        self,
        peer: NodeId,
        kind: ConnectionKind,
        mut reader: FrameReader<tokio::net::tcp::OwnedReadHalf>,
        heartbeat_kind: u8,
    ) {
        // Once the handshake is over, a frame may take as long as a big transfer needs.
        reader.frame_timeout = Duration::from_secs(60);
        reader.idle_deadline = Some(match kind {
            ConnectionKind::Control => CONTROL_SILENCE_LIMIT,
            _ => LINK_SILENCE_LIMIT,
        });
        let reason = loop {
            match reader.read().await {
                // Heartbeats only prove the peer is there; they go no further.
                Ok(frame) if frame.header.kind == heartbeat_kind => {}
                Ok(frame) => match kind {
                    ConnectionKind::Mesh => self.on_mesh_frame(peer, frame),
                    ConnectionKind::Direct => {
                        let frame = from_wire_times(frame, now_ns);
                        self.deliver(frame, Via::Direct(peer))
                    }
                    ConnectionKind::Control => self.deliver(frame, Via::Control(peer)),
                },
                Err(e) => {
                    if !self.is_closing() && !matches!(e, protocol::ReadError::Closed) {
                        tracing::warn!("connection to node {peer} ({kind:?}) failed: {e}");
                    }
                    break e.to_string();
                }
            }
        };
        self.inner.table(kind).lock().expect("lock").remove(&peer);
        if !self.is_closing() {
            let _ = self.inner.inbox.send(Delivery::Lost { peer, kind, reason });
        }
    }

    /// Records whether `peer` shares this machine's monotonic clock.
    pub fn set_same_machine(&self, peer: NodeId, same: bool) {
        self.inner
            .same_machine
            .lock()
            .expect("lock")
            .insert(peer, same);
    }

    /// Whether `peer` runs on this machine (one boot of it), by the address table; taken as
    /// so where the table did not say.
    pub fn same_machine(&self, peer: NodeId) -> bool {
        self.inner
            .same_machine
            .lock()
            .expect("lock")
            .get(&peer)
            .copied()
            .unwrap_or(true)
    }

    /// Stamps a frame with the model times of crossing the link to `neighbor`, and sends it.
    pub(super) fn send_on_link(&self, neighbor: NodeId, mut frame: Frame) {
        let p = self
            .inner
            .mesh
            .lock()
            .expect("lock")
            .get(&neighbor)
            .cloned();
        let Some(p) = p else {
            tracing::debug!(
                "no link to node {neighbor}; frame for {} dropped",
                frame.header.receiver
            );
            self.inner.count(|c| &c.frames_dropped);
            return;
        };
        let model = &self.inner.model;
        if model.links_delayed() {
            let (packets, size) = model.packets(frame.wire_len());
            let hop = model.hop_ns(
                self.inner.topology.is_vertical(self.inner.me, neighbor),
                size,
            );
            let (first, last) = p.clock.lock().expect("lock").cross(
                frame.header.first_ns,
                frame.header.last_ns,
                packets,
                hop,
            );
            frame.header.first_ns = first;
            frame.header.last_ns = last;
        }
        self.inner
            .counters
            .bytes_mesh_out
            .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
        let _ = p.tx.send(to_wire_times(frame, p.same_clock, now_ns));
    }

    /// Sends a frame over a direct (DMA or G-bus) connection. `ready_ns`, when not 0, is the
    /// model time at which the receiver may use it (the role computes DMA and bus times).
    pub fn send_direct(
        &self,
        peer: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let mut frame = Frame::new(self.inner.me, peer, message, data).with_tag(tag);
        frame.header.first_ns = ready_ns;
        frame.header.last_ns = ready_ns;
        self.send_direct_frame(peer, frame)
    }

    pub(super) fn send_direct_frame(&self, peer: NodeId, frame: Frame) -> Result<(), SendError> {
        self.inner.count(|c| &c.frames_sent);
        let p = self.inner.direct.lock().expect("lock").get(&peer).cloned();
        match p {
            Some(p) => {
                self.inner
                    .counters
                    .bytes_direct_out
                    .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
                let _ = p.tx.send(to_wire_times(frame, p.same_clock, now_ns));
                Ok(())
            }
            None => Err(SendError::NotConnected {
                peer,
                kind: ConnectionKind::Direct,
            }),
        }
    }

    /// Sends on a control connection (a node to the host, or the host to a node).
    pub fn send_control(&self, peer: NodeId, message: &Message) -> Result<(), SendError> {
        self.send_control_frame(peer, Frame::new(self.inner.me, peer, message, Box::new([])))
    }

    /// Sends `frame` on the control connection to `peer`.
    pub(super) fn send_control_frame(&self, peer: NodeId, frame: Frame) -> Result<(), SendError> {
        let p = self.inner.control.lock().expect("lock").get(&peer).cloned();
        match p {
            Some(p) => {
                let _ = p.tx.send(frame);
                Ok(())
            }
            None => Err(SendError::NotConnected {
                peer,
                kind: ConnectionKind::Control,
            }),
        }
    }

    pub fn has_direct(&self, peer: NodeId) -> bool {
        self.inner.direct.lock().expect("lock").contains_key(&peer)
    }

    /// Whether the control connection to `peer` is still open.
    pub fn has_control(&self, peer: NodeId) -> bool {
        self.inner.control.lock().expect("lock").contains_key(&peer)
    }

    pub fn mesh_links_up(&self) -> usize {
        self.inner.mesh.lock().expect("lock").len()
    }

    pub fn direct_links_up(&self) -> usize {
        self.inner.direct.lock().expect("lock").len()
    }
}

/// When a connection that last sent at `last` sends its heartbeat: on the first beat of the
/// system clock (a whole multiple of [`HEARTBEAT_INTERVAL`] since the epoch) at least half an
/// interval after `last`, so a quiet connection hears from its peer every half to one and a
/// half intervals.
///
/// Why beats of a shared clock: a cluster on one machine holds hundreds of connections, most
/// of them quiet while a few render nodes work. With a timer per connection running from its
/// own last frame, their heartbeats were spread over each second, and every one woke a writer
/// and a reader in two processes (about 1,500 context switches a second on 86 processes,
/// each evicting some of a rendering thread's caches). On shared beats every process wakes
/// once a beat for all its quiet connections, and its peers read them in one wake-up.
fn next_beat(last: Instant, now: Instant, since_epoch: Duration) -> Instant {
    let period = HEARTBEAT_INTERVAL.as_nanos();
    let phase = since_epoch.as_nanos() % period;
    let mut beat = now + Duration::from_nanos(((period - phase) % period) as u64);
    while beat < last + HEARTBEAT_INTERVAL / 2 {
        beat += HEARTBEAT_INTERVAL;
    }
    beat
}

/// [`next_beat`] for a connection that sends now.
fn beat_after_sending() -> Instant {
    let now = Instant::now();
    let since_epoch = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default();
    next_beat(now, now, since_epoch)
}

/// Writes what the runtime queues for one connection, and a heartbeat on each beat it has
/// been quiet for ([`next_beat`]), until the queue closes or the peer stops reading.
async fn write_until_closed(
    mut writer: FrameWriter<tokio::net::tcp::OwnedWriteHalf>,
    mut queue: mpsc::UnboundedReceiver<Frame>,
    heartbeat: Frame,
) {
    let beat = tokio::time::sleep_until(beat_after_sending());
    tokio::pin!(beat);
    loop {
        let frame = tokio::select! {
            biased;
            f = queue.recv() => match f {
                Some(f) => f,
                None => break,
            },
            _ = &mut beat => heartbeat.clone(),
        };
        // Whatever else is queued by now goes out in the same write.
        let mut sent = writer.put(&frame).await;
        while sent.is_ok()
            && let Ok(next) = queue.try_recv()
        {
            sent = writer.put(&next).await;
        }
        if sent.is_err() || writer.flush().await.is_err() {
            break;
        }
        beat.as_mut().reset(beat_after_sending());
    }
}

/// Model times cross machines as "so long after arrival" (`now` is read only then); on one
/// machine they stay absolute.
pub(super) fn to_wire_times(
    mut frame: Frame,
    same_clock: bool,
    now: impl FnOnce() -> u64,
) -> Frame {
    if !same_clock && frame.header.last_ns != 0 {
        let now = now();
        frame.header.first_ns = frame.header.first_ns.saturating_sub(now).max(1);
        frame.header.last_ns = frame.header.last_ns.saturating_sub(now).max(1);
        frame.header.flags |= FLAG_RELATIVE_TIMES;
    }
    frame
}

/// Undoes [`to_wire_times`] on arrival, at `now`.
pub(super) fn from_wire_times(mut frame: Frame, now: impl FnOnce() -> u64) -> Frame {
    if frame.header.flags & FLAG_RELATIVE_TIMES != 0 {
        let now = now();
        frame.header.first_ns += now;
        frame.header.last_ns += now;
        frame.header.flags &= !FLAG_RELATIVE_TIMES;
    }
    frame
}

/// The direct connections a node has in a topology: a render node to its fork node, a fork
/// node to its render nodes, to every other fork node and to the host (the G-bus).
pub fn expected_direct(t: &Topology, me: NodeId) -> Vec<NodeId> {
    match t.role(me) {
        Role::Render => t.fork_of(me).into_iter().collect(),
        Role::Fork => {
            let mut v: Vec<NodeId> = t
                .render_nodes()
                .into_iter()
                .filter(|&r| t.card(r) == t.card(me))
                .collect();
            v.extend(t.fork_nodes().into_iter().filter(|&f| f != me));
            v.push(0);
            v
        }
        Role::Host => t.fork_nodes(),
    }
}

/// The connections `me` opens itself: mesh links and direct connections to higher ids, and
/// always those of a render node to its fork node and of a fork node to the host.
pub fn dials(t: &Topology, me: NodeId) -> Vec<(NodeId, ConnectionKind)> {
    let mut out: Vec<(NodeId, ConnectionKind)> = t
        .neighbors(me)
        .iter()
        .filter(|&&n| n > me)
        .map(|&n| (n, ConnectionKind::Mesh))
        .collect();
    for peer in expected_direct(t, me) {
        let i_dial = match (t.role(me), t.role(peer)) {
            (Role::Render, Role::Fork) => true,
            (Role::Fork, Role::Render) => false,
            (Role::Fork, Role::Host) => true,
            (Role::Host, Role::Fork) => false,
            _ => me < peer,
        };
        if i_dial {
            out.push((peer, ConnectionKind::Direct));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(first_ns: u64, last_ns: u64) -> Frame {
        let mut f = Frame::new(1, 2, &Message::Go, Box::new([]));
        f.header.first_ns = first_ns;
        f.header.last_ns = last_ns;
        f
    }

    /// Heartbeats fall on whole beats of the system clock, half an interval to one and a half
    /// after the connection last sent: quiet connections of every process beat together, and
    /// a peer never waits much longer than an interval, far within the silence limits.
    #[test]
    fn heartbeats_fall_on_shared_beats_within_one_and_a_half_intervals() {
        let i = HEARTBEAT_INTERVAL;
        let now = Instant::now();
        for phase_ms in [0u64, 1, 250, 499, 500, 501, 999] {
            let phase = Duration::from_millis(phase_ms) * i.as_millis() as u32 / 1000;
            // An epoch reading a whole number of intervals, plus the phase.
            let since_epoch = i * 1_000_000 + phase;
            let beat = next_beat(now, now, since_epoch);
            let wait = beat - now;
            assert!(
                wait >= i / 2 && wait < i * 3 / 2,
                "phase {phase:?}: waits {wait:?}"
            );
            // On a beat: the clock then reads a whole number of intervals.
            assert_eq!(
                (since_epoch + wait).as_nanos() % i.as_nanos(),
                0,
                "phase {phase:?}"
            );
        }
        // Sent a while ago: the next beat that is at least half an interval after it.
        let last = now - i * 3;
        assert_eq!(next_beat(last, now, i * 7), now);
        assert!(CONTROL_SILENCE_LIMIT > i * 3 && LINK_SILENCE_LIMIT > i * 3);
    }

    #[test]
    fn wire_times_are_relative_between_machines_and_restored_on_arrival() {
        let sent = to_wire_times(frame(1_500, 2_000), false, || 1_000);
        assert_eq!((sent.header.first_ns, sent.header.last_ns), (500, 1_000));
        assert_ne!(sent.header.flags & FLAG_RELATIVE_TIMES, 0);
        // It arrives on a machine whose clock reads 70 000 at that moment.
        let arrived = from_wire_times(sent, || 70_000);
        assert_eq!(
            (arrived.header.first_ns, arrived.header.last_ns),
            (70_500, 71_000)
        );
        assert_eq!(arrived.header.flags & FLAG_RELATIVE_TIMES, 0);
    }

    #[test]
    fn wire_times_stay_absolute_on_one_machine_and_without_a_model() {
        let clock = || panic!("the clock need not be read");
        let same = to_wire_times(frame(1_500, 2_000), true, clock);
        assert_eq!((same.header.first_ns, same.header.last_ns), (1_500, 2_000));
        let unmodelled = to_wire_times(frame(0, 0), false, clock);
        assert_eq!(unmodelled.header.flags & FLAG_RELATIVE_TIMES, 0);
        assert_eq!(from_wire_times(same, clock).header.last_ns, 2_000);
    }

    #[test]
    fn a_time_already_past_still_arrives_as_a_time() {
        // 0 means "no model time", so a late frame is due at once, not never.
        let sent = to_wire_times(frame(100, 200), false, || 5_000);
        assert_eq!((sent.header.first_ns, sent.header.last_ns), (1, 1));
    }

    #[test]
    fn direct_connections_by_role() {
        // grid:2x1x1: host 0, fork nodes 1 and 2, render nodes 3 (card 0) and 4 (card 1).
        let t = Topology::preset("grid:2x1x1").unwrap();
        assert_eq!(expected_direct(&t, 0), vec![1, 2]);
        assert_eq!(expected_direct(&t, 1), vec![3, 2, 0]);
        assert_eq!(expected_direct(&t, 2), vec![4, 1, 0]);
        assert_eq!(expected_direct(&t, 3), vec![1]);
        assert_eq!(expected_direct(&t, 4), vec![2]);
    }

    #[test]
    fn each_connection_is_dialled_by_exactly_one_end() {
        use ConnectionKind::{Direct, Mesh};
        let t = Topology::preset("grid:2x1x1").unwrap();
        assert_eq!(dials(&t, 0), vec![(1, Mesh)]);
        assert_eq!(
            dials(&t, 1),
            vec![(2, Mesh), (3, Mesh), (2, Direct), (0, Direct)]
        );
        assert_eq!(dials(&t, 3), vec![(4, Mesh), (1, Direct)]);
        assert_eq!(dials(&t, 4), vec![(2, Direct)]);
        for t in [
            t,
            Topology::preset("tiny").unwrap(),
            Topology::preset("magg").unwrap(),
        ] {
            for a in 0..t.len() as NodeId {
                for &b in t.neighbors(a) {
                    let ab = dials(&t, a).contains(&(b, Mesh));
                    let ba = dials(&t, b).contains(&(a, Mesh));
                    assert!(ab != ba, "mesh link {a}-{b} in {}", t.name);
                }
                for b in expected_direct(&t, a) {
                    let ab = dials(&t, a).contains(&(b, Direct));
                    let ba = dials(&t, b).contains(&(a, Direct));
                    assert!(ab != ba, "direct connection {a}-{b} in {}", t.name);
                    assert!(expected_direct(&t, b).contains(&a), "{a}-{b} one-sided");
                }
            }
        }
    }
}
