//! Large per-pixel buffers backed by transparent huge pages where the kernel gives them on
//! request (Linux, THP in its default `madvise` mode). A decoder writes hundreds of MiB of
//! fresh state and maps per camera and pose; with 4 KiB pages each first write of a page is
//! a fault (≈ 70 000 per decode of 1920×1200 with three projectors, about a fifth of its
//! time), with 2 MiB pages 512 times fewer (docs/design.md §6).

/// `len` copies of `value`, the kernel asked to back the buffer with huge pages before its
/// first write. Only a hint: where it is not taken (another system, THP off, a small buffer)
/// the vector is the same.
pub(super) fn filled<T: Clone>(value: T, len: usize) -> Vec<T> {
    collected(len, std::iter::repeat_n(value, len))
}

/// A vector of the items of `iter` (exactly `len` of them, as from a per-pixel map), backed
/// as [`filled`]'s.
pub(super) fn collected<T>(len: usize, iter: impl Iterator<Item = T>) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(len);
    advise_huge(v.as_mut_ptr().cast::<u8>(), len * std::mem::size_of::<T>());
    v.extend(iter);
    v
}

/// Buffers below one huge page gain nothing.
const HUGE_PAGE: usize = 2 << 20;

#[cfg(target_os = "linux")]
fn advise_huge(start: *mut u8, bytes: usize) {
    if bytes < HUGE_PAGE {
        return;
    }
    // SAFETY: sysconf has no preconditions.
    let page = usize::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }).unwrap_or(4096);
    // The whole pages inside the allocation: the advice never reaches beyond it.
    let begin = (start as usize).next_multiple_of(page);
    let end = (start as usize + bytes) / page * page;
    if end > begin {
        // SAFETY: [begin, end) lies inside this vector's own allocation; MADV_HUGEPAGE
        // changes only how the kernel backs those pages, never their contents. A refusal
        // (EINVAL without THP) leaves them as they were, so its result is not needed.
        unsafe {
            libc::madvise(begin as *mut libc::c_void, end - begin, libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge(_start: *mut u8, _bytes: usize) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huge_buffers_hold_what_plain_ones_do() {
        // Below and above one huge page, and an odd length (a partial last page).
        for len in [100, 3 << 20, (5 << 20) + 7] {
            let v = filled(7u16, len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 7));
            let w = collected(len, (0..len).map(|i| i as u32));
            assert!(w.iter().enumerate().all(|(i, &x)| x == i as u32));
        }
    }
}
