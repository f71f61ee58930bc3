//! A scene's walking forms in large pages (2 MiB; [`fabric::pages`] says why) when it is
//! rendered in this process (and in `bench rays`, which prepares as a render does). Intel
//! Embree's scenes get large pages too (its process held about 120 MiB of them while
//! `bench/peers/embree.py` traced).

use fabric::pages::LargePages;
use renderer::{
    MemoryData, PrepareOptions, SceneDesc, SceneHeader,
    region::{Block, BlockMut},
};

/// Zeroed words in large pages ([`fabric::pages`]), written once before they are shared.
pub struct LargePageWords(LargePages);

impl LargePageWords {
    /// `words` zeroed words, or none at all if that much memory cannot be had (the caller
    /// then keeps what it has).
    pub fn new(words: usize) -> LargePageWords {
        LargePageWords(LargePages::new(words).unwrap_or_else(LargePages::empty))
    }
}

impl Block for LargePageWords {
    fn words(&self) -> &[u32] {
        // SAFETY: the mapping's words were zeroed when made and stay owned by this value;
        // writes go through `&mut self` only.
        unsafe { std::slice::from_raw_parts(self.0.as_ptr(), self.0.len()) }
    }
}

impl BlockMut for LargePageWords {
    fn words_mut(&mut self) -> &mut [u32] {
        // SAFETY: as in `words`, and `&mut self` makes this the only reference.
        unsafe { std::slice::from_raw_parts_mut(self.0.as_ptr(), self.0.len()) }
    }
}

/// Walking forms smaller than this stay in the heap: a TLB maps them whole in small pages,
/// and a large page would hold mostly nothing (the Cornell box's forms take 15 KB).
const WORTH_A_BLOCK: usize = 8 << 20;

/// Prepares a scene as [`renderer::prepare`] does, the chunks' trees made one tree with the
/// top-level tree and built in one block of large pages if it is large enough to gain from
/// it (see the module doc; [`renderer::prepare_flat`]): a process that holds every chunk
/// walks the scene as one tree.
pub fn prepare(desc: SceneDesc, opts: &PrepareOptions) -> (SceneHeader, MemoryData) {
    // An empty block where the forms are too small: they are then built in the heap, as
    // `prepare` builds them.
    let make = |words: usize| -> Box<dyn BlockMut> {
        let words = if words.saturating_mul(4) < WORTH_A_BLOCK {
            0
        } else {
            words
        };
        Box::new(LargePageWords::new(words))
    };
    renderer::prepare_flat(desc, opts, &make)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_are_zeroed_aligned_to_a_large_page_and_writable() {
        let mut b = LargePageWords::new(1000);
        assert_eq!(b.words().len(), 1000);
        assert!(b.words().iter().all(|&w| w == 0));
        assert!((b.words().as_ptr() as usize).is_multiple_of(fabric::pages::LARGE_PAGE));
        b.words_mut()[999] = 7;
        assert_eq!(b.words()[999], 7);
        assert!(LargePageWords::new(0).words().is_empty());
        assert!(LargePageWords::new(usize::MAX).words().is_empty());
    }
}
