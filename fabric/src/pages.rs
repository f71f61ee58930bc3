//! Memory in large pages (2 MiB), for the walking forms rays read: a scene's in one process,
//! and those a render node transcodes for chunks it received.
//!
//! Random rays through a large scene meet a different node or leaf at nearly every step, and
//! with 4 KiB pages each step may also wait for a page walk: a processor's TLB maps a few
//! thousand pages (about 12 MiB of 4 KiB pages on the machines measured), against 76 MB of
//! walking form for a million triangles. On Linux, transparent huge pages are commonly given
//! only to memory that asks for them (`madvise` mode), which this memory does before it is
//! first written. Where the system gives none, it is ordinary memory, and rays walk it the
//! same: only the time to reach it changes, never an answer.
//!
//! Here and not in the renderer, which does no system calls; the roles put their
//! `renderer::region::Block`s over it.

use std::{alloc::Layout, ptr::NonNull};

/// The large page size these mappings are aligned to and advised for.
pub const LARGE_PAGE: usize = 2 << 20;

/// Zeroed words, aligned to a large page and asked to be mapped in large pages. It hands out
/// a pointer, not slices: its users decide who writes which words when (a block written once
/// before it is shared, or spans each written once by whoever takes them).
pub struct LargePages {
    ptr: NonNull<u32>,
    words: usize,
    /// None when nothing was allocated (no words).
    layout: Option<Layout>,
}

// SAFETY: the words are plain memory owned by this value; who reads and writes them through
// `as_ptr` is for its users to order (see the type's doc).
unsafe impl Send for LargePages {}
// SAFETY: as above.
unsafe impl Sync for LargePages {}

impl LargePages {
    /// `words` zeroed words, or `None` if that much memory cannot be had (the caller then
    /// keeps what it has). Zero words give an empty value.
    pub fn new(words: usize) -> Option<LargePages> {
        if words == 0 {
            return Some(LargePages::empty());
        }
        let layout = words
            .checked_mul(4)
            .map(|b| b.next_multiple_of(LARGE_PAGE))
            .and_then(|b| Layout::from_size_align(b, LARGE_PAGE).ok())?;
        let ptr = allocate(layout)?;
        Some(LargePages {
            ptr: ptr.cast(),
            words,
            layout: Some(layout),
        })
    }

    /// No words, and no mapping.
    pub fn empty() -> LargePages {
        LargePages {
            ptr: NonNull::dangling(),
            words: 0,
            layout: None,
        }
    }

    /// The first word. Valid for [`LargePages::len`] words while this value lives.
    pub fn as_ptr(&self) -> *mut u32 {
        self.ptr.as_ptr()
    }

    /// How many words.
    pub fn len(&self) -> usize {
        self.words
    }

    pub fn is_empty(&self) -> bool {
        self.words == 0
    }
}

impl Drop for LargePages {
    fn drop(&mut self) {
        if let Some(layout) = self.layout {
            release(self.ptr.cast(), layout);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_are_zeroed_aligned_to_a_large_page_and_writable() {
        let p = LargePages::new(1000).unwrap();
        assert_eq!(p.len(), 1000);
        assert!((p.as_ptr() as usize).is_multiple_of(LARGE_PAGE));
        // SAFETY: 1000 words from `as_ptr`, this test the only user.
        let words = unsafe { std::slice::from_raw_parts_mut(p.as_ptr(), p.len()) };
        assert!(words.iter().all(|&w| w == 0));
        words[999] = 7;
        assert_eq!(words[999], 7);
        assert!(LargePages::new(0).unwrap().is_empty());
        assert!(LargePages::new(usize::MAX).is_none());
    }
}
