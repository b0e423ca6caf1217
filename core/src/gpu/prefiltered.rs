//! Prefiltered per-pixel evaluation on the GPU: [`crate::prefiltered::Prefiltered::march`]
//! for every depth sample, with the reference march near on-screen epipoles and for rays
//! along the light, averaged into pixels as the CPU frame does.

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::{GpuError, GpuResult};
use super::march::{march_params, surface_values, MarchInputs};
use super::shader::Shader;
use crate::epipolar::{EpipolarMap, MapLayout};
use crate::layers::Layers;
use crate::prefiltered::{FilteredBasis, Prefiltered, WARP_KNOTS};
use crate::upsample::reduced_size;

pub const STAGE: &str = "prefiltered evaluation";
const LOCAL: [u32; 2] = [8, 8];

/// The shader's `PrefilteredParams` block.
pub fn prefiltered_params(
    map: &EpipolarMap,
    prefiltered: &Prefiltered,
    epipoles: &[[f64; 2]],
    block: f64,
) -> GpuResult<Vec<u8>> {
    if epipoles.len() > 2 {
        return Err(GpuError::Unsupported(format!(
            "{} on-screen epipoles (at most 2)",
            epipoles.len()
        )));
    }
    let g = map.geometry();
    let tables = prefiltered.tables();
    let mut e = [0.0f32; 4];
    for (i, epipole) in epipoles.iter().enumerate() {
        e[2 * i] = epipole[0] as f32;
        e[2 * i + 1] = epipole[1] as f32;
    }
    let layout = match g.layout {
        MapLayout::Radial => 0,
        MapLayout::Parallel => 1,
        MapLayout::Projective => 2,
    };
    let snorm = matches!(tables.basis, FilteredBasis::Snorm16(_));
    Ok(Std430::new()
        .mat4(g.from_world.to_cols_array().map(|v| v as f32))
        .vec4(e)
        .vec4([
            g.along.x as f32,
            g.along.y as f32,
            g.normal.x as f32,
            g.normal.y as f32,
        ])
        .f32(g.first as f32)
        .f32(g.step as f32)
        .f32(g.slope as f32)
        .f32(g.spacing_first as f32)
        .f32(g.spacing_step as f32)
        .f32(block as f32)
        .u32(layout)
        .u32(g.full_circle as u32)
        .u32(g.reciprocal_spacing as u32)
        .u32(map.slices)
        .u32(map.samples)
        .u32(tables.stride as u32)
        .u32(snorm as u32)
        .u32(epipoles.len() as u32)
        .u32(tables.near_plane_correction as u32)
        .u32(0)
        .finish())
}

/// The filtered basis as the shader reads it: f32 bits, or snorm16 pairs per word.
pub fn basis_words(basis: &FilteredBasis) -> Vec<u32> {
    match basis {
        FilteredBasis::F32(values) => values.iter().map(|v| v.to_bits()).collect(),
        FilteredBasis::Snorm16(values) => values
            .chunks(2)
            .map(|pair| {
                let low = pair[0] as u16 as u32;
                let high = pair.get(1).map_or(0, |&v| v as u16 as u32);
                low | (high << 16)
            })
            .collect(),
    }
}

/// Evaluates every output pixel; returns the layers and the dispatch's GPU time.
pub fn shade(
    device: &Arc<Device>,
    inputs: &MarchInputs,
    map: &EpipolarMap,
    prefiltered: &Prefiltered,
    epipoles: &[[f64; 2]],
    block: f64,
) -> GpuResult<(Layers, Option<f64>)> {
    let stride = inputs.settings.downsample;
    let width = reduced_size(inputs.camera.width, stride);
    let height = reduced_size(inputs.camera.height, stride);
    let pixels = width as u64 * height as u64;
    let groups = groups_2d(width, height, LOCAL, device.physical.max_workgroup_count)?;
    let tables = prefiltered.tables();
    let frames: Vec<f32> = tables
        .frames
        .iter()
        .flat_map(|(knots, log2_fastest)| {
            knots
                .iter()
                .map(|&k| k as f32)
                .chain(std::iter::once(*log2_fastest as f32))
        })
        .collect();
    debug_assert_eq!(frames.len(), tables.frames.len() * (WARP_KNOTS + 1));
    let slice_bands: Vec<u32> = tables.slice_bands.iter().flatten().copied().collect();
    let bands: Vec<u32> = tables.bands.iter().flatten().copied().collect();
    let run = || -> GpuResult<(Layers, Option<f64>)> {
        let mut rec = Recorder::new(device, STAGE, 1, 13)?;
        let params = rec.upload(&march_params(inputs), "march parameters")?;
        let shadow = rec.upload(&inputs.shadow.depth, "shadow map")?;
        let surfaces = rec.upload(&surface_values(inputs.surfaces), "surface distances")?;
        let volume = rec.storage(pixels * 16, "volume layer")?;
        let visibility = rec.storage(pixels * 4, "visibility layer")?;
        let depth = rec.storage(pixels * 4, "depth layer")?;
        let pf = rec.upload(
            &prefiltered_params(map, prefiltered, epipoles, block)?,
            "prefiltered parameters",
        )?;
        let frames = rec.upload(&frames, "slice frames")?;
        let slice_bands = rec.upload(&slice_bands, "slice bands")?;
        let bands = rec.upload(&bands, "bands")?;
        let weight = rec.upload(tables.weight, "cumulative weights")?;
        let basis = rec.upload(&basis_words(tables.basis), "filtered basis")?;
        let coefficients = rec.upload(tables.coefficients, "coefficient table")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Prefiltered, 13);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[
                    &params,
                    &shadow,
                    &surfaces,
                    &volume,
                    &visibility,
                    &depth,
                    &pf,
                    &frames,
                    &slice_bands,
                    &bands,
                    &weight,
                    &basis,
                    &coefficients,
                ],
                &[],
                groups,
            )
        })?;
        let volume_back = rec.download(&volume, "volume read-back")?;
        let visibility_back = rec.download(&visibility, "visibility read-back")?;
        let depth_back = rec.download(&depth, "depth read-back")?;
        let done = rec.submit_and_wait()?;
        let layers = Layers {
            width,
            height,
            volume: done.read(volume_back)?,
            visibility: done.read(visibility_back)?,
            depth: done.read(depth_back)?,
        };
        Ok((layers, done.milliseconds(STAGE)))
    };
    run().map_err(|err| err.in_stage(STAGE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn snorm_pairs_pack_low_half_first() {
        let words = basis_words(&FilteredBasis::Snorm16(vec![-1, 2, 3]));
        assert_eq!(words, vec![0x0002_FFFF, 0x0000_0003]);
        assert_eq!(
            basis_words(&FilteredBasis::F32(vec![0.5])),
            vec![0.5f32.to_bits()]
        );
    }
}
