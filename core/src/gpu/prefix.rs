//! Prefiltering's basis computation and per-band prefix sums on the GPU, from the plan the
//! CPU builds over the rectified map ([`crate::prefiltered::PrefixPlan`]). Each band's rows
//! are summed in runs side by side ([`runs_per_band`]), since a frame has few bands (about
//! 900 of about 900 rows at 1080p) and one serial chain per band left most of a GPU idle.

use std::sync::{Arc, Mutex};

use super::barrier::Access;
use super::buffer::Buffer;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::Std430;
use super::error::{GpuError, GpuResult};
use super::shader::Shader;
use crate::error::Result;
use crate::prefiltered::{FilteredBasis, PrefixPlan, PrefixSums};
use crate::scene::BasisStorage;

pub const STAGE: &str = "prefiltered prefix sums";
/// Invocations per band (the shader's workgroup): one per pair of lanes and run of rows.
const LOCAL: u32 = 256;

/// Runs of rows each band's sums are cut into for rows of `stride` values: as many as the
/// workgroup holds one invocation per pair of lanes of each (8 at M = 64, 16 at M = 32);
/// `None` for rows that do not come in pairs or exceed the workgroup.
pub fn runs_per_band(stride: usize) -> Option<u32> {
    let pairs = stride / 2;
    (stride.is_multiple_of(2) && (1..=LOCAL as usize).contains(&pairs))
        .then(|| LOCAL / pairs as u32)
}

/// Workgroups for `bands` bands, one each, folded into y past the device's x limit.
pub fn band_groups(bands: u32, max_groups: [u32; 3]) -> GpuResult<[u32; 3]> {
    let x = bands.clamp(1, max_groups[0]);
    let y = bands.div_ceil(x).max(1);
    if y > max_groups[1] {
        return Err(GpuError::Unsupported(format!(
            "{bands} bands exceed the device's workgroup grid"
        )));
    }
    Ok([x, y, 1])
}

/// Bytes of the filtered basis as the shader writes it.
pub fn basis_bytes(plan: &PrefixPlan) -> u64 {
    let per_value = match plan.storage {
        BasisStorage::F32 => 4,
        BasisStorage::Snorm16 => 2,
    };
    (plan.total_rows * plan.stride) as u64 * per_value
}

fn push_constants(plan: &PrefixPlan, runs: u32) -> Vec<u8> {
    Std430::new()
        .u32(plan.stride as u32)
        .u32((plan.storage == BasisStorage::Snorm16) as u32)
        .u32(plan.bands.len() as u32)
        .u32(plan.samples_per_row as u32)
        .u32(runs)
        .finish()
}

/// The values of the packed output.
pub fn unpack(words: &[u32], storage: BasisStorage) -> FilteredBasis {
    match storage {
        BasisStorage::F32 => FilteredBasis::F32(words.iter().map(|&w| f32::from_bits(w)).collect()),
        BasisStorage::Snorm16 => FilteredBasis::Snorm16(
            words
                .iter()
                .flat_map(|&w| [w as u16 as i16, (w >> 16) as u16 as i16])
                .collect(),
        ),
    }
}

/// [`PrefixSums`] on a Vulkan device; remembers the GPU time of its last run.
pub struct GpuPrefixSums {
    device: Arc<Device>,
    milliseconds: Mutex<Option<f64>>,
}

impl GpuPrefixSums {
    pub fn new(device: &Arc<Device>) -> Self {
        Self {
            device: device.clone(),
            milliseconds: Mutex::new(None),
        }
    }

    pub fn milliseconds(&self) -> Option<f64> {
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn run(&self, plan: &PrefixPlan) -> GpuResult<FilteredBasis> {
        let (basis, ms) = resident(&self.device, plan)?;
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner()) = ms;
        let mut rec = Recorder::new(&self.device, STAGE, 0, 0)?;
        let back = rec.download(&basis, "filtered basis read-back")?;
        let done = rec.submit_and_wait()?;
        Ok(unpack(&done.read::<u32>(back)?, plan.storage))
    }
}

/// Computes the filtered basis into a device buffer that stays there (packed as
/// [`unpack`] reads it); also returns the GPU time in milliseconds.
pub fn resident(device: &Arc<Device>, plan: &PrefixPlan) -> GpuResult<(Buffer, Option<f64>)> {
    let run = || {
        let bytes = basis_bytes(plan);
        if bytes > device.physical.max_storage_buffer_range as u64 {
            return Err(GpuError::Unsupported(format!(
                "a filtered basis of {bytes} bytes exceeds the device's storage-buffer range \
                 of {} bytes",
                device.physical.max_storage_buffer_range
            )));
        }
        if device.physical.max_workgroup_width < LOCAL {
            return Err(GpuError::Unsupported(format!(
                "workgroups of {} invocations (the prefix sums take {LOCAL})",
                device.physical.max_workgroup_width
            )));
        }
        let Some(runs) = runs_per_band(plan.stride) else {
            return Err(GpuError::Unsupported(format!(
                "basis rows of {} values",
                plan.stride
            )));
        };
        let groups = band_groups(plan.bands.len() as u32, device.physical.max_workgroup_count)?;
        let bands: Vec<u32> = plan
            .bands
            .iter()
            .flat_map(|b| [b.first_row as u32, b.rows as u32])
            .collect();
        let mut rec = Recorder::new(device, STAGE, 1, 6)?;
        let bands = rec.upload(&bands, "prefix bands")?;
        let entries = rec.upload(&plan.entries, "prefix entries")?;
        let weights = rec.upload(&plan.weights, "prefix weights")?;
        let scales = rec.upload(&plan.scales, "prefix scales")?;
        let table = rec.upload(plan.table, "basis table")?;
        let basis = rec.storage(bytes, "filtered basis")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let push = push_constants(plan, runs);
        let desc = ComputePipelineDesc::new(Shader::Prefix, 6).push_constants(push.len() as u32);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[&bands, &entries, &weights, &scales, &table, &basis],
                &push,
                groups,
            )
        })?;
        let done = rec.submit_and_wait()?;
        Ok((basis, done.milliseconds(STAGE)))
    };
    run().map_err(|err: GpuError| err.in_stage(STAGE))
}

impl PrefixSums for GpuPrefixSums {
    fn prefix_sums(&self, plan: &PrefixPlan) -> Result<FilteredBasis> {
        Ok(self.run(plan).map_err(|err| err.in_stage(STAGE))?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bands_fold_into_a_second_axis_past_the_limit() {
        assert_eq!(band_groups(1000, [65_535; 3]).unwrap(), [1000, 1, 1]);
        assert_eq!(band_groups(70_000, [65_535; 3]).unwrap(), [65_535, 2, 1]);
        assert_eq!(band_groups(0, [65_535; 3]).unwrap(), [1, 1, 1]);
        assert!(band_groups(u32::MAX, [1024, 1024, 1]).is_err());
    }

    #[test]
    fn runs_fill_the_workgroup_one_invocation_per_pair_of_lanes() {
        assert_eq!(runs_per_band(64), Some(8));
        assert_eq!(runs_per_band(32), Some(16));
        assert_eq!(runs_per_band(24), Some(21));
        assert_eq!(runs_per_band(8), Some(64));
        for stride in (8..=64).step_by(8) {
            let runs = runs_per_band(stride).unwrap();
            assert!(runs as usize * stride / 2 <= LOCAL as usize);
            assert!((runs as usize + 1) * stride / 2 > LOCAL as usize);
        }
        assert_eq!(runs_per_band(0), None);
        assert_eq!(runs_per_band(33), None);
        assert_eq!(runs_per_band(2 * LOCAL as usize + 2), None);
    }

    #[test]
    fn snorm_pairs_unpack_low_half_first() {
        let word = (0x8001u32 << 16) | 0x7FFF;
        assert_eq!(
            unpack(&[word], BasisStorage::Snorm16),
            FilteredBasis::Snorm16(vec![32767, -32767])
        );
        assert_eq!(
            unpack(&[1.5f32.to_bits()], BasisStorage::F32),
            FilteredBasis::F32(vec![1.5])
        );
    }
}
