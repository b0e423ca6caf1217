//! Prefiltered per-pixel evaluation on the GPU: [`crate::prefiltered::Prefiltered::march`]
//! for every depth sample, with the reference march near on-screen epipoles and for rays
//! along the light, averaged into pixels as the CPU frame does; with an adaptive tolerance,
//! only where neighbours disagree (the phases of `prefiltered.comp`).

use std::sync::Arc;

use super::barrier::Access;
use super::buffer::Buffer;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_1d, groups_2d, Std430};
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

/// The shader's phases (`Adaptive.phase` in `prefiltered.comp`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Phase {
    /// Every pixel shaded.
    Full = 0,
    /// Every fourth pixel each way shaded.
    Coarse = 1,
    /// Midpoints on the resolved grid's lines, interpolated or listed.
    Edges = 2,
    /// Its cells' centres, likewise.
    Centres = 3,
    /// The listed pixels' workgroup counts.
    Args = 4,
    /// The listed pixels shaded (an indirect dispatch).
    Listed = 5,
}

/// `adaptive_floor.comp`'s phases.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum FloorPhase {
    /// Per workgroup, the sum of its coarse pixels.
    PartialSums = 0,
    /// The floor from those sums, and the counts reset.
    Floor = 1,
}

/// The coarse grid's step, and the steps of the grids the refinement resolves from it.
const COARSE_STEP: u32 = 4;
const REFINED_STEPS: [u32; 2] = [4, 2];
/// `AdaptiveState` (`shaders/adaptive_state.glsl`): three counts and a pad, the
/// indirect arguments at byte 16, the floor at 32.
const STATE_BYTES: u64 = 48;
const ARGS_OFFSET: u64 = 16;
/// Index, in 32-bit words, of the count of pixels shaded in all.
const SHADED_WORD: usize = 2;
// The indirect arguments lie inside the state on a 4-byte boundary, after the counts.
const _: () = assert!(
    ARGS_OFFSET.is_multiple_of(4)
        && ARGS_OFFSET + 12 <= STATE_BYTES
        && (SHADED_WORD as u64 * 4) < ARGS_OFFSET
);
const PUSH_BYTES: u32 = 16;
const FLOOR_LOCAL: u32 = 256;
const FLOOR_PUSH_BYTES: u32 = 32;
/// Dispatches in an adaptive evaluation: the uniformity table, the coarse grid, the two
/// of the floor, and per refined step and kind of midpoint a classification, its
/// arguments and its listed pixels.
const MOST_DISPATCHES: u32 = 4 + REFINED_STEPS.len() as u32 * 2 * 3;

/// The shader's push constants for `phase`.
fn adaptive_push(phase: Phase, step: u32, tolerance: f32, perspective: bool) -> Vec<u8> {
    Std430::new()
        .u32(phase as u32)
        .u32(step)
        .f32(tolerance)
        .u32(perspective as u32)
        .finish()
}

/// `adaptive_floor.comp`'s push constants.
fn floor_push(
    phase: FloorPhase,
    width: u32,
    coarse_width: u32,
    coarse_count: u32,
    partial_count: u32,
) -> Vec<u8> {
    Std430::new()
        .u32(phase as u32)
        .u32(width)
        .u32(coarse_width)
        .u32(coarse_count)
        .u32(partial_count)
        .u32(0)
        .u32(0)
        .u32(0)
        .finish()
}

/// The layers one evaluation wrote.
pub struct Shaded {
    pub layers: Layers,
    /// GPU milliseconds of the uniformity table and the evaluation.
    pub milliseconds: Option<f64>,
    /// Pixels shaded rather than interpolated: all of them where `tolerance` is 0.
    pub shaded_pixels: u64,
}

/// Evaluates the output pixels from the plan's tables and the filtered basis already on
/// the device (as [`super::prefix::resident`] leaves it). With the settings' adaptive
/// tolerance above 0 the pixels are shaded adaptively (see `prefiltered.comp`), else every
/// one.
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
) -> GpuResult<Shaded> {
    if !tables.stride.is_multiple_of(LANES) {
        return Err(GpuError::Unsupported(format!(
            "basis rows of {} values (whole lanes of {LANES} expected)",
            tables.stride
        )));
    }
    let stride = inputs.settings.downsample;
    let width = reduced_size(inputs.camera.width, stride);
    let height = reduced_size(inputs.camera.height, stride);
    let pixels = width as u64 * height as u64;
    let max_groups = device.physical.max_workgroup_count;
    let groups = groups_2d(width, height, LOCAL, max_groups)?;
    let tolerance = inputs.settings.effective_adaptive_tolerance();
    let adaptive = tolerance > 0.0;
    let coarse = [width.div_ceil(COARSE_STEP), height.div_ceil(COARSE_STEP)];
    let coarse_groups = groups_2d(coarse[0], coarse[1], LOCAL, max_groups)?;
    let coarse_count = coarse[0] * coarse[1];
    let partial_groups = groups_1d(coarse_count, FLOOR_LOCAL, max_groups)?;
    let partial_count = partial_groups[0];
    let perspective = inputs.camera.is_perspective();
    let push = |phase: Phase, step: u32| adaptive_push(phase, step, tolerance, perspective);
    let floor_push =
        |phase: FloorPhase| floor_push(phase, width, coarse[0], coarse_count, partial_count);
    let band_knots: Vec<f32> = tables
        .band_knots
        .iter()
        .flat_map(|knots| knots.iter().map(|&k| k as f32))
        .collect();
    debug_assert_eq!(band_knots.len(), tables.bands.len() * WARP_KNOTS);
    let log2_fastest: Vec<f32> = tables.log2_fastest.iter().map(|&v| v as f32).collect();
    let slice_bands: Vec<u32> = tables.slice_bands.iter().flatten().copied().collect();
    let bands: Vec<u32> = tables.bands.iter().flatten().copied().collect();
    let run = || -> GpuResult<Shaded> {
        let mut rec = Recorder::new(device, STAGE, MOST_DISPATCHES, 20)?;
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
        // Shading every pixel, the shader reads none of these, but bindings need buffers.
        let state = rec.storage(STATE_BYTES, "adaptive shading state")?;
        let list = rec.storage(if adaptive { pixels * 4 } else { 4 }, "pixels to shade")?;
        let partials = rec.storage(
            if adaptive {
                partial_count as u64 * 16
            } else {
                16
            },
            "coarse sums",
        )?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let table_push = uniformity_push(map);
        let table_desc =
            ComputePipelineDesc::new(Shader::Uniformity, 3).push_constants(table_push.len() as u32);
        let table_groups = band_groups(map.slices, max_groups)?;
        rec.timed(UNIFORMITY_STAGE, |rec| {
            rec.dispatch(
                &table_desc,
                &[&rectified, &bound_factors, &runs],
                &table_push,
                table_groups,
            )
        })?;
        rec.barrier(Access::ComputeWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Prefiltered, 19).push_constants(PUSH_BYTES);
        let buffers = [
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
            &state,
            &list,
        ];
        rec.timed(STAGE, |rec| {
            if !adaptive {
                return rec.dispatch(&desc, &buffers, &push(Phase::Full, 0), groups);
            }
            let one = [1, 1, 1];
            rec.dispatch(&desc, &buffers, &push(Phase::Coarse, 0), coarse_groups)?;
            rec.barrier(Access::ComputeWrite, Access::ComputeRead);
            let floor_desc =
                ComputePipelineDesc::new(Shader::AdaptiveFloor, 3).push_constants(FLOOR_PUSH_BYTES);
            let floor_buffers = [&out.volume, &partials, &state];
            let sums = floor_push(FloorPhase::PartialSums);
            rec.dispatch(&floor_desc, &floor_buffers, &sums, partial_groups)?;
            rec.barrier(Access::ComputeWrite, Access::ComputeRead);
            let floor = floor_push(FloorPhase::Floor);
            rec.dispatch(&floor_desc, &floor_buffers, &floor, one)?;
            rec.barrier(Access::ComputeWrite, Access::ComputeRead);
            for step in REFINED_STEPS {
                let cells = [width.div_ceil(step), height.div_ceil(step)];
                for (phase, grid) in [
                    (Phase::Edges, [2 * cells[0], cells[1]]),
                    (Phase::Centres, cells),
                ] {
                    let grid_groups = groups_2d(grid[0], grid[1], LOCAL, max_groups)?;
                    rec.dispatch(&desc, &buffers, &push(phase, step), grid_groups)?;
                    rec.barrier(Access::ComputeWrite, Access::ComputeRead);
                    rec.dispatch(&desc, &buffers, &push(Phase::Args, 0), one)?;
                    rec.barrier(Access::ComputeWrite, Access::IndirectRead);
                    rec.barrier(Access::ComputeWrite, Access::ComputeRead);
                    let listed = push(Phase::Listed, 0);
                    rec.dispatch_indirect(&desc, &buffers, &listed, &state, ARGS_OFFSET)?;
                    rec.barrier(Access::ComputeWrite, Access::ComputeRead);
                }
            }
            Ok(())
        })?;
        let back = out.download(&mut rec)?;
        let state_back = adaptive
            .then(|| rec.download(&state, "adaptive shading state"))
            .transpose()?;
        let done = rec.submit_and_wait()?;
        let layers = back.read(&done)?;
        let shaded_pixels = match state_back {
            Some(state_back) => {
                let words: Vec<u32> = done.read(state_back)?;
                let shaded = words.get(SHADED_WORD).ok_or_else(|| {
                    GpuError::Unsupported("a short adaptive shading state".to_owned())
                })?;
                *shaded as u64
            }
            None => pixels,
        };
        let milliseconds = [STAGE, UNIFORMITY_STAGE]
            .iter()
            .map(|stage| done.milliseconds(stage))
            .sum::<Option<f64>>();
        Ok(Shaded {
            layers,
            milliseconds,
            shaded_pixels,
        })
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
    fn adaptive_push_constants_fill_the_pipelines_ranges() {
        let bytes = adaptive_push(Phase::Edges, 4, 0.01, true);
        assert_eq!(bytes.len(), PUSH_BYTES as usize);
        let word = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        assert_eq!([word(0), word(4), word(12)], [2, 4, 1]);
        assert_eq!(f32::from_bits(word(8)), 0.01);
        let bytes = floor_push(FloorPhase::Floor, 1920, 480, 129_600, 507);
        assert_eq!(bytes.len(), FLOOR_PUSH_BYTES as usize);
        let word = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        assert_eq!(
            [word(0), word(4), word(8), word(12), word(16)],
            [1, 1920, 480, 129_600, 507]
        );
    }

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
