//! The shader cores' clock rate, measured. GPUs lower it when lightly loaded, and every
//! compute stage then takes longer, nearly in proportion: one H200 ran whole bench
//! processes at its idle 345 MHz and others at 1980 MHz, its depth passes 5.6 times and
//! its prefiltered evaluation 5.0 times as long in the first.
//! The bench reports the clock beside its timings, read by a probe: one invocation counts
//! its subgroup's cycles (VK_KHR_shader_clock) around a dependent chain of multiply-adds,
//! and the cycles over the dispatch's timestamped duration give the rate.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::Std430;
use super::error::{GpuError, GpuResult};
use super::shader::Shader;

pub const STAGE: &str = "clock probe";

/// Links of the probe's chain: a quarter of a millisecond or more at 2 GHz (a link takes a
/// few cycles), against a few microseconds of dispatch overhead inside the timestamps,
/// which make the rate read a little low.
pub const CHAIN_LINKS: u32 = 1 << 17;

/// Whether the device has the subgroup clock and timestamps the probe needs.
pub fn supported(device: &Device) -> bool {
    device.physical.shader_clock && device.physical.timestamp_valid_bits > 0
}

/// The rate in MHz of a counter that read `start` and then `end` (each as 32-bit halves,
/// low first, as `clock2x32ARB` gives them) over `milliseconds`; `None` for readings no
/// clock gives (a counter that went backwards or stood still, or no time).
pub fn megahertz(start: [u32; 2], end: [u32; 2], milliseconds: f64) -> Option<f64> {
    let count = |halves: [u32; 2]| (u64::from(halves[1]) << 32) | u64::from(halves[0]);
    let cycles = count(end).checked_sub(count(start))?;
    (cycles > 0 && milliseconds > 0.0).then(|| cycles as f64 / (milliseconds * 1e3))
}

/// The clock rate in MHz while one probe of `links` ran; `None` where the device cannot
/// tell (no subgroup clock or no timestamps).
pub fn measure(device: &Arc<Device>, links: u32) -> GpuResult<Option<f64>> {
    if !supported(device) {
        return Ok(None);
    }
    let run = || {
        let mut rec = Recorder::new(device, STAGE, 1, 1)?;
        let readings = rec.storage(32, "clock readings")?;
        let desc = ComputePipelineDesc::new(Shader::Clock, 1).push_constants(16);
        let push = Std430::new().u32(links).f32(0.5).finish();
        rec.timed(STAGE, |rec| {
            rec.dispatch(&desc, &[&readings], &push, [1, 1, 1])
        })?;
        let back = rec.download(&readings, "clock readings")?;
        let done = rec.submit_and_wait()?;
        Ok::<_, GpuError>((done.read::<u32>(back)?, done.milliseconds(STAGE)))
    };
    let (words, milliseconds) = run().map_err(|err| err.in_stage(STAGE))?;
    Ok(match (words.get(..4), milliseconds) {
        (Some(w), Some(ms)) => megahertz([w[0], w[1]], [w[2], w[3]], ms),
        _ => None,
    })
}

/// Keeps the device busy with probes for `duration` (clocks rise under load), and returns
/// the last rate read.
pub fn warm_up(device: &Arc<Device>, duration: Duration) -> GpuResult<Option<f64>> {
    if !supported(device) {
        return Ok(None);
    }
    let started = Instant::now();
    let mut rate = None;
    while started.elapsed() < duration {
        rate = measure(device, CHAIN_LINKS * 8)?;
    }
    Ok(rate)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycles_over_milliseconds_give_megahertz() {
        assert_eq!(megahertz([0, 0], [2_000_000, 0], 1.0), Some(2000.0));
        // The low half wraps into the high one.
        let rate = megahertz([u32::MAX - 99, 6], [900, 7], 0.5).unwrap();
        assert!((rate - 2.0).abs() < 1e-12, "{rate}");
    }

    #[test]
    fn readings_no_clock_gives_are_none() {
        assert_eq!(megahertz([5, 1], [4, 1], 1.0), None);
        assert_eq!(megahertz([5, 1], [5, 1], 1.0), None);
        assert_eq!(megahertz([0, 0], [100, 0], 0.0), None);
    }
}
