//! Sample buffers for large outputs, backed by transparent huge pages where the OS has them.
//!
//! A freshly allocated multi-megabyte buffer is mapped page by page as it is first written:
//! one page fault per 4 KiB. On a 3840×2160 f32 image (33 MB) that is 8 100 faults, which
//! cost more than the filtering itself, and allocations of 32 MB or more are returned to the
//! OS on every free by the C allocator, so they fault again on every call. Asking the kernel
//! for 2 MiB pages (`madvise(MADV_HUGEPAGE)`, what NumPy does for arrays of 4 MiB and more)
//! before the first write cuts the faults 512-fold. The advice never changes the contents.

/// Buffers at least this large are advised to use huge pages (NumPy's threshold).
pub const HUGE_PAGE_MIN_BYTES: usize = 4 << 20;

/// Size and alignment of a transparent huge page on x86-64 and aarch64 Linux.
#[cfg(target_os = "linux")]
const HUGE_PAGE_BYTES: usize = 2 << 20;

/// `len` default (zero) samples; large buffers are advised to use huge pages before any is
/// written. Use for output images and tables that the caller then overwrites.
pub fn zeroed<T: Clone + Default>(len: usize) -> Vec<T> {
    // `vec![zero; n]` of a primitive comes from `calloc`: large blocks are fresh mappings that
    // nothing has touched yet.
    let buffer = vec![T::default(); len];
    advise_huge_pages(&buffer);
    buffer
}

/// Advises the kernel to back the whole 2 MiB pages inside `buffer` with huge pages (Linux;
/// a no-op elsewhere and below [`HUGE_PAGE_MIN_BYTES`]).
pub fn advise_huge_pages<T>(buffer: &[T]) {
    #[cfg(target_os = "linux")]
    {
        let bytes = std::mem::size_of_val(buffer);
        if bytes < HUGE_PAGE_MIN_BYTES {
            return;
        }
        let start = buffer.as_ptr() as usize;
        let first = start.next_multiple_of(HUGE_PAGE_BYTES);
        let end = (start + bytes) & !(HUGE_PAGE_BYTES - 1);
        if end > first {
            advise(first, end - first);
        }
    }
}

#[cfg(target_os = "linux")]
#[allow(unsafe_code)] // one system call; see the SAFETY comment
fn advise(address: usize, length: usize) {
    // SAFETY: the range lies inside one live allocation (see `advise_huge_pages`), and
    // MADV_HUGEPAGE only changes how the kernel backs it: no memory is freed, moved or
    // modified. A failure (THP disabled) leaves everything as it was, so the result is ignored.
    unsafe {
        libc::madvise(address as *mut libc::c_void, length, libc::MADV_HUGEPAGE);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_buffers_are_zero_and_writable() {
        for len in [0usize, 1, 1000, HUGE_PAGE_MIN_BYTES / 4 + 12_345] {
            let mut v: Vec<f32> = zeroed(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
            for (i, x) in v.iter_mut().enumerate() {
                *x = i as f32;
            }
            assert!(v.iter().enumerate().all(|(i, &x)| x == i as f32));
        }
    }
}
