//! Large per-frame buffers kept from one frame for the next. Writing to freshly mapped
//! memory faults on every page, and prefiltering's filtered basis (70–250 MiB at 1080p)
//! spent a quarter of its preparation in those faults, frame after frame.

use std::sync::Mutex;

/// A few buffers of `T` kept for reuse: the most recently handed back.
pub(crate) struct Spare<T> {
    kept: Mutex<Vec<Vec<T>>>,
    /// How many are kept at most.
    slots: usize,
}

impl<T: Copy + Default> Spare<T> {
    /// One buffer kept: for what a frame needs once.
    pub(crate) const fn new() -> Self {
        Self::with_slots(1)
    }

    /// `slots` buffers kept: a downsampled frame needs its layers in two sizes at once
    /// (the reduced ones, then the upsampled ones).
    pub(crate) const fn with_slots(slots: usize) -> Self {
        Self {
            kept: Mutex::new(Vec::new()),
            slots,
        }
    }

    /// A buffer of `len` values. It is a kept one where one is large enough and not more
    /// than twice the size (a small frame does not take on a large frame's memory; that is
    /// released by later [`Spare::keep`]s), and then its values are whatever they were:
    /// callers overwrite every one.
    pub(crate) fn take(&self, len: usize) -> Vec<T> {
        // A poisoned lock only means another frame panicked while swapping: allocate anew.
        let found = self.kept.lock().ok().and_then(|mut kept| {
            let fitting = kept
                .iter()
                .enumerate()
                .filter(|(_, buffer)| (len..=2 * len).contains(&buffer.capacity()))
                .min_by_key(|(_, buffer)| buffer.capacity())
                .map(|(index, _)| index)?;
            Some(kept.swap_remove(fitting))
        });
        let mut buffer = found.unwrap_or_else(|| Vec::with_capacity(len));
        buffer.truncate(len);
        buffer.resize(len, T::default());
        buffer
    }

    /// Lets go of every kept buffer.
    pub(crate) fn clear(&self) {
        if let Ok(mut kept) = self.kept.lock() {
            *kept = Vec::new();
        }
    }

    /// Keeps `buffer` for a later [`Spare::take`], letting go of the least recently kept
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

    #[test]
    fn kept_buffers_are_reused_when_they_fit_and_released_two_frames_later() {
        let spare = Spare::<u16>::with_slots(2);
        let first = spare.take(1000);
        assert_eq!(first.len(), 1000);
        let address = first.as_ptr();
        spare.keep(first);
        let again = spare.take(800);
        assert_eq!((again.len(), again.as_ptr()), (800, address));
        spare.keep(again);
        // Far smaller: a fresh buffer; the large one stays kept for a while.
        let small = spare.take(100);
        assert_eq!(small.len(), 100);
        assert!(small.capacity() < 1000);
        let small_address = small.as_ptr();
        spare.keep(small);
        // Two sizes in one frame, as downsampling takes them: each finds its own.
        let (large, small) = (spare.take(900), spare.take(90));
        assert_eq!((large.as_ptr(), small.as_ptr()), (address, small_address));
        spare.keep(small);
        spare.keep(large);
        // Two newer keeps release the large one.
        spare.keep(spare.take(50));
        spare.keep(spare.take(40));
        let capacities = kept_capacities(&spare);
        assert!(
            capacities.iter().all(|&capacity| capacity < 900),
            "{capacities:?}"
        );
        // Larger than anything kept: fresh, zeroed.
        let large = spare.take(5000);
        assert!(large.len() == 5000 && large.iter().all(|&v| v == 0));
        // One slot: the next buffer kept replaces the last.
        let single = Spare::<u16>::new();
        single.keep(vec![0; 1000]);
        single.keep(vec![0; 10]);
        let capacities = kept_capacities(&single);
        assert_eq!(capacities, [10]);
        single.clear();
        assert!(single.kept.lock().unwrap().is_empty());
    }
}
