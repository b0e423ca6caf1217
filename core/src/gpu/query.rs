//! GPU timestamps: a query pool of labelled pairs, read back after the submission.

use ash::vk;

use super::error::{GpuResult, VkContext};

/// Milliseconds between two raw timestamps of a queue with `valid_bits` valid bits and
/// `period_ns` nanoseconds per tick; the counter may have wrapped once in between.
pub fn elapsed_ms(start: u64, end: u64, valid_bits: u32, period_ns: f32) -> f64 {
    let mask = if valid_bits >= 64 {
        u64::MAX
    } else {
        (1u64 << valid_bits) - 1
    };
    let ticks = (end & mask).wrapping_sub(start & mask) & mask;
    ticks as f64 * period_ns as f64 * 1e-6
}

pub struct TimestampPool {
    pub raw: vk::QueryPool,
    capacity: u32,
    labels: Vec<&'static str>,
}

impl TimestampPool {
    pub fn new(device: &ash::Device, capacity: u32) -> GpuResult<Self> {
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(capacity);
        // SAFETY: `info` outlives the call.
        let raw = unsafe { device.create_query_pool(&info, None) }.call("vkCreateQueryPool")?;
        Ok(Self {
            raw,
            capacity,
            labels: Vec::new(),
        })
    }

    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Reserves the next start/end pair for `label`; `None` when the pool is full.
    pub fn reserve(&mut self, label: &'static str) -> Option<(u32, u32)> {
        let first = self.labels.len() as u32 * 2;
        if first + 2 > self.capacity {
            return None;
        }
        self.labels.push(label);
        Some((first, first + 1))
    }

    /// (label, milliseconds) per reserved pair, once the submission has completed.
    pub fn read(
        &self,
        device: &ash::Device,
        valid_bits: u32,
        period_ns: f32,
    ) -> GpuResult<Vec<(&'static str, f64)>> {
        if self.labels.is_empty() {
            return Ok(Vec::new());
        }
        let mut ticks = vec![0u64; self.labels.len() * 2];
        // SAFETY: every reserved query was written by the completed command buffer.
        unsafe {
            device.get_query_pool_results(
                self.raw,
                0,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .call("vkGetQueryPoolResults")?;
        Ok(self
            .labels
            .iter()
            .enumerate()
            .map(|(i, &label)| {
                (
                    label,
                    elapsed_ms(ticks[2 * i], ticks[2 * i + 1], valid_bits, period_ns),
                )
            })
            .collect())
    }

    pub fn destroy(&self, device: &ash::Device) {
        // SAFETY: the submission that used the pool has completed.
        unsafe { device.destroy_query_pool(self.raw, None) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_become_milliseconds() {
        assert!((elapsed_ms(1_000, 2_001_000, 64, 1.0) - 2.0).abs() < 1e-12);
        assert!((elapsed_ms(0, 1_000, 64, 2.5) - 0.0025).abs() < 1e-12);
    }

    #[test]
    fn a_wrapped_counter_still_gives_the_short_interval() {
        let start = (1u64 << 36) - 100;
        let end = 900;
        assert!((elapsed_ms(start, end, 36, 1.0) - 1e-3).abs() < 1e-12);
    }

    #[test]
    fn bits_above_the_valid_ones_are_ignored() {
        let garbage = 0xABCD_u64 << 48;
        assert!((elapsed_ms(garbage | 10, 1_000_010, 48, 1.0) - 1.0).abs() < 1e-12);
    }
}
