//! A scene's walking forms in large pages (2 MiB) when it is rendered in this process (and in
//! `bench rays`, which prepares as a render does).
//!
//! Random rays through a large scene meet a different node or leaf at nearly every step, and
//! with 4 KiB pages each step may also wait for a page walk: a processor's TLB maps a few
//! thousand pages (about 12 MiB of 4 KiB pages on the machines measured), against 76 MB of
//! walking form for a million triangles. Intel Embree's scenes get large pages (its process
//! held about 120 MiB of them while `bench/peers/embree.py` traced). On Linux, transparent
//! huge pages are commonly given only to memory that asks for them (`madvise` mode), which
//! this memory does before it is first written. Where the system gives none, it is ordinary
//! memory, and rays walk it the same: only the time to reach it changes, never an answer.

use std::{alloc::Layout, ptr::NonNull};

use renderer::{
    MemoryData, PrepareOptions, SceneDesc, SceneHeader,
    region::{Block, BlockMut},
};

const LARGE_PAGE: usize = 2 << 20;

/// Zeroed words, aligned to a large page and asked to be mapped in large pages.
pub struct LargePageWords {
    ptr: NonNull<u32>,
    words: usize,
    /// None when nothing was allocated (no words, or no memory to be had).
    layout: Option<Layout>,
}

// SAFETY: the words are plain memory owned by this value; `&self` hands out only `&[u32]`.
unsafe impl Send for LargePageWords {}
// SAFETY: as above.
unsafe impl Sync for LargePageWords {}

impl LargePageWords {
    /// `words` zeroed words, or none at all if that much memory cannot be had (the caller
    /// then keeps what it has).
    pub fn new(words: usize) -> LargePageWords {
        let empty = LargePageWords {
            ptr: NonNull::dangling(),
            words: 0,
            layout: None,
        };
        let Some(layout) = words
            .checked_mul(4)
            .filter(|&b| b > 0)
            .map(|b| b.next_multiple_of(LARGE_PAGE))
            .and_then(|b| Layout::from_size_align(b, LARGE_PAGE).ok())
        else {
            return empty;
        };
        let Some(ptr) = allocate(layout) else {
            return empty;
        };
        LargePageWords {
            ptr: ptr.cast(),
            words,
            layout: Some(layout),
        }
    }
}

/// Zeroed memory of `layout` (a whole number of large pages, aligned to one), its pages
/// asked to be large. On Linux a private anonymous mapping, whose pages the kernel zeroes as
/// they are first written: zeroing them here as well cost a pass over the whole block.
#[cfg(target_os = "linux")]
fn allocate(layout: Layout) -> Option<NonNull<u8>> {
    let bytes = layout.size();
    // Over-asked by an alignment, so that an aligned start lies within; the rest goes back.
    let len = bytes.checked_add(layout.align())?;
    // SAFETY: a fresh anonymous mapping; no existing memory is touched.
    let p = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            len,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
            -1,
            0,
        )
    };
    if p == libc::MAP_FAILED {
        return None;
    }
    let at = p as usize;
    let start = at.next_multiple_of(layout.align());
    let (head, tail) = (start - at, at + len - (start + bytes));
    // SAFETY: both ranges lie within the mapping just made and outside the part kept; the
    // advice covers exactly the part kept, before its first write, so that its pages are
    // faulted in large (a refusal leaves ordinary pages, which serve as well).
    unsafe {
        if head > 0 {
            libc::munmap(p, head);
        }
        if tail > 0 {
            libc::munmap((start + bytes) as *mut libc::c_void, tail);
        }
        libc::madvise(start as *mut libc::c_void, bytes, libc::MADV_HUGEPAGE);
    }
    NonNull::new(start as *mut u8)
}

#[cfg(target_os = "linux")]
fn release(ptr: NonNull<u8>, layout: Layout) {
    // SAFETY: `ptr` and the size are the part of a mapping `allocate` kept.
    unsafe { libc::munmap(ptr.as_ptr().cast(), layout.size()) };
}

/// Elsewhere, zeroed memory from the global allocator, in pages of the system's choosing.
#[cfg(not(target_os = "linux"))]
fn allocate(layout: Layout) -> Option<NonNull<u8>> {
    // SAFETY: the layout's size is not zero.
    NonNull::new(unsafe { std::alloc::alloc_zeroed(layout) })
}

#[cfg(not(target_os = "linux"))]
fn release(ptr: NonNull<u8>, layout: Layout) {
    // SAFETY: allocated by `allocate` with this very layout.
    unsafe { std::alloc::dealloc(ptr.as_ptr(), layout) };
}

impl Drop for LargePageWords {
    fn drop(&mut self) {
        if let Some(layout) = self.layout {
            release(self.ptr.cast(), layout);
        }
    }
}

impl Block for LargePageWords {
    fn words(&self) -> &[u32] {
        // SAFETY: `words` words from `ptr` were zeroed in `new` (or there are none) and stay
        // owned by this value; writes go through `&mut self` only.
        unsafe { std::slice::from_raw_parts(self.ptr.as_ptr(), self.words) }
    }
}

impl BlockMut for LargePageWords {
    fn words_mut(&mut self) -> &mut [u32] {
        // SAFETY: as in `words`, and `&mut self` makes this the only reference.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.as_ptr(), self.words) }
    }
}

/// Walking forms smaller than this stay in the heap: a TLB maps them whole in small pages,
/// and a large page would hold mostly nothing (the Cornell box's forms take 15 KB).
const WORTH_A_BLOCK: usize = 8 << 20;

/// Prepares a scene as [`renderer::prepare`] does, its walking forms built in one block of
/// large pages if they are large enough to gain from it (see the module doc).
pub fn prepare(desc: SceneDesc, opts: &PrepareOptions) -> (SceneHeader, MemoryData) {
    renderer::prepare_with(
        desc,
        opts,
        Some(&|words| {
            // An empty block: the forms are then built in the heap, as `prepare` builds them.
            let words = if words.saturating_mul(4) < WORTH_A_BLOCK {
                0
            } else {
                words
            };
            Box::new(LargePageWords::new(words))
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_are_zeroed_aligned_to_a_large_page_and_writable() {
        let mut b = LargePageWords::new(1000);
        assert_eq!(b.words().len(), 1000);
        assert!(b.words().iter().all(|&w| w == 0));
        assert!((b.words().as_ptr() as usize).is_multiple_of(LARGE_PAGE));
        b.words_mut()[999] = 7;
        assert_eq!(b.words()[999], 7);
        assert!(LargePageWords::new(0).words().is_empty());
        assert!(LargePageWords::new(usize::MAX).words().is_empty());
    }
}
