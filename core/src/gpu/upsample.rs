//! Joint-bilateral upsampling on the GPU: [`crate::upsample::joint_bilateral`] of layers
//! evaluated at reduced resolution, guided by the full-size depth and, in bounded media,
//! by an opacity guide ([`crate::upsample::opacity_guide`]).

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::{GpuError, GpuResult};
use super::shader::Shader;
use crate::layers::Layers;
use crate::upsample::{reduced_size, BLENDED, DEPTH_TOLERANCE};

pub const STAGE: &str = "upsampling";
const LOCAL: [u32; 2] = [8, 8];
const PUSH_BYTES: u32 = 32;

fn push_constants(width: u32, height: u32, low: &Layers, factor: u32, guided: bool) -> Vec<u8> {
    Std430::new()
        .u32(width)
        .u32(height)
        .u32(low.width)
        .u32(low.height)
        .u32(factor)
        .f32(DEPTH_TOLERANCE)
        .u32(guided as u32)
        .u32(0)
        .finish()
}

/// Upsamples `low` to `width × height` by `factor`, guided by `depth` (full size), which
/// the result keeps as its depth layer, and by `opacity` (full size) if given; also
/// returns the GPU time in milliseconds.
pub fn joint_bilateral(
    device: &Arc<Device>,
    low: &Layers,
    depth: &[f32],
    opacity: Option<&[f32]>,
    width: u32,
    height: u32,
    factor: u32,
) -> GpuResult<(Layers, Option<f64>)> {
    let pixels = width as usize * height as usize;
    if depth.len() != pixels
        || opacity.is_some_and(|guide| guide.len() != pixels)
        || low.width != reduced_size(width, factor)
        || low.height != reduced_size(height, factor)
    {
        return Err(GpuError::Unsupported(format!(
            "upsampling {}×{} layers by {factor} to {width}×{height} with {} guide depths \
             and {} guide opacities",
            low.width,
            low.height,
            depth.len(),
            opacity.map_or(0, <[f32]>::len)
        )));
    }
    let groups = groups_2d(width, height, LOCAL, device.physical.max_workgroup_count)?;
    let run = || {
        let mut rec = Recorder::new(device, STAGE, 1, 7)?;
        let low_volume = rec.upload(&low.volume, "low-resolution volume")?;
        let low_visibility = rec.upload(&low.visibility, "low-resolution visibility")?;
        let low_depth = rec.upload(&low.depth, "low-resolution depth")?;
        let guide = rec.upload(depth, "full-size depth")?;
        // Unguided, the shader reads no opacity, but the binding still needs a buffer.
        let opacity_guide = rec.upload(opacity.unwrap_or(&[BLENDED]), "full-size opacity")?;
        let volume = rec.storage(pixels as u64 * 16, "volume layer")?;
        let visibility = rec.storage(pixels as u64 * 4, "visibility layer")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Upsample, 7).push_constants(PUSH_BYTES);
        let push = push_constants(width, height, low, factor, opacity.is_some());
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[
                    &low_volume,
                    &low_visibility,
                    &low_depth,
                    &guide,
                    &volume,
                    &visibility,
                    &opacity_guide,
                ],
                &push,
                groups,
            )
        })?;
        let volume_back = rec.download(&volume, "volume read-back")?;
        let visibility_back = rec.download(&visibility, "visibility read-back")?;
        let done = rec.submit_and_wait()?;
        let mut layers = Layers::for_overwrite(width, height).map_err(GpuError::host)?;
        done.read_into(volume_back, &mut layers.volume)?;
        done.read_into(visibility_back, &mut layers.visibility)?;
        layers.depth.copy_from_slice(depth);
        Ok::<_, GpuError>((layers, done.milliseconds(STAGE)))
    };
    run().map_err(|err| err.in_stage(STAGE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn push_constants_carry_both_sizes_the_tolerance_and_the_guide() {
        let low = Layers::new(5, 3);
        let bytes = push_constants(10, 6, &low, 2, true);
        assert_eq!(bytes.len(), PUSH_BYTES as usize);
        let word = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        assert_eq!(
            [word(0), word(4), word(8), word(12), word(16)],
            [10, 6, 5, 3, 2]
        );
        assert_eq!(f32::from_bits(word(20)), DEPTH_TOLERANCE);
        assert_eq!(word(24), 1);
        assert_eq!(push_constants(10, 6, &low, 2, false)[24..28], [0; 4]);
    }
}
