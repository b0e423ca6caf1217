//! Hole creation (thresholded, animated Perlin fBm on chosen objects, Eq. 4–5) on the GPU:
//! one thread per texel evaluates [`HoleNoise`] where the shadow map's object id is a
//! chosen one and opens the occluder (+∞) below the threshold. The block placement runs
//! in double precision and the noise in single precision with the CPU's expressions and
//! order, so the result equals [`HoleNoise::apply`] bit for bit.

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::GpuError;
use super::shader::Shader;
use crate::error::{Error, Result};
use crate::holes::{HoleNoise, NoiseParams, MAX_OCTAVES};

pub const STAGE: &str = "hole creation";
const LOCAL: [u32; 2] = [16, 16];
/// Bytes of the shader's `Params`: four dvec2, eleven scalars padded to 16, and
/// `MAX_OCTAVES` octaves of 32 bytes.
pub const PARAMS_BYTES: usize = 64 + 48 + MAX_OCTAVES as usize * 32;

/// The shader's parameter buffer.
pub fn pack_params(params: &NoiseParams) -> Vec<u8> {
    let mut p = Std430::new();
    p.dvec2(params.origin)
        .dvec2(params.per_x)
        .dvec2(params.per_y)
        .dvec2(params.rotation)
        .u32(params.size)
        .u32(params.octaves.len() as u32)
        .u32(params.block)
        .u32(params.objects.len() as u32)
        .u32(params.period_whole)
        .u32(params.period_mask)
        .f32(params.period_cells)
        .f32(params.period_inverse)
        .f32(params.threshold)
        .f32(params.warp)
        .f32(params.perlin_scale);
    for index in 0..MAX_OCTAVES as usize {
        match params.octaves.get(index) {
            Some(octave) => p
                .dvec2(octave.shift)
                .f64(octave.scale)
                .f32(octave.weight)
                .u32(octave.seed),
            None => p.dvec2([0.0; 2]).f64(0.0).f32(0.0).u32(0),
        };
    }
    p.finish()
}

/// [`HoleNoise::apply`] on a copy of `depth` on the GPU; also returns the GPU time in
/// milliseconds (`None` where nothing ran or the device has no timestamps).
pub fn apply(
    device: &Arc<Device>,
    noise: &HoleNoise,
    depth: &[f32],
    ids: &[u32],
) -> Result<(Vec<f32>, Option<f64>)> {
    let size = noise.size();
    let texels = size as usize * size as usize;
    if depth.len() != texels || ids.len() != texels {
        return Err(Error::invalid(
            "holes.depth",
            format!(
                "{} depths and {} ids do not fill a {size}² map",
                depth.len(),
                ids.len()
            ),
        ));
    }
    if noise.opens_nothing() {
        return Ok((depth.to_vec(), None));
    }
    if !super::silhouette::supported(device) {
        return Err(GpuError::Unsupported(format!(
            "the {STAGE} stage needs double precision in shaders (shaderFloat64)"
        ))
        .into());
    }
    let params = noise.params();
    let packed = pack_params(&params);
    let groups = groups_2d(size, size, LOCAL, device.physical.max_workgroup_count)?;
    let run = || {
        let mut rec = Recorder::new(device, STAGE, 1, 5)?;
        let source = rec.upload(depth, "shadow-map depth")?;
        let object_ids = rec.upload(ids, "shadow-map object ids")?;
        let parameters = rec.upload(&packed, "noise parameters")?;
        let objects = rec.upload(&params.objects, "chosen objects")?;
        let target = rec.storage(depth.len() as u64 * 4, "holed depth")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Holes, 5);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[&source, &object_ids, &parameters, &objects, &target],
                &[],
                groups,
            )
        })?;
        let back = rec.download(&target, "holed depth read-back")?;
        let done = rec.submit_and_wait()?;
        Ok::<_, GpuError>((done.read(back)?, done.milliseconds(STAGE)))
    };
    Ok(run().map_err(|err| err.in_stage(STAGE))?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::holes::HolesDesc;
    use glam::{DMat4, DVec3};

    fn noise(desc: &HolesDesc) -> HoleNoise {
        HoleNoise::new(desc, &DMat4::from_scale(DVec3::new(20.0, 20.0, 1.0)), 64).unwrap()
    }

    #[test]
    fn params_fill_the_shader_layout() {
        let desc = HolesDesc {
            octaves: 3,
            grid_size: 60,
            time: 2.0,
            objects: vec![9, 2, 9],
            ..HolesDesc::default()
        };
        let params = noise(&desc).params();
        assert_eq!(params.objects, [2, 9], "sorted, without duplicates");
        assert_eq!(params.period_mask, 0, "60 cells wrap with a division");
        let bytes = pack_params(&params);
        assert_eq!(bytes.len(), PARAMS_BYTES);
        let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        let double = |at: usize| f64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
        assert_eq!(double(48), params.rotation[0]);
        assert_eq!((word(64), word(68), word(72), word(76)), (64, 3, 64, 2));
        assert_eq!(word(80), 60);
        // The third octave starts at 112 + 2·32: shift, then scale 4.
        assert_eq!(double(112 + 64 + 16), 4.0);
        assert_eq!(word(112 + 64 + 28), params.octaves[2].seed);
        assert_eq!(word(112 + 3 * 32 + 28), 0, "unused octaves are zero");
    }

    #[test]
    fn a_power_of_two_grid_wraps_with_a_mask() {
        let params = noise(&HolesDesc::default()).params();
        assert_eq!(params.period_whole, 64);
        assert_eq!(params.period_mask, 63);
        assert_eq!(params.octaves.len(), 4);
        let weights: f32 = params.octaves.iter().map(|o| o.weight).sum();
        assert!((weights - 1.0).abs() < 1e-6);
    }

    #[test]
    fn no_chosen_object_or_a_zero_threshold_opens_nothing() {
        assert!(noise(&HolesDesc::default()).opens_nothing());
        let chosen = HolesDesc {
            objects: vec![1],
            ..HolesDesc::default()
        };
        assert!(!noise(&chosen).opens_nothing());
        let closed = HolesDesc {
            threshold: 0.0,
            ..chosen
        };
        assert!(noise(&closed).opens_nothing());
    }
}
