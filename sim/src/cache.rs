//! A render node's demand cache as the simulator keeps it: items within a byte budget, the
//! least recently used evicted first, as `render-node`'s `DemandCache` does (which
//! approximates exactly this order with per-slot stamps).

use std::collections::{BTreeMap, HashMap};

/// A chunk or a texture tile, by id.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Item {
    Chunk(u32),
    Tile(u32),
}

#[derive(Debug)]
pub struct Lru {
    budget: u64,
    used: u64,
    clock: u64,
    /// Resident items: their last use and bytes.
    resident: HashMap<Item, (u64, u64)>,
    /// Resident items by last use: the first is evicted next.
    by_use: BTreeMap<u64, Item>,
    pub evictions: u64,
}

impl Lru {
    pub fn new(budget: u64) -> Lru {
        Lru {
            budget,
            used: 0,
            clock: 0,
            resident: HashMap::new(),
            by_use: BTreeMap::new(),
            evictions: 0,
        }
    }

    /// Uses `item` if it is resident (true), making it the most recently used.
    pub fn touch(&mut self, item: Item) -> bool {
        let Some(entry) = self.resident.get_mut(&item) else {
            return false;
        };
        self.clock += 1;
        self.by_use.remove(&entry.0);
        entry.0 = self.clock;
        self.by_use.insert(self.clock, item);
        true
    }

    /// Puts a fetched item in, evicting the least recently used until it fits.
    pub fn insert(&mut self, item: Item, bytes: u64) {
        if self.touch(item) {
            return;
        }
        while self.used + bytes > self.budget {
            let Some((_, oldest)) = self.by_use.pop_first() else {
                break;
            };
            let (_, freed) = self
                .resident
                .remove(&oldest)
                .expect("indexed items are resident");
            self.used -= freed;
            self.evictions += 1;
        }
        self.clock += 1;
        self.resident.insert(item, (self.clock, bytes));
        self.by_use.insert(self.clock, item);
        self.used += bytes;
    }

    pub fn used(&self) -> u64 {
        self.used
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_the_least_recently_used_within_the_budget() {
        let mut c = Lru::new(30);
        c.insert(Item::Chunk(0), 10);
        c.insert(Item::Chunk(1), 10);
        c.insert(Item::Tile(0), 10);
        assert!(c.touch(Item::Chunk(0)));
        c.insert(Item::Chunk(2), 10);
        assert!(!c.touch(Item::Chunk(1)), "the oldest went");
        assert!(c.touch(Item::Chunk(0)) && c.touch(Item::Tile(0)) && c.touch(Item::Chunk(2)));
        assert_eq!((c.used(), c.evictions), (30, 1));
        c.insert(Item::Chunk(3), 25);
        assert_eq!((c.used(), c.evictions), (25, 4));
    }
}
