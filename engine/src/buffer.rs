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

/// Freed blocks below this size stay with the process for reuse (see [`keep_freed_memory`]).
pub const KEEP_FREED_BELOW_BYTES: usize = 32 << 20;

/// Free memory the C allocator may hold at the top of a heap before returning it to the OS.
pub const TRIM_ABOVE_BYTES: usize = 256 << 20;

/// Lets the C allocator keep freed blocks for reuse instead of returning them to the OS at once
/// (glibc only; elsewhere nothing happens). Returns whether the settings were applied.
///
/// glibc serves blocks above a threshold from fresh mappings and returns the top of a heap to
/// the OS once more than twice that threshold is free there; the threshold starts at 128 KiB
/// and follows the largest block freed. An operator that allocates a few megabytes of levels
/// or intermediates per call therefore gets pages the kernel must map and zero again on every
/// call: one fault per 4 KiB, about 15 % of an ORB call on a 1080p image. This fixes the
/// threshold at [`KEEP_FREED_BELOW_BYTES`] (larger blocks are still mapped and unmapped, with
/// huge pages, see [`zeroed`]) and trims a heap only when more than [`TRIM_ABOVE_BYTES`] of it
/// is free, so the memory of one frame is reused by the next. The cost is resident memory:
/// what a run freed stays mapped, up to that bound per heap. The CLI calls it once at start
/// (streaming runs still trim once per window); benchmarks call it too, to measure what the
/// CLI runs. The Python module does not: it would change the allocator of the user's whole
/// process. glibc refuses an mmap threshold above half its heap size (32 MiB on 64-bit).
#[allow(unsafe_code)] // two allocator tunables; see the SAFETY comments
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes allocator tunables; it is safe to call at any time.
        let mmap = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, KEEP_FREED_BELOW_BYTES as i32) };
        // SAFETY: as above.
        let trim = unsafe { libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_ABOVE_BYTES as i32) };
        mmap == 1 && trim == 1
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// `len` default (zero) samples; large buffers are advised to use huge pages before any is
/// written. Use for output images and tables that the caller then overwrites.
pub fn zeroed<T: Clone + Default>(len: usize) -> Vec<T> {
    // `vec![zero; n]` of a primitive comes from `calloc`: blocks above the mmap threshold are
    // fresh mappings that nothing has touched yet; smaller ones reused from a heap are cleared
    // by `calloc` itself.
    let buffer = vec![T::default(); len];
    advise_huge_pages(&buffer);
    buffer
}

/// `len` samples computed band by band in parallel: `fill(band_index, band)` receives each
/// `band_len`-sample chunk in order of index (the last may be shorter) and must set every sample.
///
/// Each band is zeroed just before `fill` sees it, while it is in cache, instead of zeroing the
/// whole buffer up front on one thread: a `calloc` of a block the allocator reuses is a
/// `memset` as long as a light kernel (a 2×2 mean reads 4 bytes per byte it writes). Large
/// buffers are advised to use huge pages, as in [`zeroed`]. The result depends only on `fill`,
/// never on the thread count.
pub fn par_filled<T, F>(len: usize, band_len: usize, fill: F) -> Vec<T>
where
    T: Copy + Default + Send + Sync,
    F: Fn(usize, &mut [T]) + Sync + Send,
{
    use rayon::prelude::*;
    let mut buffer: Vec<T> = Vec::with_capacity(len);
    let spare = &mut buffer.spare_capacity_mut()[..len];
    advise_huge_pages(spare);
    spare
        .par_chunks_mut(band_len.max(1))
        .enumerate()
        .for_each(|(band, chunk)| {
            chunk.fill(std::mem::MaybeUninit::new(T::default()));
            fill(band, assume_init_mut(chunk));
        });
    set_len_after_fill(&mut buffer, len);
    buffer
}

#[allow(unsafe_code)] // a cast of initialised memory; see the SAFETY comment
fn assume_init_mut<T>(chunk: &mut [std::mem::MaybeUninit<T>]) -> &mut [T] {
    // SAFETY: only called on chunks whose every element was written just before (`fill` with
    // `MaybeUninit::new`), and `MaybeUninit<T>` has the layout of `T`.
    unsafe { &mut *(chunk as *mut [std::mem::MaybeUninit<T>] as *mut [T]) }
}

#[allow(unsafe_code)] // see the SAFETY comment
fn set_len_after_fill<T>(buffer: &mut Vec<T>, len: usize) {
    // SAFETY: `par_filled` initialised the first `len` elements of the spare capacity (the
    // parallel loop covers all of `spare[..len]` and writes every chunk before returning; a panic
    // in `fill` unwinds past this call, leaving the vector empty).
    unsafe { buffer.set_len(len) }
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
    fn par_filled_gives_what_fill_writes_for_any_thread_count() {
        for (len, band) in [
            (0usize, 4usize),
            (1, 4),
            (1000, 7),
            (HUGE_PAGE_MIN_BYTES / 2 + 3, 4096),
        ] {
            let expected: Vec<u16> = (0..len).map(|i| (i % 65_521) as u16).collect();
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let got = pool.install(|| {
                    par_filled::<u16, _>(len, band, |b, chunk| {
                        for (k, x) in chunk.iter_mut().enumerate() {
                            *x = ((b * band + k) % 65_521) as u16;
                        }
                    })
                });
                assert_eq!(got, expected, "len {len} band {band} threads {threads}");
            }
        }
    }

    #[test]
    fn par_filled_bands_start_zeroed() {
        let v: Vec<f32> = par_filled(100, 9, |b, chunk| {
            assert!(chunk.iter().all(|&x| x == 0.0));
            assert_eq!(chunk.len(), if b == 11 { 1 } else { 9 });
        });
        assert_eq!(v, vec![0.0; 100]);
    }

    #[test]
    fn kept_memory_comes_back_zeroed() {
        let applied = keep_freed_memory();
        if cfg!(not(all(target_os = "linux", target_env = "gnu"))) {
            assert!(!applied);
        } else if cfg!(target_pointer_width = "64") {
            assert!(applied, "glibc refused the allocator settings");
        }
        for _ in 0..3 {
            // A block the allocator now keeps and hands out again must still start at zero.
            let mut buffer: Vec<u8> = zeroed(6 << 20);
            assert!(buffer.iter().all(|&b| b == 0));
            buffer.fill(0xA5);
            drop(buffer);
        }
    }

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
