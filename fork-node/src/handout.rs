//! Handing the card's render nodes what they need before they render: once this card's
//! memory is complete, the scene header (by DMA, each once), and for a batch job every
//! chunk and tile too. Whichever of the header, the last held item and the job arrives last
//! triggers it, so the handout remembers what it has already begun.

use std::{
    collections::HashSet,
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, Ordering},
    },
};

use fabric::clock::now_ns;
use protocol::{JobSpec, Message, NodeId, TransferMode, bytes_to_words};

use crate::ForkNode;

#[derive(Default)]
pub(crate) struct Handout {
    job: Mutex<Option<JobSpec>>,
    header_sent: AtomicBool,
    /// Render nodes given the header: this card's, and those of a lost fork node's card that
    /// this one serves now.
    header_sent_to: Mutex<HashSet<NodeId>>,
    batch_started: AtomicBool,
}

impl Handout {
    pub fn set_job(&self, job: JobSpec) {
        *self.job.lock().expect("job lock") = Some(job);
    }

    fn batch_job(&self) -> bool {
        matches!(self.job.lock().expect("job lock").as_ref(), Some(j) if j.transfer == TransferMode::Batch)
    }
}

impl ForkNode {
    /// Once this card's memory is complete: give the card's render nodes the header (by
    /// DMA), and, for a batch job, everything else too.
    pub(crate) fn maybe_ready(self: &Arc<ForkNode>) {
        let (complete, header, table) = {
            let m = self.memory.lock().expect("memory lock");
            (
                m.complete(),
                m.header_bytes.clone(),
                (m.chunk_owner.clone(), m.tile_owner.clone()),
            )
        };
        if !complete {
            return;
        }
        let Some(header) = header else { return };
        let f = &self.fabric;
        let card = self.card_render_nodes();
        if !self.handout.header_sent.swap(true, Ordering::SeqCst) {
            // Announced before the header, on the same connections, so that a render node
            // knows the segment before it starts rendering.
            self.publish_segment(&card);
        }
        // Render nodes this card serves that have no header from it yet: at first its own;
        // after another fork node is lost, that card's too (one that started already keeps
        // the header it has: the same scene).
        let new: Vec<NodeId> = {
            let mut sent = self.handout.header_sent_to.lock().expect("handout lock");
            self.served_render_nodes()
                .into_iter()
                .filter(|&r| sent.insert(r))
                .collect()
        };
        if !new.is_empty() {
            let msg = Message::Header {
                len: header.len() as u64,
                chunk_owner: table.0,
                tile_owner: table.1,
            };
            let words = bytes_to_words(&header);
            for r in new {
                let ready = self
                    .serving
                    .dma_done(f.model(), words.len() as u64 * 4, now_ns());
                if f.has_direct(r) {
                    let _ = f.send_direct(r, &msg, words.clone(), 0, ready);
                } else {
                    let _ = f.send(r, &msg, words.clone(), 0);
                }
            }
        }
        if self.handout.batch_job() && !self.handout.batch_started.swap(true, Ordering::SeqCst) {
            let me = self.clone();
            tokio::spawn(async move { me.send_batch(card).await });
        }
    }

    /// The render nodes of this fork node's card.
    pub(crate) fn card_render_nodes(&self) -> Vec<NodeId> {
        let t = self.fabric.topology();
        t.render_nodes()
            .into_iter()
            .filter(|&r| t.fork_of(r) == Some(self.fabric.me()))
            .collect()
    }

    /// The render nodes this fork node serves now: its card's, and those of lost fork
    /// nodes' cards that [`fabric::Topology::serving_fork`] gives it.
    pub(crate) fn served_render_nodes(&self) -> Vec<NodeId> {
        let f = &self.fabric;
        f.topology()
            .render_nodes()
            .into_iter()
            .filter(|&r| f.is_alive(r) && f.serving_fork(r) == Some(f.me()))
            .collect()
    }

    /// Batch transfer: every render node of the card gets every chunk and tile.
    async fn send_batch(self: Arc<ForkNode>, card: Vec<NodeId>) {
        let ids = self.memory.lock().expect("memory lock").all_ids();
        let f = &self.fabric;
        for id in &ids {
            let (data, ready) = match self.get(*id).await {
                Some(x) => x,
                None => return,
            };
            for &r in &card {
                let t = self
                    .serving
                    .dma_done(f.model(), data.len() as u64 * 4, ready);
                let _ = f.send_direct(
                    r,
                    &Message::Hold { id: *id },
                    data.to_vec().into_boxed_slice(),
                    0,
                    t,
                );
                self.serving.count_served(data.len() as u64 * 4);
            }
        }
        for &r in &card {
            let _ = f.send_direct(
                r,
                &Message::HoldDone {
                    count: ids.len() as u32,
                },
                Box::new([]),
                0,
                0,
            );
        }
    }
}
