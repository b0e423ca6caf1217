//! Buffers kept between frames. Every stage used to create its staging, storage and
//! read-back buffers anew and release them once waited for: on lavapipe that was 11–20 ms
//! of a 1080p frame, and fresh host-visible memory pays its page faults again on every
//! first write. A released buffer is kept here instead, keyed by its role and a capacity
//! rounded up to a quarter octave, and handed to the next request of that key. What is
//! kept is bounded in bytes; past the bound the buffers kept longest ago are released.
//!
//! The pool holds no GPU handles of its own kind: it is generic over what it keeps, so
//! that its logic runs without a device.

use std::collections::VecDeque;

use super::buffer::BufferRole;

/// The smallest capacity a kept buffer has: small buffers (parameters, tables) round up
/// to it, so that they share one key whatever their exact size.
pub const MIN_CAPACITY: u64 = 64 * 1024;

/// The most bytes kept on a device whatever its memory: a 1080p prefiltered frame's
/// buffers take about 250 MB, and 4K about four times that.
pub const MOST_KEPT_BYTES: u64 = 1 << 30;

/// The capacity a buffer of `size` bytes is created with: `size` rounded up to a quarter
/// octave (so at most 25% larger), and at least [`MIN_CAPACITY`]. Sizes that vary a
/// little from frame to frame (a plan's rows follow the camera) so share a capacity.
pub fn pooled_capacity(size: u64) -> u64 {
    let size = size.max(MIN_CAPACITY);
    // Steps of a quarter of the power of two at or below `size`: 2^k × {1, 1.25, 1.5, 1.75}.
    let octave = 63 - size.leading_zeros();
    let step = 1u64 << (octave - 2);
    size.div_ceil(step).saturating_mul(step)
}

/// The bytes a device keeps: an eighth of its device-local memory, at most
/// [`MOST_KEPT_BYTES`].
pub fn kept_bytes_limit(device_local_bytes: u64) -> u64 {
    (device_local_bytes / 8).min(MOST_KEPT_BYTES)
}

struct Kept<T> {
    role: BufferRole,
    capacity: u64,
    item: T,
}

/// Released buffers by role and capacity, oldest first.
pub struct BufferPool<T> {
    kept: VecDeque<Kept<T>>,
    kept_bytes: u64,
    limit: u64,
}

impl<T> BufferPool<T> {
    pub fn new(limit: u64) -> Self {
        Self {
            kept: VecDeque::new(),
            kept_bytes: 0,
            limit,
        }
    }

    /// The most recently kept buffer of `role` and `capacity`, if any.
    pub fn take(&mut self, role: BufferRole, capacity: u64) -> Option<T> {
        let index = self
            .kept
            .iter()
            .rposition(|k| k.role == role && k.capacity == capacity)?;
        let kept = self.kept.remove(index)?;
        self.kept_bytes -= kept.capacity;
        Some(kept.item)
    }

    /// Keeps `item`, a buffer of `role` and `capacity`. Returns what is no longer kept, for
    /// the caller to release: the buffers kept longest ago past the limit, or `item` itself
    /// where it alone exceeds it.
    pub fn keep(&mut self, role: BufferRole, capacity: u64, item: T) -> Vec<T> {
        if capacity > self.limit {
            return vec![item];
        }
        self.kept.push_back(Kept {
            role,
            capacity,
            item,
        });
        self.kept_bytes += capacity;
        let mut released = Vec::new();
        while self.kept_bytes > self.limit {
            let Some(oldest) = self.kept.pop_front() else {
                break;
            };
            self.kept_bytes -= oldest.capacity;
            released.push(oldest.item);
        }
        released
    }

    /// Everything kept, for the caller to release (the device's end).
    pub fn drain(&mut self) -> Vec<T> {
        self.kept_bytes = 0;
        self.kept.drain(..).map(|k| k.item).collect()
    }

    pub fn kept_bytes(&self) -> u64 {
        self.kept_bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capacities_round_up_to_a_quarter_octave() {
        assert_eq!(pooled_capacity(0), MIN_CAPACITY);
        assert_eq!(pooled_capacity(1), MIN_CAPACITY);
        assert_eq!(pooled_capacity(MIN_CAPACITY), MIN_CAPACITY);
        let mib = 1u64 << 20;
        assert_eq!(pooled_capacity(mib), mib);
        assert_eq!(pooled_capacity(mib + 1), mib + mib / 4);
        assert_eq!(pooled_capacity(mib + mib / 4), mib + mib / 4);
        assert_eq!(pooled_capacity(mib + mib / 4 + 1), mib + mib / 2);
        assert_eq!(pooled_capacity(2 * mib - 1), 2 * mib);
        // A 1080p volume layer (16 bytes a pixel) and a frame a few rows taller share one.
        let layer = 1920 * 1080 * 16;
        assert_eq!(pooled_capacity(layer), pooled_capacity(1920 * 1090 * 16));
        for size in (1..200_000_000u64).step_by(999_983) {
            let capacity = pooled_capacity(size);
            assert!(capacity >= size, "{size} → {capacity}");
            assert!(
                capacity <= (size + size / 4).max(MIN_CAPACITY),
                "{size} → {capacity}: more than a quarter larger"
            );
        }
    }

    #[test]
    fn the_limit_is_an_eighth_of_device_memory_at_most_a_gibibyte() {
        assert_eq!(kept_bytes_limit(4 << 30), 512 << 20);
        assert_eq!(kept_bytes_limit(80 << 30), MOST_KEPT_BYTES);
        assert_eq!(kept_bytes_limit(0), 0);
    }

    #[test]
    fn a_kept_buffer_goes_to_the_next_request_of_its_role_and_capacity() {
        let mut pool = BufferPool::new(1 << 20);
        assert!(pool
            .keep(BufferRole::Upload, MIN_CAPACITY, "upload")
            .is_empty());
        assert!(pool
            .keep(BufferRole::Storage, MIN_CAPACITY, "old")
            .is_empty());
        assert!(pool
            .keep(BufferRole::Storage, MIN_CAPACITY, "new")
            .is_empty());
        assert_eq!(pool.kept_bytes(), 3 * MIN_CAPACITY);
        assert_eq!(pool.take(BufferRole::Readback, MIN_CAPACITY), None);
        assert_eq!(pool.take(BufferRole::Storage, 2 * MIN_CAPACITY), None);
        // The warmest first: its memory was touched last.
        assert_eq!(pool.take(BufferRole::Storage, MIN_CAPACITY), Some("new"));
        assert_eq!(pool.take(BufferRole::Storage, MIN_CAPACITY), Some("old"));
        assert_eq!(pool.take(BufferRole::Storage, MIN_CAPACITY), None);
        assert_eq!(pool.kept_bytes(), MIN_CAPACITY);
        assert_eq!(pool.drain(), vec!["upload"]);
        assert_eq!(pool.kept_bytes(), 0);
    }

    #[test]
    fn past_the_limit_the_oldest_are_released() {
        let mut pool = BufferPool::new(3 * MIN_CAPACITY);
        for name in ["a", "b", "c"] {
            assert!(pool
                .keep(BufferRole::Storage, MIN_CAPACITY, name)
                .is_empty());
        }
        assert_eq!(
            pool.keep(BufferRole::Readback, 2 * MIN_CAPACITY, "d"),
            vec!["a", "b"]
        );
        assert_eq!(pool.kept_bytes(), 3 * MIN_CAPACITY);
        // Larger than the whole limit: handed straight back, nothing else released.
        assert_eq!(
            pool.keep(BufferRole::Upload, 4 * MIN_CAPACITY, "e"),
            vec!["e"]
        );
        assert_eq!(pool.drain(), vec!["c", "d"]);
    }
}
