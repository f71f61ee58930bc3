//! Frames on their way: sent from here, forwarded hop by hop through the mesh along the
//! routes (which go around nodes declared dead), copied down the broadcast spanning tree,
//! and finally held until their model time has come and handed to the role code.
//!
//! Forwarding runs on the reader task of the link a frame arrived on, at once, so it never
//! waits for rendering (the paper's high-priority communication process).

use std::sync::atomic::Ordering;

use protocol::{BROADCAST, Frame, FrameHeader, Message, NodeId, frame::Mode};

use super::{Delivery, FLAG_REPLY, Fabric, SendError, Via, links::from_wire_times};
use crate::clock::now_ns;

/// What a node does with a frame that arrived on a mesh link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Onward {
    /// It has crossed more links than any route has: a loop, so it goes no further.
    Drop,
    /// Copy it to this node's children in the tree rooted at `root`, and deliver it here.
    Broadcast { root: NodeId },
    /// It is for this node.
    Deliver,
    /// Pass it to the neighbour `next` on the route to its receiver.
    Forward { next: NodeId },
    /// The mesh has no route to its receiver from here (dead nodes cut it off).
    NoRoute,
}

/// Decides [`Onward`] for a frame at node `me` whose header already counts this hop.
fn onward(
    header: &FrameHeader,
    me: NodeId,
    next_hop: impl FnOnce(NodeId) -> Option<NodeId>,
) -> Onward {
    if header.hops > protocol::frame::MAX_HOPS {
        return Onward::Drop;
    }
    match header.mode {
        Mode::Broadcast => Onward::Broadcast {
            root: header.sender,
        },
        Mode::OneToOne if header.receiver == me => Onward::Deliver,
        Mode::OneToOne => match next_hop(header.receiver) {
            Some(next) => Onward::Forward { next },
            None => Onward::NoRoute,
        },
    }
}

impl Fabric {
    /// Sends `message` (and `data`) to node `to` through the mesh.
    pub fn send(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
    ) -> Result<(), SendError> {
        let frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        self.send_frame(frame, 0)
    }

    /// Sends to every node through the broadcast spanning tree rooted here.
    pub fn broadcast(&self, message: &Message, data: Box<[u32]>) {
        let _ = self.send(BROADCAST, message, data, 0);
    }

    /// Like [`Fabric::send`], for a message whose data is only ready at model time
    /// `ready_ns` (sent now, stamped as if sent then).
    pub fn send_at(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        tag: u32,
        flags: u8,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let mut frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        frame.header.flags |= flags;
        self.send_frame(frame, ready_ns)
    }

    /// Stamps a frame leaving this node at model time `ready_ns` (or now) and sends it on
    /// its first link: towards its receiver, or down the broadcast tree.
    pub(super) fn send_frame(&self, mut frame: Frame, ready_ns: u64) -> Result<(), SendError> {
        self.inner.count(|c| &c.frames_sent);
        if self.inner.model.links_delayed() {
            let ready = ready_ns.max(now_ns()) + self.inner.model.base_ns();
            frame.header.first_ns = ready;
            frame.header.last_ns = ready;
        }
        let to = frame.header.receiver;
        if to == self.inner.me {
            self.deliver(frame, Via::Mesh(self.inner.me));
            return Ok(());
        }
        if to == BROADCAST {
            for child in self.broadcast_children(self.inner.me) {
                self.send_on_link(child, frame.clone());
            }
            return Ok(());
        }
        let next = self
            .inner
            .routes
            .read()
            .expect("routes lock")
            .next_hop(self.inner.me, to);
        match next {
            Some(n) => {
                self.send_on_link(n, frame);
                Ok(())
            }
            None => self.send_around_the_mesh(frame),
        }
    }

    /// When lost nodes have cut the mesh between here and `frame`'s receiver, the frame
    /// takes a direct or control connection to it instead, if there is one (a render node
    /// has both to the host and to its fork node): a hole in the mesh then slows nothing
    /// that matters. Such a frame is outside the link model, so it carries no model times.
    pub(super) fn send_around_the_mesh(&self, mut frame: Frame) -> Result<(), SendError> {
        let to = frame.header.receiver;
        frame.header.first_ns = 0;
        frame.header.last_ns = 0;
        let direct = self.inner.direct.lock().expect("lock").get(&to).cloned();
        let peer = direct.or_else(|| self.inner.control.lock().expect("lock").get(&to).cloned());
        match peer {
            Some(p) => {
                self.inner.count(|c| &c.frames_around_mesh);
                let _ = p.tx.send(frame);
                Ok(())
            }
            None => Err(SendError::NoRoute {
                from: self.inner.me,
                to,
            }),
        }
    }

    /// A frame arrived on a mesh link from `neighbor`: deliver it here, pass it on, or both.
    pub(super) fn on_mesh_frame(&self, neighbor: NodeId, frame: Frame) {
        let mut frame = from_wire_times(frame, now_ns);
        frame.header.hops = frame.header.hops.saturating_add(1);
        let next_hop = |to| {
            let routes = self.inner.routes.read().expect("routes lock");
            routes.next_hop(self.inner.me, to)
        };
        match onward(&frame.header, self.inner.me, next_hop) {
            Onward::Drop => self.inner.count(|c| &c.frames_dropped),
            Onward::Broadcast { root } => {
                for child in self.broadcast_children(root) {
                    self.count_forwarded(&frame);
                    self.send_on_link(child, frame.clone());
                }
                self.deliver(frame, Via::Mesh(neighbor));
            }
            Onward::Deliver => self.deliver(frame, Via::Mesh(neighbor)),
            Onward::Forward { next } => {
                self.count_forwarded(&frame);
                self.send_on_link(next, frame);
            }
            Onward::NoRoute => {
                let (to, from) = (frame.header.receiver, frame.header.sender);
                if self.send_around_the_mesh(frame).is_ok() {
                    return;
                }
                tracing::warn!("no route to node {to}; frame from {from} dropped");
                self.inner.count(|c| &c.frames_dropped);
            }
        }
    }

    fn count_forwarded(&self, frame: &Frame) {
        self.inner.count(|c| &c.frames_forwarded);
        self.inner
            .counters
            .bytes_forwarded
            .fetch_add(frame.wire_len() as u64, Ordering::Relaxed);
    }

    fn broadcast_children(&self, root: NodeId) -> Vec<NodeId> {
        self.inner
            .routes
            .read()
            .expect("routes lock")
            .broadcast_children(self.inner.me, root)
            .to_vec()
    }

    /// Hands a frame to the role code (or to the request it answers), once its model time
    /// has come.
    pub(super) fn deliver(&self, frame: Frame, via: Via) {
        if frame.header.flags & FLAG_REPLY != 0 {
            self.deliver_answer(frame);
            return;
        }
        let deadline = frame.header.last_ns;
        let inner = self.inner.clone();
        if deadline > now_ns() {
            let timer = inner.timer.clone();
            tokio::spawn(async move {
                timer.sleep_until(deadline).await;
                inner.count(|c| &c.frames_delivered);
                let _ = inner.inbox.send(Delivery::Frame { frame, via });
            });
        } else {
            inner.count(|c| &c.frames_delivered);
            let _ = inner.inbox.send(Delivery::Frame { frame, via });
        }
    }

    /// Marks nodes dead or alive and recomputes routes around the dead ones.
    pub fn set_alive(&self, alive: &[bool]) {
        let mut routes = self.inner.routes.write().expect("routes lock");
        *routes = routes.with_alive(alive);
    }

    pub fn is_alive(&self, id: NodeId) -> bool {
        self.inner.routes.read().expect("routes lock").is_alive(id)
    }

    /// The fork node serving render node `id` given the losses this node knows of
    /// ([`crate::Topology::serving_fork`]).
    pub fn serving_fork(&self, id: NodeId) -> Option<NodeId> {
        let routes = self.inner.routes.read().expect("routes lock");
        self.inner.topology.serving_fork(id, routes.alive())
    }

    /// The G-bus arbiter given the losses this node knows of: the first live fork node.
    pub fn first_live_fork(&self) -> Option<NodeId> {
        let routes = self.inner.routes.read().expect("routes lock");
        self.inner.topology.first_live_fork(routes.alive())
    }

    /// Declares `node` dead: routes go around it from now on, and requests waiting for
    /// answers are sent again in case they or their answers were lost in it. Returns false
    /// if it was already known dead.
    pub fn mark_dead(&self, node: NodeId) -> bool {
        {
            let mut routes = self.inner.routes.write().expect("routes lock");
            if !routes.is_alive(node) || node == self.inner.me {
                return false;
            }
            let mut alive = routes.alive().to_vec();
            alive[node as usize] = false;
            *routes = routes.with_alive(&alive);
        }
        self.abandon_requests_to(node);
        self.resend_pending();
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(mode: Mode, sender: NodeId, receiver: NodeId, hops: u8) -> FrameHeader {
        let mut frame = Frame::new(sender, receiver, &Message::Go, Box::new([]));
        frame.header.mode = mode;
        frame.header.hops = hops;
        frame.header
    }

    #[test]
    fn a_frame_for_this_node_is_delivered_here() {
        let h = header(Mode::OneToOne, 2, 7, 3);
        assert_eq!(
            onward(&h, 7, |_| panic!("no route needed")),
            Onward::Deliver
        );
    }

    #[test]
    fn a_frame_for_another_node_takes_the_next_hop_or_goes_around() {
        let h = header(Mode::OneToOne, 2, 9, 1);
        assert_eq!(
            onward(&h, 7, |to| (to == 9).then_some(8)),
            Onward::Forward { next: 8 }
        );
        assert_eq!(onward(&h, 7, |_| None), Onward::NoRoute);
    }

    #[test]
    fn a_broadcast_goes_down_the_tree_of_its_sender() {
        let h = header(Mode::Broadcast, 4, BROADCAST, 2);
        assert_eq!(onward(&h, 7, |_| None), Onward::Broadcast { root: 4 });
    }

    #[test]
    fn a_frame_past_the_hop_limit_is_dropped() {
        let max = protocol::frame::MAX_HOPS;
        let h = header(Mode::OneToOne, 2, 7, max);
        assert_eq!(onward(&h, 7, |_| None), Onward::Deliver);
        let h = header(Mode::OneToOne, 2, 7, max + 1);
        assert_eq!(onward(&h, 7, |_| None), Onward::Drop);
        let h = header(Mode::Broadcast, 2, BROADCAST, max + 1);
        assert_eq!(onward(&h, 7, |_| None), Onward::Drop);
    }
}
