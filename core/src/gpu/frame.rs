//! One frame on the Vulkan backend. Ported stages run on the GPU; the others run on the
//! CPU exactly as in the CPU backend:
//!
//! | stage | where |
//! |---|---|
//! | shadow map rasterization (depth and object ids), camera depth rasterization | GPU (graphics pipeline, depth passes) |
//! | camera depth given by the host: conversion to ray distances | CPU |
//! | hole filling (2D closing and the other morphology operations) | GPU |
//! | silhouette enhancement (line set-up per column and ray: CPU), hole creation | GPU (double precision in shaders) |
//! | reference ray march | GPU |
//! | epipolar rectification (resampling) for `prefiltered` | GPU |
//! | projective rectification (rasterized: projected depth), min-max scattering (its shadow map and camera depth included) | CPU |
//! | prefiltered: planning (frames, bands, weights) | CPU |
//! | prefiltered: basis computation, per-band prefix sums, per-pixel evaluation (adaptive shading included) | GPU |
//! | upsampling of downsampled evaluation | GPU |
//! | transfer function: baking | CPU; application | GPU |
//!
//! A depth target larger than the device's framebuffers, or a queue without graphics,
//! keeps that rasterization on the CPU, and a device without double precision in shaders
//! keeps silhouettes and hole creation there (listed in [`GpuTimes::cpu_stages`]).

use std::sync::Arc;

use super::device::Device;
use super::march::{self, MarchInputs};
use super::raster::GpuRasterizer;
use super::rectify::GpuResampler;
use crate::camera::CameraModel;
use crate::control::RenderControl;
use crate::epipolar::{epipoles_in_image, EpipolarMap, RectifyDesc};
use crate::error::Result;
use crate::layers::Layers;
use crate::prefiltered::{CpuPrefixSums, PrefilteredPlan};
use crate::reference::Marcher;
use crate::render::{
    camera_raster, frame_is_dark, prefiltered_desc, scatter_timed, Frame, SampleRays, StageTimes,
    SurfaceDistances,
};
use crate::scene::Method;
use crate::shadow_map::ShadowMap;
use crate::slice_reach::slice_reaches;
use crate::style::{OccluderOperator, Style};
use crate::upsample::{keep_opacity_guide, opacity_guide, reduced_size};

/// GPU timestamps of the stages that ran on the GPU, in milliseconds, and the names of
/// the stages that ran on the CPU.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GpuTimes {
    /// The shadow map's depth pass (depth and object ids).
    pub shadow_map: Option<f64>,
    /// The camera's depth pass.
    pub camera_depth: Option<f64>,
    pub hole_filling: Option<f64>,
    /// Silhouette enhancement (1D epipolar dilation or closure).
    pub silhouettes: Option<f64>,
    pub hole_creation: Option<f64>,
    pub ray_march: Option<f64>,
    /// Epipolar rectification (resampling the shadow map along slices).
    pub rectification: Option<f64>,
    /// Prefiltering's basis computation and prefix sums.
    pub prefix_sums: Option<f64>,
    /// Prefiltering's per-pixel evaluation (with the reference near epipoles).
    pub prefiltered: Option<f64>,
    /// Joint-bilateral upsampling of downsampled evaluation.
    pub upsampling: Option<f64>,
    pub transfer_function: Option<f64>,
    pub cpu_stages: Vec<&'static str>,
}

impl GpuTimes {
    /// The scattering stages' total, as [`StageTimes::scattering`] counts them on the CPU:
    /// rectification, the basis and its prefix sums, per-pixel evaluation (or the
    /// reference march) and upsampling; not the depth maps, the occluder operators or the
    /// transfer function.
    pub fn scattering(&self) -> f64 {
        [
            self.rectification,
            self.prefix_sums,
            self.prefiltered,
            self.ray_march,
            self.upsampling,
        ]
        .into_iter()
        .flatten()
        .sum()
    }

    /// The GPU stages' total.
    pub fn total(&self) -> f64 {
        [
            self.shadow_map,
            self.camera_depth,
            self.hole_filling,
            self.silhouettes,
            self.hole_creation,
            self.ray_march,
            self.rectification,
            self.prefix_sums,
            self.prefiltered,
            self.upsampling,
            self.transfer_function,
        ]
        .into_iter()
        .flatten()
        .sum()
    }
}

/// Renders `frame` with the ported stages on `device`.
pub fn render_timed(
    device: &Arc<Device>,
    frame: &Frame,
    control: &RenderControl,
) -> Result<(Layers, StageTimes, GpuTimes)> {
    frame.validate()?;
    let mut gpu = GpuTimes::default();
    let camera = CameraModel::new(frame.camera);
    let (mut layers, mut times) = if frame.settings.method != Method::MinMax {
        gpu_frame(device, frame, &camera, control, &mut gpu)?
    } else {
        gpu.cpu_stages = vec!["shadow map", "camera depth", "rectification"];
        if frame.style.manipulates_occluders() {
            gpu.cpu_stages.push("occluder manipulation");
        }
        gpu.cpu_stages.push(frame.settings.method.name());
        scatter_timed(frame, control, &CpuPrefixSums)?
    };
    if frame.style.tf.is_some() {
        let started = std::time::Instant::now();
        let light = frame.sun.irradiance() * frame.medium.albedo;
        if let Some((texture, settings)) =
            frame
                .style
                .bake_transfer_function(&layers, &camera, light.to_array())?
        {
            gpu.transfer_function =
                super::transfer::apply(device, &mut layers, &texture, &settings)?;
        }
        times.transfer_function = started.elapsed().as_secs_f64();
        gpu.cpu_stages.push("transfer-function baking");
    }
    Ok((layers, times, gpu))
}

/// The reference or the prefiltered method with their per-pixel work on the GPU.
fn gpu_frame(
    device: &Arc<Device>,
    frame: &Frame,
    camera: &CameraModel,
    control: &RenderControl,
    gpu: &mut GpuTimes,
) -> Result<(Layers, StageTimes)> {
    let mut times = StageTimes::default();
    let mut stopwatch = crate::render::Stopwatch::start();
    let rows = reduced_size(frame.camera.image_size().1, frame.settings.downsample);
    control.begin(rows as u64);
    control.check()?;
    let shadow_rasterizer = GpuRasterizer::shadow_map(device);
    let size = frame.settings.shadow_map_size;
    let mut shadow = if shadow_rasterizer.fits(size, size) {
        let shadow = ShadowMap::build_with(
            camera,
            frame.sun,
            frame.medium,
            frame.settings,
            &frame.geometry,
            &shadow_rasterizer,
        )?;
        gpu.shadow_map = shadow_rasterizer.milliseconds();
        shadow
    } else {
        gpu.cpu_stages.push("shadow map");
        ShadowMap::build(
            camera,
            frame.sun,
            frame.medium,
            frame.settings,
            &frame.geometry,
        )?
    };
    control.check()?;
    times.shadow_map = stopwatch.lap();
    // As the CPU frame's: a reshaped map keeps the light at rays' ends.
    let mut shadowed_ends = true;
    if frame.style.manipulates_occluders() {
        let rasterized = shadow.depth.clone();
        shadow = manipulate_occluders(device, frame.style, shadow, camera, gpu)?;
        shadowed_ends = shadow.depth == rasterized;
        times.occluders = stopwatch.lap();
    }
    let depth_rasterizer = GpuRasterizer::camera_depth(device);
    let (_, depth_desc) = camera_raster(camera, frame.settings.supersampling);
    let surfaces = if frame.camera_depth.is_none()
        && depth_rasterizer.fits(depth_desc.width, depth_desc.height)
    {
        let surfaces = SurfaceDistances::new_with(camera, frame, &depth_rasterizer)?;
        gpu.camera_depth = depth_rasterizer.milliseconds();
        surfaces
    } else {
        gpu.cpu_stages.push("camera depth");
        SurfaceDistances::new(camera, frame)?
    };
    times.camera_depth = stopwatch.lap();
    control.check()?;
    let dark_frame = frame_is_dark(frame, camera, &shadow, &surfaces);
    let inputs = MarchInputs {
        camera,
        shadow: &shadow,
        sun: frame.sun,
        medium: frame.medium,
        settings: frame.settings,
        surfaces: &surfaces.distances,
        supersampling: surfaces.supersampling,
        dark_walks: dark_frame,
        shadowed_ends,
    };
    let map = match frame.settings.method {
        Method::Prefiltered => {
            let resampler = GpuResampler::new(device);
            let map = EpipolarMap::rectify_with(
                camera,
                &shadow,
                &frame.geometry,
                frame.sun.direction.as_dvec3().normalize(),
                frame.settings.max_distance as f64,
                frame.rectification(),
                &RectifyDesc::prefiltered(frame.settings.epipolar_slices),
                &resampler,
            )?;
            gpu.rectification = resampler.milliseconds();
            if map.as_ref().is_some_and(EpipolarMap::is_projective) {
                gpu.cpu_stages.push("projective rectification (rasterized)");
            }
            map
        }
        _ => None,
    };
    times.rectify = stopwatch.lap();
    // Rectification is undefined for an orthographic camera looking straight along the
    // light; the reference handles that view, as on the CPU.
    let (layers, ms) = match &map {
        None => march::march(device, &inputs)?,
        Some(map) => {
            gpu.cpu_stages
                .push("prefiltered planning (frames, bands, weights)");
            let block = frame.settings.epipole_block as f64;
            let epipoles: Vec<[f64; 2]> = epipoles_in_image(camera, &shadow, block).collect();
            let ahead: Vec<[f64; 2]> = epipoles_in_image(camera, &shadow, f64::INFINITY).collect();
            let reaches = slice_reaches(
                map,
                camera,
                &surfaces.farthest,
                frame.settings.max_distance as f64,
            );
            let plan = PrefilteredPlan::new(
                map,
                camera,
                &ahead,
                &prefiltered_desc(frame, dark_frame),
                frame.sun,
                frame.medium,
                Some(&reaches),
            )?;
            // The filtered basis stays on the device: evaluation reads it there.
            let (basis, ms) = super::prefix::resident(device, plan.prefix())?;
            gpu.prefix_sums = ms;
            let tables = plan.tables();
            times.structure_bytes = basis.size() as usize
                + std::mem::size_of_val(tables.weight)
                + crate::uniformity::table_bytes(map.slices, map.samples);
            times.rectified_bytes = map.memory_bytes();
            times.prepare = stopwatch.lap();
            let shaded = super::prefiltered::shade(
                device,
                &inputs,
                map,
                &tables,
                plan.prefix().storage,
                &basis,
                &epipoles,
                block,
            )?;
            times.pixels = shaded.layers.pixel_count();
            times.shaded_pixels = shaded.shaded_pixels as usize;
            (shaded.layers, shaded.milliseconds)
        }
    };
    if map.is_some() {
        gpu.prefiltered = ms;
    } else {
        gpu.ray_march = ms;
    }
    let stride = frame.settings.downsample;
    let layers = if stride > 1 {
        let max_distance = frame.settings.max_distance;
        let depth: Vec<f32> = surfaces
            .distances
            .iter()
            .map(|&d| if d.is_finite() { d } else { max_distance })
            .collect();
        let marcher = Marcher::new(&shadow, frame.sun, frame.medium, frame.settings.steps);
        let opacity = marcher
            .in_box()
            .then(|| {
                gpu.cpu_stages
                    .push("upsampling's opacity guide (box media)");
                let rays = SampleRays {
                    camera,
                    surfaces: &surfaces,
                    max_distance: max_distance as f64,
                };
                opacity_guide(&layers, camera.width, camera.height, stride, |x, y| {
                    rays.opacity(&marcher, x as usize, y as usize)
                })
            })
            .transpose()?
            .flatten();
        let (layers, ms) = super::upsample::joint_bilateral(
            device,
            &layers,
            &depth,
            opacity.as_deref(),
            camera.width,
            camera.height,
            stride,
        )?;
        if let Some(guide) = opacity {
            keep_opacity_guide(guide);
        }
        gpu.upsampling = ms;
        layers
    } else {
        layers
    };
    control.advance(rows as u64);
    control.check()?;
    times.shading = stopwatch.lap();
    Ok((layers, times))
}

/// The style's occluder operators ([`Style::occluder_operators`]), each on the GPU. A
/// device without double precision in shaders leaves silhouettes and hole creation to
/// the CPU.
fn manipulate_occluders(
    device: &Arc<Device>,
    style: &Style,
    mut shadow: ShadowMap,
    camera: &CameraModel,
    gpu: &mut GpuTimes,
) -> Result<ShadowMap> {
    let double_precision = super::silhouette::supported(device);
    for operator in style.occluder_operators(&shadow, camera)? {
        match &operator {
            OccluderOperator::HoleFilling(desc) => {
                let (depth, ms) =
                    super::morphology::apply(device, &shadow.depth, shadow.size, desc)?;
                shadow.depth = depth;
                gpu.hole_filling = ms;
            }
            OccluderOperator::Silhouettes { desc, epipole } if double_precision => {
                let (depth, ms) =
                    super::silhouette::apply(device, &shadow.depth, shadow.size, *epipole, desc)?;
                shadow.depth = depth;
                gpu.silhouettes = ms;
            }
            OccluderOperator::HoleCreation(noise) if double_precision => {
                let (depth, ms) = super::holes::apply(device, noise, &shadow.depth, &shadow.ids)?;
                shadow.depth = depth;
                gpu.hole_creation = ms;
            }
            _ => {
                const ON_THE_CPU: &str = "silhouettes and hole creation";
                if !gpu.cpu_stages.contains(&ON_THE_CPU) {
                    gpu.cpu_stages.push(ON_THE_CPU);
                }
                operator.apply(&mut shadow)?;
            }
        }
    }
    Ok(shadow)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scattering_counts_the_stages_after_the_depth_maps_and_occluders() {
        let times = GpuTimes {
            shadow_map: Some(1.0),
            camera_depth: Some(2.0),
            hole_filling: Some(4.0),
            silhouettes: Some(8.0),
            hole_creation: Some(16.0),
            ray_march: None,
            rectification: Some(32.0),
            prefix_sums: Some(64.0),
            prefiltered: Some(128.0),
            upsampling: Some(256.0),
            transfer_function: Some(512.0),
            cpu_stages: Vec::new(),
        };
        assert_eq!(times.scattering(), 480.0);
        assert_eq!(times.total(), 1023.0);
        let march = GpuTimes {
            ray_march: Some(3.0),
            ..GpuTimes::default()
        };
        assert_eq!(march.scattering(), 3.0);
    }
}
