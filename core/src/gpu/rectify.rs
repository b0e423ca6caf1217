//! Epipolar rectification on the GPU: the resampling of the shadow map along the slices of
//! an [`EpipolarMap`] whose layout the CPU chose. Projective maps are rasterized on the CPU.

use std::sync::{Arc, Mutex};

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{group_count, Std430};
use super::error::{GpuError, GpuResult};
use super::shader::Shader;
use crate::epipolar::{EpipolarMap, MapLayout, Resampler};
use crate::error::Result;
use crate::shadow_map::ShadowMap;

pub const STAGE: &str = "rectification";
const LOCAL: u32 = 64;
const PUSH_BYTES: u32 = 80;

/// The shader's push constants, or `None` for a projective map (rasterized, not resampled)
/// or a spacing that is not uniform.
pub fn push_constants(map: &EpipolarMap, shadow: &ShadowMap) -> Option<Vec<u8>> {
    let g = map.geometry();
    if g.layout == MapLayout::Projective || g.reciprocal_spacing {
        return None;
    }
    let radial = g.layout == MapLayout::Radial;
    let first = if radial { g.epipole } else { g.along };
    Some(
        Std430::new()
            .vec4([first.x as f32, first.y as f32, 0.0, 0.0])
            .vec4([g.normal.x as f32, g.normal.y as f32, 0.0, 0.0])
            .f32(g.first as f32)
            .f32(g.step as f32)
            .f32(g.spacing_first as f32)
            .f32(g.spacing_step as f32)
            .f32(g.camera_depth as f32)
            .f32(g.slope as f32)
            .f32(shadow.bias as f32)
            .u32(radial as u32)
            .u32(map.slices)
            .u32(map.samples)
            .u32(shadow.size)
            .u32(0)
            .finish(),
    )
}

/// [`Resampler`] on a Vulkan device; remembers the GPU time of its last run.
pub struct GpuResampler {
    device: Arc<Device>,
    milliseconds: Mutex<Option<f64>>,
}

impl GpuResampler {
    pub fn new(device: &Arc<Device>) -> Self {
        Self {
            device: device.clone(),
            milliseconds: Mutex::new(None),
        }
    }

    pub fn milliseconds(&self) -> Option<f64> {
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn run(&self, map: &EpipolarMap, shadow: &ShadowMap) -> GpuResult<Vec<f32>> {
        let device = &self.device;
        let push = push_constants(map, shadow).ok_or_else(|| {
            GpuError::Unsupported("resampling a projective map (it is rasterized)".to_owned())
        })?;
        let groups = [group_count(map.samples, LOCAL), map.slices, 1];
        let limits = device.physical.max_workgroup_count;
        if groups[0] > limits[0] || groups[1] > limits[1] {
            return Err(GpuError::Unsupported(format!(
                "{} slices of {} samples exceed the device's workgroup grid",
                map.slices, map.samples
            )));
        }
        let mut rec = Recorder::new(device, STAGE, 1, 2)?;
        let depth = rec.upload(&shadow.depth, "shadow map")?;
        let values = rec.storage(map.values.len() as u64 * 4, "rectified map")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Rectify, 2).push_constants(PUSH_BYTES);
        rec.timed(STAGE, |rec| {
            rec.dispatch(&desc, &[&depth, &values], &push, groups)
        })?;
        let back = rec.download(&values, "rectified map read-back")?;
        let done = rec.submit_and_wait()?;
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner()) = done.milliseconds(STAGE);
        done.read(back)
    }
}

impl Resampler for GpuResampler {
    fn resample(&self, map: &mut EpipolarMap, shadow: &ShadowMap) -> Result<()> {
        map.values = self.run(map, shadow).map_err(|err| err.in_stage(STAGE))?;
        Ok(())
    }
}
