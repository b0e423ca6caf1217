//! Large per-frame buffers kept from one frame for the next. Writing to freshly mapped
//! memory faults on every page, and prefiltering's filtered basis (70–250 MiB at 1080p)
//! spent a quarter of its preparation in those faults, frame after frame.

use std::sync::Mutex;

/// At most one buffer of `T` kept for reuse: the largest recently handed back.
pub(crate) struct Spare<T> {
    kept: Mutex<Vec<T>>,
}

impl<T: Copy + Default> Spare<T> {
    pub(crate) const fn new() -> Self {
        Self {
            kept: Mutex::new(Vec::new()),
        }
    }

    /// A buffer of `len` values. It is the kept one where that is large enough and not
    /// more than twice the size (so a small frame does not hold a large frame's memory),
    /// and then its values are whatever they were: callers overwrite every one.
    pub(crate) fn take(&self, len: usize) -> Vec<T> {
        // A poisoned lock only means another frame panicked while swapping: allocate anew.
        let kept = match self.kept.lock() {
            Ok(mut kept) => std::mem::take(&mut *kept),
            Err(_) => Vec::new(),
        };
        let mut buffer = if kept.capacity() >= len && kept.capacity() <= 2 * len {
            kept
        } else {
            drop(kept);
            Vec::with_capacity(len)
        };
        buffer.truncate(len);
        buffer.resize(len, T::default());
        buffer
    }

    /// Keeps `buffer` for the next [`Spare::take`] unless a larger one is kept already.
    pub(crate) fn keep(&self, buffer: Vec<T>) {
        if let Ok(mut kept) = self.kept.lock() {
            if buffer.capacity() > kept.capacity() {
                *kept = buffer;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kept_buffer_is_reused_when_it_fits_and_not_when_far_too_large() {
        let spare = Spare::<u16>::new();
        let first = spare.take(1000);
        assert_eq!(first.len(), 1000);
        let address = first.as_ptr();
        spare.keep(first);
        let again = spare.take(800);
        assert_eq!((again.len(), again.as_ptr()), (800, address));
        spare.keep(again);
        // Far smaller: a fresh buffer, and the large one is dropped rather than held.
        let small = spare.take(100);
        assert_eq!(small.len(), 100);
        assert!(small.capacity() < 1000);
        spare.keep(small);
        // Larger than what is kept: fresh, zeroed.
        let large = spare.take(5000);
        assert!(large.len() == 5000 && large.iter().all(|&v| v == 0));
    }
}
