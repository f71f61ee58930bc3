//! The delay model: how long the paper's hardware took to move data, applied to real frames.
//!
//! Serial links (the `paper` link model) follow the paper's measurement: an 84-byte packet
//! with no other traffic takes `T(us) = 310 + 234 d_row + 300 d_col` to cross the mesh. We
//! read that as a fixed 310 us of software overhead per message plus, per link crossed,
//! 234 us along a column (a row step) or 300 us along a row (a column step); a packet larger
//! than 84 bytes adds its extra bytes at the T800 link's rate. Bulk data over serial links
//! travels in 1 KB packets holding 640 bytes of data each, store-and-forward at every hop,
//! so a long message pipelines through the mesh and each link is busy for one packet time
//! per packet.
//!
//! DMA and G-bus timings are not given in the paper's text; the defaults below are
//! assumptions, stated here and kept in the topology file so an experiment can change them:
//!
//! | parameter | default | why |
//! |---|---|---|
//! | `dma_setup_us` | 100 | the fork node's software preparation before a DMA ("invokes DMA transfer immediately after its preparation") |
//! | `dma_bytes_per_us` | 20 | a 64-bit DMA bus between 1991 memories: tens of MB/s |
//! | `gbus_setup_us` | 5 | bus arbitration |
//! | `gbus_bytes_per_us` | 84 | the paper: "the transfer rate is up to 84MB/sec" |
//! | `gbus_count` | 2 | the paper: "2 independent busses called G-bus", round-robin arbitration (1 to [`MAX_GBUSES`]) |
//! | `link_bytes_per_us` | 1.74 | a T800 link at 20 Mbit/s moves about 1.74 MB/s of data |
//!
//! `time_scale` multiplies every modelled delay: a CPU thousands of times faster than a T800
//! renders so quickly that the paper's ratio of communication to computation needs the link
//! times scaled down (a scale below 1) or the experiment runs at the paper's real times (1).

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LinkModelKind {
    /// No added delay: the fabric runs as fast as the machine allows.
    #[default]
    None,
    /// The paper's measured timings.
    Paper,
}

/// A link model name that is neither `none` nor `paper`.
#[derive(Debug, thiserror::Error)]
#[error("unknown link model {0:?} (none or paper)")]
pub struct UnknownLinkModel(pub String);

impl std::str::FromStr for LinkModelKind {
    type Err = UnknownLinkModel;
    fn from_str(s: &str) -> Result<Self, UnknownLinkModel> {
        match s {
            "none" => Ok(LinkModelKind::None),
            "paper" => Ok(LinkModelKind::Paper),
            o => Err(UnknownLinkModel(o.to_string())),
        }
    }
}

/// A model parameter out of its range (the value as the file gave it, printed).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ModelError {
    #[error("model.{name} must be a positive number, not {value}")]
    NotPositive { name: &'static str, value: String },
    #[error("model.{name} must be a number of at least 0, not {value}")]
    Negative { name: &'static str, value: String },
    #[error("model.{name} must be at most {most}, not {value}")]
    TooLarge {
        name: &'static str,
        value: String,
        most: String,
    },
    #[error("model.packet_data_bytes must be between 1 and packet_bytes")]
    PacketData,
    #[error("model.gbus_count must be 1 to {MAX_GBUSES}, not {0}")]
    GbusCount(u32),
}

/// The largest time scale a model may have: a million times the paper's delays (beyond
/// about 1e10 a transfer's nanoseconds overflow, and the delays silently vanished).
pub const MOST_TIME_SCALE: f64 = 1e6;

/// The most G-buses a model may have. The paper's machine had two; every transfer looks at
/// each bus for the one free first, and each bus is a slot of memory on every fork node, so
/// a count in the billions (a typing slip) would take the memory and stall every transfer.
pub const MAX_GBUSES: u32 = 64;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelParams {
    pub link: LinkModelKind,
    pub time_scale: f64,
    pub base_us: f64,
    pub row_hop_us: f64,
    pub col_hop_us: f64,
    pub reference_bytes: u32,
    pub link_bytes_per_us: f64,
    pub packet_bytes: u32,
    pub packet_data_bytes: u32,
    pub dma_setup_us: f64,
    pub dma_bytes_per_us: f64,
    pub gbus_setup_us: f64,
    pub gbus_bytes_per_us: f64,
    pub gbus_count: u32,
}

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams {
            link: LinkModelKind::None,
            time_scale: 1.0,
            base_us: 310.0,
            row_hop_us: 234.0,
            col_hop_us: 300.0,
            reference_bytes: 84,
            link_bytes_per_us: 1.74,
            packet_bytes: 1024,
            packet_data_bytes: 640,
            dma_setup_us: 100.0,
            dma_bytes_per_us: 20.0,
            gbus_setup_us: 5.0,
            gbus_bytes_per_us: 84.0,
            gbus_count: 2,
        }
    }
}

impl ModelParams {
    pub fn check(&self) -> Result<(), ModelError> {
        let pos = [
            ("time_scale", self.time_scale),
            ("link_bytes_per_us", self.link_bytes_per_us),
            ("dma_bytes_per_us", self.dma_bytes_per_us),
            ("gbus_bytes_per_us", self.gbus_bytes_per_us),
        ];
        if self.time_scale > MOST_TIME_SCALE {
            return Err(ModelError::TooLarge {
                name: "time_scale",
                value: format!("{:?}", self.time_scale),
                most: MOST_TIME_SCALE.to_string(),
            });
        }
        for (name, v) in pos {
            if !(v.is_finite() && v > 0.0) {
                return Err(ModelError::NotPositive {
                    name,
                    value: v.to_string(),
                });
            }
        }
        let nonneg = [
            ("base_us", self.base_us),
            ("row_hop_us", self.row_hop_us),
            ("col_hop_us", self.col_hop_us),
            ("dma_setup_us", self.dma_setup_us),
            ("gbus_setup_us", self.gbus_setup_us),
        ];
        for (name, v) in nonneg {
            if !(v.is_finite() && v >= 0.0) {
                return Err(ModelError::Negative {
                    name,
                    value: v.to_string(),
                });
            }
        }
        if self.packet_data_bytes == 0 || self.packet_data_bytes > self.packet_bytes {
            return Err(ModelError::PacketData);
        }
        if self.gbus_count == 0 || self.gbus_count > MAX_GBUSES {
            return Err(ModelError::GbusCount(self.gbus_count));
        }
        Ok(())
    }
}

/// The model in the units the runtime uses (nanoseconds, scaled).
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    pub params: ModelParams,
}

impl Model {
    pub fn new(params: ModelParams) -> Model {
        Model { params }
    }

    /// The paper's serial-link model with every other parameter at its default: what the
    /// experiments and the unit tests of the models built on it start from.
    pub fn paper() -> Model {
        Model::new(ModelParams {
            link: LinkModelKind::Paper,
            ..ModelParams::default()
        })
    }

    pub fn links_delayed(&self) -> bool {
        self.params.link == LinkModelKind::Paper
    }

    fn ns(&self, us: f64) -> u64 {
        (us * 1000.0 * self.params.time_scale).round().max(0.0) as u64
    }

    /// Software overhead paid once per message sent over serial links.
    pub fn base_ns(&self) -> u64 {
        if self.links_delayed() {
            self.ns(self.params.base_us)
        } else {
            0
        }
    }

    /// How a message of `wire_bytes` crosses serial links: (packets, bytes per packet).
    /// A message that fits one paper packet travels as it is; longer ones in 1 KB packets of
    /// 640 data bytes.
    pub fn packets(&self, wire_bytes: usize) -> (u64, u32) {
        let p = &self.params;
        if wire_bytes <= p.packet_bytes as usize {
            (1, wire_bytes as u32)
        } else {
            (
                wire_bytes.div_ceil(p.packet_data_bytes as usize) as u64,
                p.packet_bytes,
            )
        }
    }

    /// Time for one packet of `bytes` to cross one link.
    pub fn hop_ns(&self, vertical: bool, bytes: u32) -> u64 {
        if !self.links_delayed() {
            return 0;
        }
        let p = &self.params;
        let reference = if vertical { p.row_hop_us } else { p.col_hop_us };
        let extra = (bytes as f64 - p.reference_bytes as f64) / p.link_bytes_per_us;
        self.ns((reference + extra).max(0.0))
    }

    /// A DMA transfer of `bytes` between a fork node's shared memory and a render node.
    pub fn dma_ns(&self, bytes: u64) -> u64 {
        if !self.links_delayed() {
            return 0;
        }
        self.ns(self.params.dma_setup_us + bytes as f64 / self.params.dma_bytes_per_us)
    }

    /// One G-bus transfer of `bytes` between two cards' shared memories.
    pub fn gbus_ns(&self, bytes: u64) -> u64 {
        if !self.links_delayed() {
            return 0;
        }
        self.ns(self.params.gbus_setup_us + bytes as f64 / self.params.gbus_bytes_per_us)
    }

    /// The paper's formula for an 84-byte packet, in ns, for comparison with measurements.
    pub fn formula_ns(&self, d_row: u32, d_col: u32) -> u64 {
        let p = &self.params;
        self.ns(p.base_us + p.row_hop_us * d_row as f64 + p.col_hop_us * d_col as f64)
    }
}

/// The model clock of one direction of one link: when it is next free. Frames are stamped
/// with model times as they cross it; the actual sending is not slowed, so real forwarding
/// costs hide inside the modelled ones instead of adding to them (deadline accounting).
#[derive(Clone, Copy, Debug, Default)]
pub struct LinkClock {
    free_at: u64,
}

impl LinkClock {
    /// Advances the clock for a message whose first and last packets are ready (at this end of
    /// the link) at `first` and `last`, in `packets` packets of `hop` each. Returns when the
    /// first and last packets are ready at the other end.
    pub fn cross(&mut self, first: u64, last: u64, packets: u64, hop: u64) -> (u64, u64) {
        let start = first.max(self.free_at);
        let first_done = start + hop;
        let last_done = (first_done + hop * packets.saturating_sub(1)).max(last + hop);
        self.free_at = last_done;
        (first_done, last_done)
    }
}

/// Several identical buses shared round-robin: a transfer takes the one free first.
#[derive(Clone, Debug)]
pub struct Buses {
    free_at: Vec<u64>,
}

impl Buses {
    pub fn new(count: u32) -> Buses {
        Buses {
            free_at: vec![0; count.max(1) as usize],
        }
    }

    /// Books a transfer of `duration` ready at `ready`; returns its completion time.
    pub fn book(&mut self, ready: u64, duration: u64) -> u64 {
        let (i, _) = self
            .free_at
            .iter()
            .enumerate()
            .min_by_key(|&(i, &t)| (t.max(ready), i))
            .expect("at least one bus");
        let done = self.free_at[i].max(ready) + duration;
        self.free_at[i] = done;
        done
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// No G-bus, or billions of them (a file's typing slip, which took 32 GB on every fork
    /// node), is refused with the count.
    #[test]
    fn gbus_counts_outside_one_to_the_most_are_refused() {
        for (count, ok) in [
            (0, false),
            (1, true),
            (MAX_GBUSES, true),
            (MAX_GBUSES + 1, false),
            (4_000_000_000, false),
        ] {
            let p = ModelParams {
                gbus_count: count,
                ..ModelParams::default()
            };
            match p.check() {
                Ok(()) => assert!(ok, "{count} taken"),
                Err(e) => {
                    assert!(!ok, "{count}: {e}");
                    assert_eq!(
                        e.to_string(),
                        format!("model.gbus_count must be 1 to 64, not {count}")
                    );
                }
            }
        }
    }

    /// A time scale whose delays would overflow the clock (and vanish) is refused.
    #[test]
    fn a_time_scale_beyond_the_most_is_refused() {
        let p = |time_scale| ModelParams {
            time_scale,
            ..ModelParams::default()
        };
        assert!(p(MOST_TIME_SCALE).check().is_ok());
        let e = p(1e300).check().unwrap_err();
        assert_eq!(
            e.to_string(),
            "model.time_scale must be at most 1000000, not 1e300"
        );
    }

    #[test]
    fn formula_decomposes_into_hops() {
        let m = Model::paper();
        // 2 row steps and 3 column steps of an 84-byte packet.
        let total = m.base_ns() + 2 * m.hop_ns(true, 84) + 3 * m.hop_ns(false, 84);
        assert_eq!(total, m.formula_ns(2, 3));
        assert_eq!(m.formula_ns(0, 1), 610_000);
    }

    #[test]
    fn long_messages_pipeline() {
        let m = Model::paper();
        let (n, size) = m.packets(6400 + 40);
        assert_eq!((n, size), (11, 1024));
        let hop = m.hop_ns(false, size);
        // Over 3 links in a row, the last packet arrives after (n + 3 - 1) packet times.
        let mut links = [LinkClock::default(); 3];
        let (mut first, mut last) = (0, 0);
        for l in &mut links {
            (first, last) = l.cross(first, last, n, hop);
        }
        assert_eq!(first, 3 * hop);
        assert_eq!(last, (n + 2) * hop);
    }

    #[test]
    fn busy_link_queues_the_next_message() {
        let mut l = LinkClock::default();
        assert_eq!(l.cross(0, 0, 1, 10), (10, 10));
        assert_eq!(l.cross(0, 0, 1, 10), (20, 20));
        assert_eq!(l.cross(100, 100, 1, 10), (110, 110));
    }

    #[test]
    fn two_buses_take_turns() {
        let mut b = Buses::new(2);
        assert_eq!(b.book(0, 10), 10);
        assert_eq!(b.book(0, 10), 10);
        assert_eq!(b.book(0, 10), 20);
    }

    #[test]
    fn none_adds_nothing_and_scale_multiplies() {
        let none = Model::new(ModelParams::default());
        assert_eq!(
            none.hop_ns(true, 1024) + none.base_ns() + none.dma_ns(1 << 20),
            0
        );
        let half = Model::new(ModelParams {
            link: LinkModelKind::Paper,
            time_scale: 0.5,
            ..ModelParams::default()
        });
        assert_eq!(half.formula_ns(0, 1), 305_000);
    }
}
