//! The Vulkan path's host-side time, summed per kind of work over all threads: creating
//! and releasing buffers (allocation), copying into and out of mapped memory, and waiting
//! for submissions. On an H200 a prefiltered frame's GPU stages took about 1.5 ms of a
//! 33–75 ms frame; the bench splits the rest with these sums.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// A kind of host work the sums tell apart.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HostWork {
    /// Creating buffers with their memory, and destroying them.
    Allocation,
    /// Copies into mapped memory (uploads).
    Writes,
    /// From a submission until its fence signals.
    Waits,
    /// Copies out of mapped memory (read-backs).
    Reads,
}

const KINDS: usize = 4;

static NANOSECONDS: [AtomicU64; KINDS] = [const { AtomicU64::new(0) }; KINDS];
static BYTES_WRITTEN: AtomicU64 = AtomicU64::new(0);
static BYTES_READ: AtomicU64 = AtomicU64::new(0);

/// Seconds of host work per kind, and the bytes the copies moved.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HostTimes {
    pub allocation: f64,
    pub writes: f64,
    pub waits: f64,
    pub reads: f64,
    pub bytes_written: u64,
    pub bytes_read: u64,
}

/// Runs `f`, adding its wall time to `work`'s sum.
pub fn timed<T>(work: HostWork, f: impl FnOnce() -> T) -> T {
    let started = Instant::now();
    let result = f();
    let elapsed = u64::try_from(started.elapsed().as_nanos()).unwrap_or(u64::MAX);
    NANOSECONDS[work as usize].fetch_add(elapsed, Ordering::Relaxed);
    result
}

/// Adds `bytes` copied into mapped memory.
pub fn count_written(bytes: usize) {
    BYTES_WRITTEN.fetch_add(bytes as u64, Ordering::Relaxed);
}

/// Adds `bytes` copied out of mapped memory.
pub fn count_read(bytes: usize) {
    BYTES_READ.fetch_add(bytes as u64, Ordering::Relaxed);
}

/// The sums since the last call, which starts new ones.
pub fn take() -> HostTimes {
    let take = |work: HostWork| NANOSECONDS[work as usize].swap(0, Ordering::Relaxed) as f64 * 1e-9;
    HostTimes {
        allocation: take(HostWork::Allocation),
        writes: take(HostWork::Writes),
        waits: take(HostWork::Waits),
        reads: take(HostWork::Reads),
        bytes_written: BYTES_WRITTEN.swap(0, Ordering::Relaxed),
        bytes_read: BYTES_READ.swap(0, Ordering::Relaxed),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timed_work_is_summed_by_kind() {
        let pause = std::time::Duration::from_millis(3);
        let value = timed(HostWork::Reads, || {
            std::thread::sleep(pause);
            7
        });
        assert_eq!(value, 7);
        let first = take();
        assert!(first.reads >= pause.as_secs_f64(), "{first:?}");
        count_written(1000);
        count_read(24);
        let counted = take();
        assert!(
            counted.bytes_written >= 1000 && counted.bytes_read >= 24,
            "{counted:?}"
        );
        timed(HostWork::Waits, || std::thread::sleep(pause));
        let second = take();
        // Other tests may render on a GPU meanwhile and add to any sum: only lower bounds.
        assert!(second.waits >= pause.as_secs_f64(), "{second:?}");
    }
}
