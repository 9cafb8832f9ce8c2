//! The allocation cap: the harness's global allocator refuses any single allocation above
//! [`MAX_ALLOCATION`] and any growth of live memory above [`MAX_LIVE`]. An input that asks
//! for that much has made hexcal allocate from an unchecked count or size, which is a bug:
//! the allocator writes the input being run to its artifact file and the message to stderr
//! (both without allocating), then aborts. Rust cannot unwind out of an allocator, so an
//! allocation failure ends the campaign; its artifact reproduces it (`replay`).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicPtr, AtomicUsize, Ordering};

/// Largest single allocation an input may cause (256 MiB).
pub const MAX_ALLOCATION: usize = 256 << 20;

/// Largest live heap while an input runs (2 GiB).
pub const MAX_LIVE: usize = 2 << 30;

/// The system allocator with the cap.
pub struct Capped;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static INPUT: AtomicPtr<u8> = AtomicPtr::new(std::ptr::null_mut());
static INPUT_LEN: AtomicUsize = AtomicUsize::new(0);
/// NUL-terminated path of the artifact to write on a refused allocation.
static ARTIFACT: AtomicPtr<u8> = AtomicPtr::new(std::ptr::null_mut());

/// Registers the input about to run and the artifact path (NUL-terminated) it goes to if
/// it breaks the cap; both must live until [`clear_input`].
pub fn set_input(input: &[u8], artifact: &std::ffi::CStr) {
    INPUT_LEN.store(input.len(), Ordering::SeqCst);
    INPUT.store(input.as_ptr().cast_mut(), Ordering::SeqCst);
    ARTIFACT.store(artifact.as_ptr().cast_mut().cast(), Ordering::SeqCst);
}

/// Forgets the registered input.
pub fn clear_input() {
    INPUT.store(std::ptr::null_mut(), Ordering::SeqCst);
    ARTIFACT.store(std::ptr::null_mut(), Ordering::SeqCst);
}

/// Writes `bytes` to file descriptor `fd`, ignoring failures (no allocation).
fn raw_write(fd: libc::c_int, bytes: &[u8]) {
    // SAFETY: a plain write(2) of a valid buffer.
    unsafe {
        libc::write(fd, bytes.as_ptr().cast(), bytes.len());
    }
}

/// Decimal digits of `n` into `buf`, without allocating.
fn digits(mut n: usize, buf: &mut [u8; 20]) -> &[u8] {
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 {
            return &buf[i..];
        }
    }
}

/// Reports a refused allocation of `size` bytes, saves the input, aborts.
fn refuse(size: usize) -> ! {
    let mut buf = [0u8; 20];
    raw_write(2, b"\nhexcal-fuzz: allocation of ");
    raw_write(2, digits(size, &mut buf));
    raw_write(2, b" bytes beyond the cap (single 256 MiB, live 2 GiB)");
    let input = INPUT.load(Ordering::SeqCst);
    let path = ARTIFACT.load(Ordering::SeqCst);
    if !input.is_null() && !path.is_null() {
        // SAFETY: set_input registered a live input slice and a NUL-terminated path.
        unsafe {
            let fd = libc::open(
                path.cast(),
                libc::O_WRONLY | libc::O_CREAT | libc::O_TRUNC,
                0o644,
            );
            if fd >= 0 {
                let len = INPUT_LEN.load(Ordering::SeqCst);
                raw_write(fd, std::slice::from_raw_parts(input, len));
                libc::close(fd);
            }
            raw_write(2, b"; input saved to ");
            raw_write(2, std::ffi::CStr::from_ptr(path.cast()).to_bytes());
        }
    }
    raw_write(2, b"\n");
    std::process::abort()
}

/// Counts `size` more live bytes, refusing what breaks the cap.
fn admit(size: usize) {
    if size > MAX_ALLOCATION || LIVE.fetch_add(size, Ordering::Relaxed) + size > MAX_LIVE {
        refuse(size);
    }
}

// SAFETY: every call is forwarded to the system allocator with the same layout; the counts
// only decide whether to abort.
unsafe impl GlobalAlloc for Capped {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        admit(layout.size());
        // SAFETY: forwarded unchanged.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        admit(layout.size());
        // SAFETY: forwarded unchanged.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        admit(new_size);
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        // SAFETY: forwarded unchanged.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn digits_without_allocation() {
        let mut buf = [0u8; 20];
        assert_eq!(super::digits(0, &mut buf), b"0");
        assert_eq!(super::digits(268_435_457, &mut buf), b"268435457");
        assert_eq!(
            super::digits(usize::MAX, &mut buf),
            usize::MAX.to_string().as_bytes()
        );
    }
}
