//! Shared by every fuzz target: an allocator that turns any single allocation above
//! [`LIMIT`] into an abort, so that a reader which trusts a size from its input before
//! checking it is reported by libFuzzer as a crash (with the input that caused it) instead
//! of being hidden by lazily mapped memory. Rust without a sanitizer has no malloc hooks,
//! so libFuzzer's own `-malloc_limit_mb` does not apply; `-rss_limit_mb` still does.
//!
//! This crate is tooling, not part of gs4city: its one `unsafe` block set is the
//! `GlobalAlloc` implementation that the trait requires.
use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;

pub mod checks;

/// The largest single allocation a reader may make on fuzz input (1 GiB).
pub const LIMIT: usize = 1 << 30;

/// The guarding allocator (forwards to the system allocator).
pub struct Guard;

#[cold]
fn too_big(size: usize) -> ! {
    // No allocation here: a fixed message on unbuffered stderr, then abort.
    let _ =
        std::io::stderr().write_all(b"fuzz guard: a single allocation above 1 GiB was requested\n");
    let _ = size;
    std::process::abort()
}

// SAFETY: every method forwards to `System` with the caller's arguments unchanged (so the
// caller's guarantees about `layout` and `ptr` carry over); the only addition is an abort
// before the call when the requested size exceeds `LIMIT`, which never returns.
unsafe impl GlobalAlloc for Guard {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > LIMIT {
            too_big(layout.size());
        }
        // SAFETY: forwarded unchanged (see the impl's note).
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > LIMIT {
            too_big(layout.size());
        }
        // SAFETY: forwarded unchanged (see the impl's note).
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged (see the impl's note).
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > LIMIT {
            too_big(new_size);
        }
        // SAFETY: forwarded unchanged (see the impl's note).
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Guard = Guard;
