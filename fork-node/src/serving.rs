//! Serving the card's render nodes: demand requests answered from this card's memory or,
//! for items another card holds, over the G-bus; sent back by DMA or through the mesh as the
//! request asks. The card has one DMA bus, so DMA transfers queue behind each other in model
//! time; that queue is this job's own state. When a fork node is lost, requests for what it
//! held wait until the host has placed that share on the live cards.

use std::{
    sync::{
        Arc, Mutex,
        atomic::{AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use fabric::{Model, Route, clock::now_ns};
use protocol::{DataId, Frame, Message, NodeId, Transfer};

use crate::ForkNode;

/// How long a request waits for the item it asks for to have a live holder again: the host
/// rebuilds a lost card's share from its own copy of the scene in about the time it takes to
/// prepare the scene.
pub(crate) const REBUILD_WAIT: Duration = Duration::from_secs(120);

/// How often a request waiting for an item looks again.
const POLL: Duration = Duration::from_millis(20);

#[derive(Default)]
pub(crate) struct Serving {
    /// When this card's DMA bus is next free (model time).
    dma_free_at: Mutex<u64>,
    pub bytes_served: AtomicU64,
}

impl Serving {
    /// Books a DMA transfer of `bytes` ready at `ready` (model time) on the card's bus and
    /// returns when it completes; 0 (no delay) when the model adds none.
    pub fn dma_done(&self, model: &Model, bytes: u64, ready: u64) -> u64 {
        if !model.links_delayed() {
            return 0;
        }
        let mut free = self.dma_free_at.lock().expect("dma lock");
        let done = (*free).max(ready) + model.dma_ns(bytes);
        *free = done;
        done
    }

    pub fn count_served(&self, bytes: u64) {
        self.bytes_served.fetch_add(bytes, Ordering::Relaxed);
    }
}

impl ForkNode {
    /// Answers a render node's demand request, by DMA or through the mesh. Without
    /// `payload` (the render node reads the bytes from a shared segment) the reply carries
    /// no data, but every model time is charged as if it did. An item whose holder is lost
    /// is waited for until the host has rebuilt that card's share on a live one.
    pub(crate) async fn serve_request(
        &self,
        request: Frame,
        id: DataId,
        transfer: Transfer,
        owner: NodeId,
        payload: bool,
    ) {
        let f = &self.fabric;
        let ready = now_ns();
        let deadline = Instant::now() + REBUILD_WAIT;
        let (data, ready) = loop {
            // Our own address table decides where data lives, when we have one; the host
            // changes it when a fork node is lost.
            let owner = self
                .memory
                .lock()
                .expect("memory lock")
                .owner(id)
                .unwrap_or(owner);
            let got = if owner == f.me() {
                self.held(id, deadline).await.map(|d| (d, ready))
            } else if f.is_alive(owner) {
                self.fetch_remote(id, owner, ready).await
            } else {
                None
            };
            if let Some(x) = got {
                break x;
            }
            if Instant::now() >= deadline {
                tracing::warn!(
                    "fork node {}: no live fork node holds {id:?}; node {} is not answered",
                    f.me(),
                    request.header.sender
                );
                return;
            }
            tokio::time::sleep(POLL).await;
        };
        let bytes = data.len() as u64 * 4;
        self.serving.count_served(bytes);
        let data = if payload { data } else { Box::default() };
        // A render node of a lost fork node's card has no DMA connection here: its answers
        // go through the mesh (same bytes, another model time).
        let dma = transfer == Transfer::Dma && f.has_direct(request.header.sender);
        let result = if dma {
            let done = self.serving.dma_done(f.model(), bytes, ready);
            f.reply(
                &request,
                &Message::DataReply { id },
                data,
                Route::Direct,
                done,
            )
        } else {
            f.reply(
                &request,
                &Message::DataReply { id },
                data,
                Route::Mesh,
                ready,
            )
        };
        if let Err(e) = result {
            tracing::warn!(
                "fork node {}: cannot answer node {}: {e}",
                f.me(),
                request.header.sender
            );
        }
    }

    /// Item `id` from this card's memory, waiting until `deadline` for it to arrive: after
    /// a fork node is lost, the address table may name this card before the host's copy of
    /// the item is here. A synthetic item (the host's transfer measurements) is zeros of its
    /// size.
    pub(crate) async fn held(&self, id: DataId, deadline: Instant) -> Option<Box<[u32]>> {
        loop {
            if let DataId::Synthetic { .. } = id {
                return Some(self.read_local(id));
            }
            if let Some(d) = self.memory.lock().expect("memory lock").item_words(id) {
                return Some(d.into());
            }
            if Instant::now() >= deadline {
                return None;
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// An item from this card's memory, or over the G-bus from the card that holds it, with
    /// the model time it is ready here.
    pub(crate) async fn get(&self, id: DataId) -> Option<(Arc<[u32]>, u64)> {
        let now = now_ns();
        if let Some(d) = self.memory.lock().expect("memory lock").item(id) {
            return Some((d, now));
        }
        let owner = self.memory.lock().expect("memory lock").owner(id)?;
        self.fetch_remote(id, owner, now)
            .await
            .map(|(d, t)| (Arc::from(d), t))
    }

    /// Data this card's shared memory holds; a synthetic item (the host's transfer
    /// measurements) is zeros of its size.
    pub(crate) fn read_local(&self, id: DataId) -> Box<[u32]> {
        match id {
            DataId::Synthetic { bytes } => {
                vec![0u32; (bytes as usize).div_ceil(4)].into_boxed_slice()
            }
            _ => self
                .memory
                .lock()
                .expect("memory lock")
                .item_words(id)
                .map(Box::from)
                .unwrap_or_default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use fabric::model::ModelParams;

    use super::*;

    #[test]
    fn dma_costs_nothing_when_links_are_not_delayed() {
        let s = Serving::default();
        let model = Model::new(ModelParams::default());
        assert_eq!(s.dma_done(&model, 1 << 20, 5_000), 0);
        assert_eq!(s.dma_done(&model, 1 << 20, 0), 0);
    }

    #[test]
    fn dma_transfers_queue_on_the_card_bus() {
        let s = Serving::default();
        let model = Model::paper();
        let d = model.dma_ns(2000);
        // 100 us setup + 2000 bytes at 20 bytes/us.
        assert_eq!(d, 200_000);
        let first = s.dma_done(&model, 2000, 1_000);
        assert_eq!(first, 1_000 + d);
        // Ready before the bus is free: waits for the first transfer.
        assert_eq!(s.dma_done(&model, 2000, 1_500), first + d);
        // Ready after the bus is free: starts when ready.
        let late = first + 10 * d;
        assert_eq!(s.dma_done(&model, 2000, late), late + d);
    }

    #[test]
    fn served_bytes_add_up() {
        let s = Serving::default();
        s.count_served(10);
        s.count_served(32);
        assert_eq!(s.bytes_served.load(Ordering::Relaxed), 42);
    }
}
