//! Requests that wait for their answer. A request carries a tag; the answer comes back
//! with the same tag and the reply flag, and goes to the waiting request instead of the
//! role code. Requests through the mesh keep a copy, sent again when routes change, because
//! a node declared dead may have taken the request or its answer with it. A request to the
//! node declared dead itself ends at once ([`RequestError::Closed`]): its asker can turn to
//! whoever stands in for that node instead of waiting out its timeout.

use std::{sync::atomic::Ordering, time::Duration};

use protocol::{Frame, Message, NodeId};

use super::{FLAG_REPLY, Fabric, RequestError, Route, SendError};

/// When routes change, requests still waiting for an answer are sent again now and after
/// these delays: the first copy may have been lost in the dead node, and a node on the way
/// may learn of the death a little later than the sender.
const RESEND_AFTER: [Duration; 3] = [
    Duration::ZERO,
    Duration::from_millis(300),
    Duration::from_millis(1500),
];

/// A request waiting for its answer.
pub(super) struct Pending {
    /// Whom it asked.
    to: NodeId,
    answer: tokio::sync::oneshot::Sender<Frame>,
    /// A copy to send again when routes change (mesh requests only: a direct connection
    /// has no route to change).
    resend: Option<Frame>,
}

impl Fabric {
    /// Sends a request and waits for the frame that answers it (same tag, reply flag). A
    /// mesh request is sent again when routes change, so the receiver must treat a repeated
    /// tag from the same sender as the same request.
    pub async fn request(
        &self,
        to: NodeId,
        message: &Message,
        data: Box<[u32]>,
        route: Route,
        timeout: Duration,
    ) -> Result<Frame, RequestError> {
        let tag = self.inner.next_tag.fetch_add(1, Ordering::Relaxed).max(1);
        let (tx, rx) = tokio::sync::oneshot::channel();
        let frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
        let resend = (route == Route::Mesh).then(|| frame.clone());
        self.inner.pending.lock().expect("lock").insert(
            tag,
            Pending {
                to,
                answer: tx,
                resend,
            },
        );
        let sent = match route {
            Route::Mesh => self.send_frame(frame, 0),
            Route::Direct => self.send_direct_frame(to, frame),
            Route::Control => self.send_control_frame(to, frame),
        };
        if let Err(e) = sent {
            self.inner.pending.lock().expect("lock").remove(&tag);
            return Err(e.into());
        }
        match tokio::time::timeout(timeout, rx).await {
            Ok(Ok(frame)) => Ok(frame),
            Ok(Err(_)) => Err(RequestError::Closed(to)),
            Err(_) => {
                self.inner.pending.lock().expect("lock").remove(&tag);
                Err(RequestError::Timeout {
                    peer: to,
                    seconds: timeout.as_secs(),
                })
            }
        }
    }

    /// Answers `request` (a frame from another node) with `message` and `data`, usable by
    /// the requester from model time `ready_ns` (0: as soon as it arrives).
    pub fn reply(
        &self,
        request: &Frame,
        message: &Message,
        data: Box<[u32]>,
        route: Route,
        ready_ns: u64,
    ) -> Result<(), SendError> {
        let to = request.header.sender;
        let tag = request.header.tag;
        match route {
            Route::Mesh => self.send_at(to, message, data, tag, FLAG_REPLY, ready_ns),
            Route::Direct | Route::Control => {
                let mut frame = Frame::new(self.inner.me, to, message, data).with_tag(tag);
                frame.header.flags |= FLAG_REPLY;
                if route == Route::Direct {
                    frame.header.first_ns = ready_ns;
                    frame.header.last_ns = ready_ns;
                    self.send_direct_frame(to, frame)
                } else {
                    // A control connection carries no model times.
                    self.send_control_frame(to, frame)
                }
            }
        }
    }

    /// Ends every request waiting for an answer from `node`, declared dead: dropping its
    /// sender tells the asker the connection closed.
    pub(super) fn abandon_requests_to(&self, node: NodeId) {
        self.inner
            .pending
            .lock()
            .expect("lock")
            .retain(|_, p| p.to != node);
    }

    /// Sends every mesh request still waiting for its answer again, now and a little later
    /// (routes have just changed).
    pub(super) fn resend_pending(&self) {
        let me = self.clone();
        tokio::spawn(async move {
            for delay in RESEND_AFTER {
                tokio::time::sleep(delay).await;
                let frames: Vec<Frame> = me
                    .inner
                    .pending
                    .lock()
                    .expect("lock")
                    .values()
                    .filter_map(|p| p.resend.clone())
                    .collect();
                for f in frames {
                    let _ = me.send_frame(f, 0);
                }
            }
        });
    }

    /// Hands an answer to the request waiting for it, once its model time has come.
    pub(super) fn deliver_answer(&self, frame: Frame) {
        let deadline = frame.header.last_ns;
        let inner = self.inner.clone();
        let waiter = inner
            .pending
            .lock()
            .expect("lock")
            .remove(&frame.header.tag);
        match waiter {
            Some(w) => {
                let timer = inner.timer.clone();
                tokio::spawn(async move {
                    timer.sleep_until(deadline).await;
                    inner.count(|c| &c.frames_delivered);
                    let _ = w.answer.send(frame);
                });
            }
            // A second answer to a request sent again, or one whose asker gave up.
            None => tracing::debug!(
                "dropped an answer (tag {}) from node {} that nobody waits for",
                frame.header.tag,
                frame.header.sender
            ),
        }
    }
}
