//! Transfer-function application on the GPU: [`crate::transfer_function::apply`] with
//! the TF baked on the CPU.

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_1d, Std430};
use super::shader::Shader;
use crate::error::{Error, Result};
use crate::layers::Layers;
use crate::transfer_function::{per_light_matrix, ApplySettings, TfMode, TfTexture};

pub const STAGE: &str = "transfer function";
const LOCAL: u32 = 256;
const PUSH_BYTES: u32 = 80;

/// The shader's push constants.
pub fn push_constants(pixels: u32, texture_size: u32, settings: &ApplySettings) -> Vec<u8> {
    let range = settings.depth_range;
    let m = per_light_matrix(settings.light_color);
    let mut p = Std430::new();
    p.u32(pixels)
        .u32(texture_size)
        .f32(range.near)
        .f32(1.0 / (range.far - range.near))
        .u32((settings.mode == TfMode::Monochrome) as u32)
        .u32(0)
        .u32(0)
        .u32(0);
    for row in m {
        p.vec4([row[0], row[1], row[2], 0.0]);
    }
    p.finish()
}

/// Applies `texture` to `layers.volume` in place; returns the GPU time in milliseconds.
pub fn apply(
    device: &Arc<Device>,
    layers: &mut Layers,
    texture: &TfTexture,
    settings: &ApplySettings,
) -> Result<Option<f64>> {
    settings.validate()?;
    let pixels = layers.pixel_count();
    if layers.volume.len() != pixels * 4
        || layers.visibility.len() != pixels
        || layers.depth.len() != pixels
    {
        return Err(Error::invalid(
            "volume",
            format!(
                "layer sizes differ from {}×{}: {} visibility, {} depth and {} volume values",
                layers.width,
                layers.height,
                layers.visibility.len(),
                layers.depth.len(),
                layers.volume.len()
            ),
        ));
    }
    if pixels == 0 {
        return Ok(None);
    }
    let groups = groups_1d(pixels as u32, LOCAL, device.physical.max_workgroup_count)?;
    let push = push_constants(pixels as u32, texture.size(), settings);
    let mut run = || {
        let mut rec = Recorder::new(device, STAGE, 1, 4)?;
        let texels = rec.upload(texture.texels(), "TF texels")?;
        let visibility = rec.upload(&layers.visibility, "visibility layer")?;
        let depth = rec.upload(&layers.depth, "depth layer")?;
        let volume = rec.upload(&layers.volume, "volume layer")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Transfer, 4).push_constants(PUSH_BYTES);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[&texels, &visibility, &depth, &volume],
                &push,
                groups,
            )
        })?;
        let back = rec.download(&volume, "volume read-back")?;
        let done = rec.submit_and_wait()?;
        // Into the layer itself: it has the size copied back, and its pages are in.
        done.read_into(back, &mut layers.volume)?;
        Ok::<_, super::GpuError>(done.milliseconds(STAGE))
    };
    Ok(run().map_err(|err| err.in_stage(STAGE))?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transfer_function::DepthRange;

    #[test]
    fn push_constants_carry_the_range_and_the_light_matrix() {
        let settings = ApplySettings {
            mode: TfMode::Color,
            depth_range: DepthRange {
                near: 2.0,
                far: 6.0,
            },
            light_color: [1.0, 0.5, 0.0],
        };
        let bytes = push_constants(100, 64, &settings);
        assert_eq!(bytes.len(), PUSH_BYTES as usize);
        let float = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        assert_eq!(float(12), 0.25, "1/(far − near)");
        // Red is present with weight 1/1, and the absent blue is fed from red and green.
        assert_eq!(float(32), 1.0);
        assert_eq!(float(48 + 4), 2.0);
        assert!(float(64) > 0.0 && float(64 + 4) > 0.0 && float(64 + 8) == 0.0);
    }
}
