//! The G-bus: two buses between the cards' shared memories, through which a fork node reads
//! items another card holds. The data comes from the card that holds it; the bus time comes
//! from the arbiter, the first fork node, which books every transfer on the bus free first
//! (the model's round-robin arbitration), so that all cards see one consistent bus. When the
//! arbiter is lost, the first live fork node arbitrates from then on.

use std::sync::{
    Mutex,
    atomic::{AtomicU64, Ordering},
};
use std::time::Duration;

use fabric::{Model, Route, model::Buses};
use protocol::{DataId, Message, NodeId};
use renderer::SceneHeader;

use crate::ForkNode;

const REQUEST_TIMEOUT: Duration = Duration::from_secs(120);

pub(crate) struct GBus {
    /// The buses' bookings; only the arbiter's are used.
    buses: Mutex<Buses>,
    /// Bytes this card read from other cards.
    pub bytes_read: AtomicU64,
}

impl GBus {
    pub fn new(count: u32) -> GBus {
        GBus {
            buses: Mutex::new(Buses::new(count)),
            bytes_read: AtomicU64::new(0),
        }
    }

    /// The arbiter's booking of a transfer of `bytes` ready at `ready_ns`: when it is done.
    pub fn book(&self, model: &Model, bytes: u64, ready_ns: u64) -> u64 {
        let duration = model.gbus_ns(bytes);
        self.buses
            .lock()
            .expect("bus lock")
            .book(ready_ns, duration)
    }
}

/// How many bytes item `id` puts on the bus, as the arbiter is told before the data itself
/// is here; a chunk this card has no header for counts as nothing.
pub(crate) fn transfer_bytes(id: DataId, scene: Option<&SceneHeader>) -> u32 {
    match id {
        DataId::Synthetic { bytes } => bytes,
        DataId::Chunk(c) => scene
            .and_then(|s| s.chunks.get(c as usize))
            .map_or(0, |c| c.byte_len),
        DataId::Tile(_) => (renderer::texture::TILE_TEXELS * 4) as u32,
    }
}

impl ForkNode {
    /// Fetches `id` from the fork node `owner` over the G-bus: the data from the owner, the
    /// bus time from the arbiter (the first fork node), both asked at once; the arbiter only
    /// when the link model adds delays.
    pub(crate) async fn fetch_remote(
        &self,
        id: DataId,
        owner: NodeId,
        ready_ns: u64,
    ) -> Option<(Box<[u32]>, u64)> {
        let f = &self.fabric;
        // The arbiter: the first fork node, or the first still alive once it is lost (the
        // bookings start afresh there; they are model time, never pixels).
        let master = f.first_live_fork().unwrap_or(f.me());
        let read = Message::RemoteRead { id, ready_ns };
        let data = f.request(owner, &read, Box::new([]), Route::Direct, REQUEST_TIMEOUT);
        let bytes = {
            let memory = self.memory.lock().expect("memory lock");
            transfer_bytes(id, memory.scene.as_deref())
        };
        let (data, done) = if !f.model().links_delayed() {
            // No model time to book: asking the arbiter would only cost two frames a read.
            (data.await, ready_ns)
        } else if master == f.me() {
            (
                data.await,
                self.gbus.book(f.model(), bytes as u64, ready_ns),
            )
        } else {
            let ask = Message::BusRequest { bytes, ready_ns };
            let grant = f.request(master, &ask, Box::new([]), Route::Direct, REQUEST_TIMEOUT);
            let (d, g) = tokio::join!(data, grant);
            let done = match g.ok().and_then(|g| g.message().ok()) {
                Some(Message::BusGrant { done_ns }) => done_ns,
                _ => ready_ns,
            };
            (d, done)
        };
        match data {
            Ok(frame) => {
                self.gbus
                    .bytes_read
                    .fetch_add(frame.data.len() as u64 * 4, Ordering::Relaxed);
                Some((frame.data, done))
            }
            Err(e) => {
                tracing::warn!(
                    "fork node {}: G-bus read of {id:?} from node {owner} failed: {e}",
                    f.me()
                );
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use fabric::model::ModelParams;

    use super::*;

    #[test]
    fn two_buses_carry_two_transfers_at_once_and_queue_the_third() {
        let model = Model::paper();
        let bus = GBus::new(2);
        // 5 us setup + 840 bytes at 84 bytes/us.
        let d = model.gbus_ns(840);
        assert_eq!(d, 15_000);
        assert_eq!(bus.book(&model, 840, 0), d);
        assert_eq!(bus.book(&model, 840, 0), d);
        assert_eq!(bus.book(&model, 840, 0), 2 * d);
        // A transfer ready after both buses are free waits for neither.
        assert_eq!(bus.book(&model, 840, 10 * d), 11 * d);
    }

    #[test]
    fn one_bus_serialises_everything() {
        let model = Model::paper();
        let bus = GBus::new(1);
        let d = model.gbus_ns(84);
        assert_eq!(bus.book(&model, 84, 100), 100 + d);
        assert_eq!(bus.book(&model, 84, 100), 100 + 2 * d);
    }

    #[test]
    fn bus_time_is_free_when_links_are_not_delayed() {
        let bus = GBus::new(2);
        let model = Model::new(ModelParams::default());
        assert_eq!(bus.book(&model, 1 << 20, 7), 7);
    }

    #[test]
    fn transfer_sizes_by_kind() {
        assert_eq!(transfer_bytes(DataId::Synthetic { bytes: 333 }, None), 333);
        let tile = (renderer::texture::TILE_TEXELS * 4) as u32;
        assert_eq!(transfer_bytes(DataId::Tile(9), None), tile);
        assert_eq!(transfer_bytes(DataId::Chunk(0), None), 0, "no header yet");
        let opts = renderer::PrepareOptions {
            chunk_triangles: 64,
        };
        let scene = renderer::prepare(renderer::demo::demo_scene(), &opts).0;
        let first = scene.chunks[0].byte_len;
        assert_eq!(transfer_bytes(DataId::Chunk(0), Some(&scene)), first);
        let past_the_end = scene.chunks.len() as u32;
        assert_eq!(transfer_bytes(DataId::Chunk(past_the_end), Some(&scene)), 0);
    }
}
