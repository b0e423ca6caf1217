//! Large per-frame buffers kept from one frame for the next. Writing to freshly mapped
//! memory faults on every page, and prefiltering's filtered basis (70–250 MiB at 1080p)
//! spent a quarter of its preparation in those faults, frame after frame. Those read all
//! over are kept on transparent huge pages.

use std::sync::Mutex;

use bytemuck::allocation::try_zeroed_vec;
use bytemuck::Zeroable;

use crate::error::{Error, Result, Sizing};

/// A few buffers of `T` kept for reuse: the most recently handed back.
pub(crate) struct Spare<T> {
    kept: Mutex<Vec<Vec<T>>>,
    /// How many are kept at most.
    slots: usize,
    /// Whether fresh buffers ask for transparent huge pages.
    huge_pages: bool,
    /// The settings that size the buffers, for the error when one cannot be allocated.
    sizing: Sizing,
}

impl<T: Zeroable + Copy> Spare<T> {
    /// One buffer kept: for what a frame needs once.
    pub(crate) const fn new(sizing: Sizing) -> Self {
        Self::with_slots(1, sizing)
    }

    /// `slots` buffers kept: a downsampled frame needs its layers in two sizes at once
    /// (the reduced ones, then the upsampled ones).
    pub(crate) const fn with_slots(slots: usize, sizing: Sizing) -> Self {
        Self::kept_in(slots, false, sizing)
    }

    /// One buffer kept, on transparent huge pages where the kernel grants them: for what
    /// rays read all over, a row or a block at a time (the filtered basis and its weights,
    /// the rectified map and the tables over it), where with 4 KiB pages nearly every read
    /// missed the TLB as well as the cache. Buffers read in order gain nothing, and
    /// faulting huge pages in stalls a fresh process's first frame more often: with every
    /// buffer on them, 6 of 16 first frames of `tree` took 400–650 ms against 2 of 16
    /// without (most take 250–350 ms).
    pub(crate) const fn on_huge_pages(sizing: Sizing) -> Self {
        Self::kept_in(1, true, sizing)
    }

    const fn kept_in(slots: usize, huge_pages: bool, sizing: Sizing) -> Self {
        Self {
            kept: Mutex::new(Vec::new()),
            slots,
            huge_pages,
            sizing,
        }
    }

    /// A buffer of `len` values. It is a kept one where one is large enough and not more
    /// than twice the size (a small frame does not take on a large frame's memory; that is
    /// released by later [`Spare::keep`]s), and then its values are whatever they were:
    /// callers overwrite every one.
    ///
    /// Where a fresh one cannot be allocated (after letting go of the kept ones), an error
    /// that names `what`, its size and the settings to lower, rather than the abort an
    /// allocation failure is in Rust: a host such as Blender would lose its unsaved work.
    pub(crate) fn try_take(&self, len: usize, what: impl FnOnce() -> String) -> Result<Vec<T>> {
        self.obtained(len)
            .ok_or_else(|| Error::out_of_memory(&what(), gib::<T>(len), self.sizing))
    }

    /// `len` values in a kept buffer that fits, else in a fresh one, letting go of the
    /// kept ones if the allocator refuses at first; `None` if it refuses again.
    fn obtained(&self, len: usize) -> Option<Vec<T>> {
        if let Some(mut kept) = self.kept_fitting(len) {
            kept.truncate(len);
            kept.resize(len, T::zeroed());
            return Some(kept);
        }
        // Zeroed by the allocator, not filled: it maps a large buffer afresh, and the
        // kernel zeroes each page as the pass that fills it first writes there, in
        // parallel. Filling it here wrote every page twice, the second time in this one
        // thread before any parallel pass (a frame's first buffers: about 150 MB at
        // 1080p).
        let mut fresh = try_zeroed_vec(len).ok().or_else(|| {
            self.clear();
            try_zeroed_vec(len).ok()
        })?;
        if self.huge_pages {
            advise_huge_pages(&mut fresh);
        }
        Some(fresh)
    }

    /// The smallest kept buffer that fits `len` values without more than doubling it.
    fn kept_fitting(&self, len: usize) -> Option<Vec<T>> {
        // A poisoned lock only means another frame panicked while swapping: allocate anew.
        self.kept.lock().ok().and_then(|mut kept| {
            let fitting = kept
                .iter()
                .enumerate()
                .filter(|(_, buffer)| (len..=2 * len).contains(&buffer.capacity()))
                .min_by_key(|(_, buffer)| buffer.capacity())
                .map(|(index, _)| index)?;
            Some(kept.swap_remove(fitting))
        })
    }

    /// Lets go of every kept buffer.
    pub(crate) fn clear(&self) {
        if let Ok(mut kept) = self.kept.lock() {
            *kept = Vec::new();
        }
    }

    /// Keeps `buffer` for a later [`Spare::try_take`], letting go of the least recently kept
    /// one beyond the slots: a large frame's memory is released as soon as as many smaller
    /// buffers have been kept.
    pub(crate) fn keep(&self, buffer: Vec<T>) {
        if buffer.capacity() == 0 {
            return;
        }
        if let Ok(mut kept) = self.kept.lock() {
            kept.insert(0, buffer);
            kept.truncate(self.slots);
        }
    }
}

/// The size of `len` values of `T`, in GiB.
fn gib<T>(len: usize) -> f64 {
    len as f64 * std::mem::size_of::<T>() as f64 / (1u64 << 30) as f64
}

/// The size of a transparent huge page on x86-64 and most arm64 kernels.
#[cfg(target_os = "linux")]
const HUGE_PAGE: usize = 2 << 20;

/// Asks the kernel to back the whole huge pages within `buffer`'s allocation with
/// transparent huge pages, before anything touches them ([`Spare::on_huge_pages`]).
fn advise_huge_pages<T>(buffer: &mut Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        let start = buffer.as_mut_ptr() as usize;
        let end = start + buffer.capacity() * std::mem::size_of::<T>();
        let (first, last) = (
            start.next_multiple_of(HUGE_PAGE),
            end / HUGE_PAGE * HUGE_PAGE,
        );
        if last > first {
            // SAFETY: the range lies within the buffer's allocation, which nothing else
            // uses; the advice changes how the kernel backs those pages, not what they hold.
            let refused = unsafe {
                libc::madvise(
                    first as *mut libc::c_void,
                    last - first,
                    libc::MADV_HUGEPAGE,
                )
            };
            // It is advice: a kernel without huge pages refuses it, and the buffer works
            // as well with small pages.
            let _ = refused;
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = buffer;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kept_capacities<T>(spare: &Spare<T>) -> Vec<usize> {
        spare
            .kept
            .lock()
            .unwrap()
            .iter()
            .map(Vec::capacity)
            .collect()
    }

    /// A buffer of `len` from `spare`, which tests always get.
    fn take<T: Zeroable + Copy>(spare: &Spare<T>, len: usize) -> Vec<T> {
        spare.try_take(len, String::new).unwrap()
    }

    #[test]
    fn kept_buffers_are_reused_when_they_fit_and_released_two_frames_later() {
        let spare = Spare::<u16>::with_slots(2, Sizing::Image);
        let first = take(&spare, 1000);
        assert_eq!(first.len(), 1000);
        let address = first.as_ptr();
        spare.keep(first);
        let again = take(&spare, 800);
        assert_eq!((again.len(), again.as_ptr()), (800, address));
        spare.keep(again);
        // Far smaller: a fresh buffer; the large one stays kept for a while.
        let small = take(&spare, 100);
        assert_eq!(small.len(), 100);
        assert!(small.capacity() < 1000);
        let small_address = small.as_ptr();
        spare.keep(small);
        // Two sizes in one frame, as downsampling takes them: each finds its own.
        let (large, small) = (take(&spare, 900), take(&spare, 90));
        assert_eq!((large.as_ptr(), small.as_ptr()), (address, small_address));
        spare.keep(small);
        spare.keep(large);
        // Two newer keeps release the large one.
        spare.keep(take(&spare, 50));
        spare.keep(take(&spare, 40));
        let capacities = kept_capacities(&spare);
        assert!(
            capacities.iter().all(|&capacity| capacity < 900),
            "{capacities:?}"
        );
        // Larger than anything kept: fresh, zeroed.
        let large = take(&spare, 5000);
        assert!(large.len() == 5000 && large.iter().all(|&v| v == 0));
        // One slot: the next buffer kept replaces the last.
        let single = Spare::<u16>::new(Sizing::Image);
        single.keep(vec![0; 1000]);
        single.keep(vec![0; 10]);
        let capacities = kept_capacities(&single);
        assert_eq!(capacities, [10]);
        single.clear();
        assert!(single.kept.lock().unwrap().is_empty());
    }

    /// Fresh buffers come zeroed from the allocator, whatever their size (a large one is
    /// mapped afresh, a small one may reuse freed memory), empty ones included; a kept one
    /// grown within its capacity is zeroed past its old length.
    #[test]
    fn fresh_buffers_come_zeroed() {
        let pairs = Spare::<(u64, f64)>::new(Sizing::Image);
        assert!(take(&pairs, 0).is_empty());
        for len in [1, 1000, 1 << 22] {
            let buffer = take(&pairs, len);
            assert_eq!(buffer.len(), len);
            assert!(buffer.iter().all(|&pair| pair == (0, 0.0)), "{len}");
            // Freed memory that a small buffer may be given next holds other values.
            drop(vec![(u64::MAX, f64::NAN); len]);
        }
        let bounds = Spare::<[f32; 2]>::on_huge_pages(Sizing::Rectified);
        let mut buffer = take(&bounds, 1000);
        assert!(buffer.iter().all(|&bound| bound == [0.0; 2]));
        buffer.fill([7.0; 2]);
        buffer.truncate(600);
        bounds.keep(buffer);
        let grown = take(&bounds, 900);
        assert!(grown[600..].iter().all(|&bound| bound == [0.0; 2]));
    }

    /// A buffer the allocator cannot give (4 PiB, more than any address space maps) is an
    /// error naming it, its size and the settings that size it, not an abort; the kept
    /// buffers are let go first, and taking smaller buffers goes on working.
    #[test]
    fn a_buffer_too_large_to_allocate_is_an_error_naming_it() {
        let spare = Spare::<f32>::new(Sizing::Rectified);
        spare.keep(vec![0.0; 1000]);
        let len = 1usize << 50;
        let error = spare
            .try_take(len, || "the test's buffer".to_string())
            .expect_err("4 PiB cannot be allocated");
        let message = error.to_string();
        assert!(
            matches!(&error, Error::InvalidInput { field, .. } if field == "render")
                && message.contains("the test's buffer needs 4194304.0 GiB")
                && message.contains("render.epipolar_slices"),
            "{message}"
        );
        assert!(kept_capacities(&spare).is_empty());
        let small = spare.try_take(800, String::new).expect("800 values");
        assert_eq!(small.len(), 800);
        spare.keep(small);
        assert_eq!(kept_capacities(&spare), [800]);
        assert_eq!(spare.try_take(700, String::new).unwrap().len(), 700);
        // An image-sized buffer names the image's settings.
        let image = Spare::<f32>::new(Sizing::Image);
        let error = image
            .try_take(len, || "the layers".to_string())
            .expect_err("4 PiB cannot be allocated");
        let message = error.to_string();
        assert!(
            matches!(&error, Error::InvalidInput { field, .. } if field == "camera")
                && message.contains("the layers needs 4194304.0 GiB")
                && message.contains("camera.width and camera.height, or render.supersampling"),
            "{message}"
        );
    }

    /// The kernel's flags for the mapping that holds `address`, from `/proc/self/smaps`.
    #[cfg(target_os = "linux")]
    fn mapping_flags(address: usize) -> Vec<String> {
        let smaps = std::fs::read_to_string("/proc/self/smaps").unwrap();
        let mut inside = false;
        for line in smaps.lines() {
            let range = line.split_whitespace().next().and_then(|field| {
                let (start, end) = field.split_once('-')?;
                Some(usize::from_str_radix(start, 16).ok()?..usize::from_str_radix(end, 16).ok()?)
            });
            if let Some(range) = range {
                inside = range.contains(&address);
            } else if let (true, Some(flags)) = (inside, line.strip_prefix("VmFlags:")) {
                return flags.split_whitespace().map(str::to_owned).collect();
            }
        }
        panic!("no mapping holds {address:#x}");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn fresh_buffers_of_whole_huge_pages_ask_for_them() {
        if !std::path::Path::new("/sys/kernel/mm/transparent_hugepage").exists() {
            eprintln!("skipped: this kernel has no transparent huge pages");
            return;
        }
        let spare = Spare::<u32>::on_huge_pages(Sizing::Rectified);
        let buffer = take(&spare, 3 * HUGE_PAGE / 4);
        let start = buffer.as_ptr() as usize;
        let inner = start.next_multiple_of(HUGE_PAGE);
        assert!(inner + HUGE_PAGE <= start + 3 * HUGE_PAGE);
        let flags = mapping_flags(inner);
        assert!(flags.iter().any(|flag| flag == "hg"), "{flags:?}");
        assert!(buffer.iter().all(|&value| value == 0));
    }
}
