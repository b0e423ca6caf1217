//! Prefiltered per-pixel evaluation on the GPU: [`crate::prefiltered::Prefiltered::march`]
//! for every depth sample, with the reference march near on-screen epipoles and for rays
//! along the light, averaged into pixels as the CPU frame does.

use std::sync::Arc;

use super::barrier::Access;
use super::buffer::Buffer;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::{GpuError, GpuResult};
use super::layer_buffers::LayerBuffers;
use super::march::{march_params, surface_values, MarchInputs};
use super::prefix::band_groups;
use super::shader::Shader;
use crate::basis_kernels::LANES;
use crate::epipolar::{EpipolarMap, MapLayout};
use crate::layers::Layers;
use crate::prefiltered::{PrefilteredTables, WARP_KNOTS};
use crate::scene::BasisStorage;
use crate::uniformity::table_bytes;
use crate::upsample::reduced_size;

pub const STAGE: &str = "prefiltered evaluation";
const UNIFORMITY_STAGE: &str = "uniformity table";
const LOCAL: [u32; 2] = [8, 8];

/// The shader's `PrefilteredParams` block.
pub fn prefiltered_params(
    map: &EpipolarMap,
    tables: &PrefilteredTables,
    storage: BasisStorage,
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
    let snorm = storage == BasisStorage::Snorm16;
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
        // Row coordinates: the map's sample coordinates over the samples per row.
        .f32((g.spacing_step * tables.samples_per_row as f64) as f32)
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
        .u32(tables.exact_ray_ends as u32)
        .u32(tables.frequencies as u32)
        .f32(tables.bands_per_octave as f32)
        .f32(tables.dark_lookup_limit as f32)
        .f32(g.key_scale as f32)
        .finish())
}

/// The uniformity shader's push constants: slices, samples, and whether K scales with
/// 1/s.
fn uniformity_push(map: &EpipolarMap) -> Vec<u8> {
    let reciprocal = map.geometry().layout != MapLayout::Parallel;
    Std430::new()
        .u32(map.slices)
        .u32(map.samples)
        .u32(reciprocal as u32)
        .finish()
}

/// Evaluates every output pixel from the plan's tables and the filtered basis already on
/// the device (as [`super::prefix::resident`] leaves it); returns the layers and the
/// dispatch's GPU time.
#[allow(clippy::too_many_arguments)]
pub fn shade(
    device: &Arc<Device>,
    inputs: &MarchInputs,
    map: &EpipolarMap,
    tables: &PrefilteredTables,
    storage: BasisStorage,
    basis: &Buffer,
    epipoles: &[[f64; 2]],
    block: f64,
) -> GpuResult<(Layers, Option<f64>)> {
    if !tables.stride.is_multiple_of(LANES) {
        return Err(GpuError::Unsupported(format!(
            "basis rows of {} values (whole lanes of {LANES} expected)",
            tables.stride
        )));
    }
    let stride = inputs.settings.downsample;
    let width = reduced_size(inputs.camera.width, stride);
    let height = reduced_size(inputs.camera.height, stride);
    let groups = groups_2d(width, height, LOCAL, device.physical.max_workgroup_count)?;
    let band_knots: Vec<f32> = tables
        .band_knots
        .iter()
        .flat_map(|knots| knots.iter().map(|&k| k as f32))
        .collect();
    debug_assert_eq!(band_knots.len(), tables.bands.len() * WARP_KNOTS);
    let log2_fastest: Vec<f32> = tables.log2_fastest.iter().map(|&v| v as f32).collect();
    let slice_bands: Vec<u32> = tables.slice_bands.iter().flatten().copied().collect();
    let bands: Vec<u32> = tables.bands.iter().flatten().copied().collect();
    let run = || -> GpuResult<(Layers, Option<f64>)> {
        let mut rec = Recorder::new(device, STAGE, 2, 20)?;
        let params = rec.upload(&march_params(inputs), "march parameters")?;
        let shadow = rec.upload(&inputs.shadow.depth, "shadow map")?;
        let surfaces = rec.upload(&surface_values(inputs.surfaces), "surface distances")?;
        let out = LayerBuffers::new(&rec, width, height)?;
        let pf = rec.upload(
            &prefiltered_params(map, tables, storage, epipoles, block)?,
            "prefiltered parameters",
        )?;
        let band_knots = rec.upload(&band_knots, "band warps")?;
        let log2_fastest = rec.upload(&log2_fastest, "slice speeds")?;
        let slice_bands = rec.upload(&slice_bands, "slice bands")?;
        let bands = rec.upload(&bands, "bands")?;
        let weight = rec.upload(tables.weight, "cumulative weights")?;
        let coefficients = rec.upload(tables.coefficients, "coefficient table")?;
        // Exact ray ends and the uniformity table read the map.
        let rectified = rec.upload(&map.values, "rectified map")?;
        let bound_factors = rec.upload(map.bound_factors().as_flattened(), "sample bounds")?;
        let runs_bytes = table_bytes(map.slices, map.samples).max(8);
        let runs = rec.storage(runs_bytes as u64, "uniformity table")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let push = uniformity_push(map);
        let table_desc =
            ComputePipelineDesc::new(Shader::Uniformity, 3).push_constants(push.len() as u32);
        let table_groups = band_groups(map.slices, device.physical.max_workgroup_count)?;
        rec.timed(UNIFORMITY_STAGE, |rec| {
            rec.dispatch(
                &table_desc,
                &[&rectified, &bound_factors, &runs],
                &push,
                table_groups,
            )
        })?;
        rec.barrier(Access::ComputeWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Prefiltered, 17);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[
                    &params,
                    &shadow,
                    &surfaces,
                    &out.volume,
                    &out.visibility,
                    &out.depth,
                    &pf,
                    &band_knots,
                    &slice_bands,
                    &bands,
                    &weight,
                    basis,
                    &coefficients,
                    &log2_fastest,
                    &rectified,
                    &bound_factors,
                    &runs,
                ],
                &[],
                groups,
            )
        })?;
        let back = out.download(&mut rec)?;
        let done = rec.submit_and_wait()?;
        let layers = back.read(&done)?;
        let ms = [STAGE, UNIFORMITY_STAGE]
            .iter()
            .map(|stage| done.milliseconds(stage))
            .sum::<Option<f64>>();
        Ok((layers, ms))
    };
    run().map_err(|err| err.in_stage(STAGE))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::builtin_scene;
    use crate::epipolar::test_support::rectified;
    use crate::epipolar::RectifyDesc;
    use crate::prefiltered::{PrefilteredDesc, PrefilteredPlan};

    #[test]
    fn params_carry_the_layout_the_epipoles_and_the_storage() {
        let mut scene = builtin_scene("torus").unwrap();
        scene.camera.width = 64;
        scene.camera.height = 36;
        scene.render.shadow_map_size = 128;
        let (camera, _, map) = rectified(
            &scene,
            crate::scene::Rectification::Epipolar,
            &RectifyDesc::prefiltered(0),
        );
        let desc = PrefilteredDesc::from_settings(&scene.render);
        let plan = PrefilteredPlan::new(&map, &camera, &[], &desc, &scene.sun, &scene.medium, None)
            .expect("memory for the plan");
        let tables = plan.tables();
        let epipoles = [[10.0, 20.0]];
        let bytes =
            prefiltered_params(&map, &tables, BasisStorage::Snorm16, &epipoles, 16.0).unwrap();
        let word = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        let float = |o: usize| f32::from_bits(word(o));
        assert_eq!(bytes.len(), 176);
        assert_eq!((float(64), float(68)), (10.0, 20.0));
        assert_eq!(float(116), 16.0, "block");
        assert_eq!(word(120), 0, "radial layout");
        assert_eq!(word(132), map.slices);
        assert_eq!(word(140), tables.stride as u32);
        assert_eq!(word(144), 1, "snorm");
        assert_eq!(word(148), 1, "one epipole");
        assert_eq!(
            word(156),
            0,
            "exact ray ends off by default in an open medium"
        );
        assert_eq!(word(160), scene.render.bases / 2, "frequencies");
        assert_eq!(float(164), 1.0, "bands an octave in a thin medium");
        assert!(prefiltered_params(&map, &tables, BasisStorage::F32, &[[0.0; 2]; 3], 1.0).is_err());
    }
}
