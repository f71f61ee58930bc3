//! Large pages for the walking forms of chunks a render node holds in its own memory
//! (received over a socket, or preloaded), so that its rays walk them as fast as one
//! process walks its scene's: through the node's heap, in 4 KiB pages, random rays through
//! a million triangles ran 20 to 25% slower (`magg-host bench rays`, its render node cache
//! against in-process), and within 3 to 7% with the heap in large pages.
//!
//! Forms are placed one after another in blocks of [`BLOCK`] bytes ([`fabric::pages`]);
//! each chunk holds its span (a `Block` of its own), and a block goes back to the
//! system when its last span is dropped (its chunk evicted and freed). An evicted form's
//! words are not reused: a cache that evicts leaves dead spans in blocks that live ones still
//! hold. That waste is bounded ([`WASTE_LIMIT`]): past it, forms stay in the heap, as they
//! are where the cache is small (below [`MIN_BUDGET`]) and until it holds [`MIN_HELD`], so
//! that a node stays within its budget plus what the cluster allows it.

use std::sync::{
    Arc, Mutex,
    atomic::{AtomicUsize, Ordering},
};

use fabric::pages::{LARGE_PAGE, LargePages};
use renderer::{accel::WalkPlace, region::Block};

/// Bytes of one block: two large pages. A form that does not fit the rest of the current
/// block starts a new one, and the rest (under one form, about 200 KB for a chunk of 4,096
/// triangles) is lost: a few percent of a block.
pub const BLOCK: usize = 2 * LARGE_PAGE;

/// The least cache budget that places forms in large pages: a block would be too large a
/// part of a smaller one.
pub const MIN_BUDGET: u64 = 64 << 20;

/// What a cache holds before forms go to large pages: a TLB maps that much in small pages,
/// and a node that receives only a few chunks (reading the rest in place in a card's
/// memory) would otherwise fault in a 2 MiB page for a form of 200 KB.
pub const MIN_HELD: u64 = 8 << 20;

/// Most bytes of blocks that hold no live form (dead spans and the ends of blocks) before
/// forms go to the heap instead.
pub const WASTE_LIMIT: usize = 4 << 20;

/// Words a span starts on: a cache line, which keeps a form's nodes on whole lines.
const ALIGN_WORDS: usize = 16;

/// Bytes of blocks and of the live spans in them.
#[derive(Default)]
struct Counts {
    /// Of every block alive: its whole size once closed, what has been handed out of the
    /// current one.
    blocks: AtomicUsize,
    live: AtomicUsize,
}

impl Counts {
    fn waste(&self) -> usize {
        self.blocks
            .load(Ordering::Relaxed)
            .saturating_sub(self.live.load(Ordering::Relaxed))
    }
}

/// One block and what its counts hold for it.
struct PageBlock {
    pages: LargePages,
    /// Bytes of it in `Counts::blocks`.
    counted: AtomicUsize,
    counts: Arc<Counts>,
}

impl PageBlock {
    /// Counts `bytes` more of this block in `Counts::blocks`.
    fn count(&self, bytes: usize) {
        self.counted.fetch_add(bytes, Ordering::Relaxed);
        self.counts.blocks.fetch_add(bytes, Ordering::Relaxed);
    }

    /// Counts the whole block, once no more forms go into it.
    fn count_whole(&self) {
        let whole = self.pages.len() * 4;
        self.count(whole.saturating_sub(self.counted.load(Ordering::Relaxed)));
    }
}

impl Drop for PageBlock {
    fn drop(&mut self) {
        let bytes = self.counted.load(Ordering::Relaxed);
        self.counts.blocks.fetch_sub(bytes, Ordering::Relaxed);
    }
}

/// A form's words in a block: written once, before this exists, and only read after.
struct Span {
    block: Arc<PageBlock>,
    start: usize,
    len: usize,
}

impl Block for Span {
    fn words(&self) -> &[u32] {
        // SAFETY: words `start..start + len` lie in the block (see `FormArena::place`),
        // were written before this span was made and are never written again: no other span
        // covers them, and the arena hands out each range once.
        unsafe { std::slice::from_raw_parts(self.block.pages.as_ptr().add(self.start), self.len) }
    }
}

impl Drop for Span {
    fn drop(&mut self) {
        self.block
            .counts
            .live
            .fetch_sub(self.len * 4, Ordering::Relaxed);
    }
}

/// Places walking forms in large pages; see the module doc.
#[derive(Default)]
pub struct FormArena {
    /// The block being filled and the next free word in it.
    current: Mutex<Option<(Arc<PageBlock>, usize)>>,
    counts: Arc<Counts>,
}

impl FormArena {
    /// Words `len` long written by `write`, in large pages; `None` (nothing written) where
    /// no memory can be had or the waste is at its limit. The form is then best left where
    /// it is.
    pub fn place(&self, len: usize, write: impl FnOnce(&mut [u32])) -> Option<WalkPlace> {
        if len == 0 {
            return None;
        }
        let mut current = self.current.lock().expect("form arena lock");
        let fitting = current.as_ref().and_then(|(block, next)| {
            let start = next.next_multiple_of(ALIGN_WORDS);
            (start + len <= block.pages.len()).then_some(start)
        });
        let start = match fitting {
            Some(start) => start,
            None => {
                // The block being filled is done with: counted whole from now on, and gone
                // at once if no form lives in it any more.
                if let Some((old, _)) = current.take() {
                    old.count_whole();
                }
                if self.counts.waste() > WASTE_LIMIT {
                    return None;
                }
                let block = PageBlock {
                    pages: LargePages::new(len.max(BLOCK / 4))?,
                    counted: AtomicUsize::new(0),
                    counts: self.counts.clone(),
                };
                *current = Some((Arc::new(block), 0));
                0
            }
        };
        let (block, next) = current.as_mut().expect("a block being filled");
        // SAFETY: `start..start + len` lies within the block (checked above) and beyond every
        // range handed out of it before (`next` only grows, under the lock): no span reads
        // these words, and no one else writes them.
        let out = unsafe { std::slice::from_raw_parts_mut(block.pages.as_ptr().add(start), len) };
        write(out);
        block.count((start + len - *next) * 4);
        *next = start + len;
        self.counts.live.fetch_add(len * 4, Ordering::Relaxed);
        let block = block.clone();
        let span: Arc<dyn Block> = Arc::new(Span { block, start, len });
        Some(WalkPlace {
            block: span,
            start: 0,
            end: len,
        })
    }

    /// Bytes of blocks alive and of the forms alive in them.
    pub fn bytes(&self) -> (usize, usize) {
        (
            self.counts.blocks.load(Ordering::Relaxed),
            self.counts.live.load(Ordering::Relaxed),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB_WORDS: usize = (1 << 20) / 4;

    /// A form of `len` words that says where it is: word i holds `tag + i`.
    fn place(arena: &FormArena, len: usize, tag: u32) -> Option<WalkPlace> {
        arena.place(len, |out| {
            for (i, w) in out.iter_mut().enumerate() {
                *w = tag.wrapping_add(i as u32);
            }
        })
    }

    fn holds(p: &WalkPlace, len: usize, tag: u32) -> bool {
        let words = &p.block.words()[p.start..p.end];
        words.len() == len
            && words
                .iter()
                .enumerate()
                .all(|(i, &w)| w == tag.wrapping_add(i as u32))
    }

    #[test]
    fn forms_keep_their_words_on_cache_lines_and_blocks_go_back_with_their_last_form() {
        let arena = FormArena::default();
        let lens = [1, 17, 5000, 50_000, 300_000, 3];
        let places: Vec<_> = lens
            .iter()
            .enumerate()
            .map(|(i, &len)| place(&arena, len, 1000 * i as u32).unwrap())
            .collect();
        for (i, (p, &len)) in places.iter().zip(&lens).enumerate() {
            assert!(holds(p, len, 1000 * i as u32), "form {i} was overwritten");
            assert!(
                (p.block.words().as_ptr() as usize).is_multiple_of(64),
                "form {i} does not start on a cache line"
            );
        }
        let live: usize = lens.iter().sum::<usize>() * 4;
        let (blocks, counted_live) = arena.bytes();
        assert_eq!(counted_live, live);
        assert!(blocks >= live && blocks - live < 16 * 4 * lens.len() + BLOCK);
        drop(places);
        assert_eq!(arena.bytes().1, 0);
        // The block being filled stays the arena's until a new one replaces it; the others
        // went back with their last form, and so does that one once replaced.
        drop(place(&arena, BLOCK / 4, 7));
        assert_eq!(arena.bytes(), (BLOCK, 0), "a block stayed without forms");
        let last = place(&arena, 1, 8).unwrap();
        assert_eq!(arena.bytes(), (4, 4));
        drop(last);
        assert!(arena.place(0, |_| {}).is_none());
    }

    #[test]
    fn a_form_larger_than_a_block_gets_one_of_its_own() {
        let arena = FormArena::default();
        let small = place(&arena, 10, 1).unwrap();
        let big = place(&arena, BLOCK / 4 + 100, 2).unwrap();
        assert!(holds(&small, 10, 1));
        assert!(holds(&big, BLOCK / 4 + 100, 2));
    }

    #[test]
    fn past_the_waste_limit_forms_stay_where_they_are() {
        let arena = FormArena::default();
        // Four forms of 1 MiB fill a block; of each block's four, one lives on.
        let mut kept = Vec::new();
        let mut refused = None;
        for i in 0..64u32 {
            let Some(p) = place(&arena, MIB_WORDS, i) else {
                refused = Some(i);
                break;
            };
            if i % 4 == 0 {
                kept.push(p);
            }
            let (blocks, live) = arena.bytes();
            assert!(
                blocks - live <= WASTE_LIMIT + BLOCK,
                "waste {} after form {i}",
                blocks - live
            );
        }
        let refused = refused.expect("the arena never refused a form");
        assert!(refused > 4, "refused too early: form {refused}");
        for (k, p) in kept.iter().enumerate() {
            assert!(holds(p, MIB_WORDS, 4 * k as u32));
        }
        // Once the waste is gone with its blocks, forms are taken again.
        drop(kept);
        assert!(place(&arena, MIB_WORDS, 9).is_some());
    }
}
