//! Where a chunk's arrays live: in memory of its own, or in place inside a block that
//! something else owns and keeps unchanged (a fork node's card memory mapped read-only into
//! a render node). Rays read both the same way, as a slice, with no branch and no copy, so a
//! render node on the fork node's machine can walk a chunk where the fork node left it
//! instead of copying and transcoding it into memory of its own.
//!
//! The core does no I/O: what the block is (a mapping, a buffer) is the caller's business;
//! the core only needs its words and that they never move or change while it holds them.

use std::{ops::Deref, ptr::NonNull, sync::Arc};

use bytemuck::Pod;

/// A block of words that stays where it is, unchanged, for as long as it is held.
pub trait Block: Send + Sync {
    fn words(&self) -> &[u32];
}

/// Memory for a [`Block`], written once before it is shared.
pub trait BlockMut: Block {
    fn words_mut(&mut self) -> &mut [u32];
}

/// Places for parts of `lens` words one after the other in a block, each starting on a
/// cache line (16 words) as a card's segment holds them, so that a walking form's nodes lie
/// on whole lines: each part's words `start..end`, and the words the block needs.
pub(crate) fn line_places(lens: impl IntoIterator<Item = usize>) -> (Vec<(usize, usize)>, usize) {
    let mut end = 0usize;
    let places = lens
        .into_iter()
        .map(|len| {
            let start = end.next_multiple_of(16);
            end = start + len;
            (start, end)
        })
        .collect();
    (places, end)
}

enum Keep<T> {
    Empty,
    Own(Box<[T]>),
    Block(Arc<dyn Block>),
}

/// A slice of `T` that this value keeps alive: owned, or part of a shared [`Block`].
pub struct Region<T> {
    ptr: NonNull<T>,
    len: usize,
    keep: Keep<T>,
}

// SAFETY: a region is a shared slice of `T` (owned, or borrowed from a block that is
// `Send + Sync` and never changes); it hands out `&[T]` only, except `make_mut` which owns.
unsafe impl<T: Send + Sync> Send for Region<T> {}
// SAFETY: as above.
unsafe impl<T: Send + Sync> Sync for Region<T> {}

impl<T> Region<T> {
    /// An empty region (usable in statics).
    pub const fn empty() -> Region<T> {
        Region {
            ptr: NonNull::dangling(),
            len: 0,
            keep: Keep::Empty,
        }
    }

    pub fn own(items: Box<[T]>) -> Region<T> {
        let mut items = items;
        // A pointer into the box stays valid when the box (the pointer to it) moves.
        let ptr = NonNull::new(items.as_mut_ptr()).unwrap_or(NonNull::dangling());
        Region {
            ptr,
            len: items.len(),
            keep: Keep::Own(items),
        }
    }

    /// Whether the items live in a shared block rather than in memory of this region's own.
    pub fn is_shared(&self) -> bool {
        matches!(self.keep, Keep::Block(_))
    }
}

impl<T: Pod> Region<T> {
    /// Words `start..end` of `block` seen as `T`s, if that range lies in the block, is
    /// aligned for `T` and is a whole number of them.
    pub fn in_block(block: Arc<dyn Block>, start: usize, end: usize) -> Option<Region<T>> {
        let words = block.words().get(start..end)?;
        let items: &[T] = bytemuck::try_cast_slice(words).ok()?;
        let ptr = NonNull::from(items).cast::<T>();
        let len = items.len();
        Some(Region {
            ptr,
            len,
            keep: Keep::Block(block),
        })
    }
}

impl<T: Clone> Region<T> {
    /// The items, mutably: copied into memory of this region's own first if they are shared.
    pub fn make_mut(&mut self) -> &mut [T] {
        if !matches!(self.keep, Keep::Own(_)) {
            *self = Region::own(self[..].into());
        }
        match &mut self.keep {
            Keep::Own(items) => items,
            _ => unreachable!("made own above"),
        }
    }
}

impl<T> Deref for Region<T> {
    type Target = [T];

    #[inline(always)]
    fn deref(&self) -> &[T] {
        // SAFETY: `ptr` and `len` describe items owned by `keep` (a box whose heap memory
        // does not move with it, or a block that neither moves nor changes while held), or
        // nothing at all (dangling with length 0).
        unsafe { std::slice::from_raw_parts(self.ptr.as_ptr(), self.len) }
    }
}

impl<T: Clone> Clone for Region<T> {
    fn clone(&self) -> Region<T> {
        match &self.keep {
            Keep::Empty => Region::empty(),
            Keep::Own(items) => Region::own(items.clone()),
            Keep::Block(block) => Region {
                ptr: self.ptr,
                len: self.len,
                keep: Keep::Block(block.clone()),
            },
        }
    }
}

impl<T> Default for Region<T> {
    fn default() -> Region<T> {
        Region::empty()
    }
}

impl<T> From<Vec<T>> for Region<T> {
    fn from(v: Vec<T>) -> Region<T> {
        Region::own(v.into_boxed_slice())
    }
}

impl<T> From<Box<[T]>> for Region<T> {
    fn from(v: Box<[T]>) -> Region<T> {
        Region::own(v)
    }
}

impl<T: PartialEq> PartialEq for Region<T> {
    fn eq(&self, o: &Region<T>) -> bool {
        self[..] == o[..]
    }
}

impl<T: std::fmt::Debug> std::fmt::Debug for Region<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

/// Blocks for tests of what is read in place.
#[cfg(test)]
pub(crate) mod testing {
    use std::sync::Arc;

    use super::{Block, BlockMut};

    pub struct Words(pub Vec<u32>);
    impl Block for Words {
        fn words(&self) -> &[u32] {
            &self.0
        }
    }

    /// Sixteen words: one cache line.
    #[derive(Clone, Copy)]
    #[repr(C, align(64))]
    struct Line([u32; 16]);
    // SAFETY: `repr(C)` of sixteen `u32`s, 64 bytes, as aligned as it is long: no padding,
    // every bit pattern valid.
    unsafe impl bytemuck::Zeroable for Line {}
    // SAFETY: as above.
    unsafe impl bytemuck::Pod for Line {}

    /// `len` zeroed words starting on a cache line, as a card's segment or the host's large
    /// pages hold walking forms.
    pub struct Lines {
        lines: Vec<Line>,
        len: usize,
    }

    impl Lines {
        pub fn new(len: usize) -> Lines {
            Lines {
                lines: vec![Line([0; 16]); len.div_ceil(16)],
                len,
            }
        }
    }

    impl Block for Lines {
        fn words(&self) -> &[u32] {
            &bytemuck::cast_slice(&self.lines)[..self.len]
        }
    }

    impl BlockMut for Lines {
        fn words_mut(&mut self) -> &mut [u32] {
            &mut bytemuck::cast_slice_mut(&mut self.lines)[..self.len]
        }
    }

    /// `parts` one after the other in a block, each at a 64-byte aligned place as a card's
    /// segment holds them; the block and each part's words `start..end`.
    pub fn aligned_block(parts: &[&[u32]]) -> (Arc<dyn Block>, Vec<(usize, usize)>) {
        let (places, end) = super::line_places(parts.iter().map(|p| p.len()));
        let mut block = Lines::new(end);
        for (p, &(s, e)) in parts.iter().zip(&places) {
            block.words_mut()[s..e].copy_from_slice(p);
        }
        (Arc::new(block), places)
    }
}

#[cfg(test)]
mod tests {
    use super::testing::Words;
    use super::*;

    #[test]
    fn a_region_in_a_block_sees_its_words_and_keeps_the_block_alive() {
        let block: Arc<dyn Block> = Arc::new(Words((0..16).collect()));
        let r: Region<[u32; 2]> = Region::in_block(block.clone(), 4, 8).unwrap();
        assert_eq!(&r[..], &[[4, 5], [6, 7]]);
        assert!(r.is_shared());
        drop(block);
        let copy = r.clone();
        drop(r);
        assert_eq!(copy[1], [6, 7]);
    }

    #[test]
    fn ranges_outside_the_block_or_not_whole_items_are_refused() {
        let block: Arc<dyn Block> = Arc::new(Words(vec![0; 8]));
        assert!(Region::<u32>::in_block(block.clone(), 4, 9).is_none());
        assert!(Region::<u32>::in_block(block.clone(), 5, 4).is_none());
        assert!(Region::<[u32; 2]>::in_block(block, 0, 3).is_none());
    }

    #[test]
    fn make_mut_copies_a_shared_region_and_leaves_the_block_alone() {
        let block: Arc<dyn Block> = Arc::new(Words(vec![1; 4]));
        let mut r: Region<u32> = Region::in_block(block.clone(), 0, 4).unwrap();
        r.make_mut()[0] = 9;
        assert!(!r.is_shared());
        assert_eq!(&r[..], &[9, 1, 1, 1]);
        assert_eq!(block.words(), &[1, 1, 1, 1]);
        let mut own = Region::from(vec![3u32]);
        own.make_mut()[0] = 4;
        assert_eq!(&own[..], &[4]);
    }
}
