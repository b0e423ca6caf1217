//! The reference ray march on the GPU: the same layers as
//! [`crate::reference::Marcher`] averaged per pixel as in the CPU frame, from the shadow
//! map and the per-sample surface distances.

use std::sync::Arc;

use glam::{DMat4, DVec3};

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::GpuResult;
use super::layer_buffers::LayerBuffers;
use super::shader::Shader;
use crate::camera::CameraModel;
use crate::layers::Layers;
use crate::scene::{Extent, Medium, PhaseModel, RenderSettings, Sun};
use crate::shadow_map::ShadowMap;
use crate::upsample::reduced_size;

pub const STAGE: &str = "reference ray march";
const LOCAL: [u32; 2] = [8, 8];
/// Bytes of the shader's `Params` block.
pub const PARAMS_BYTES: usize = 416;

/// Everything the march reads.
pub struct MarchInputs<'a> {
    pub camera: &'a CameraModel,
    pub shadow: &'a ShadowMap,
    pub sun: &'a Sun,
    pub medium: &'a Medium,
    pub settings: &'a RenderSettings,
    /// Ray distance to the first surface per depth sample (+∞ for background), at
    /// `supersampling` samples per pixel along each axis.
    pub surfaces: &'a [f32],
    pub supersampling: u32,
    /// Whether walks still dark at e^−10 go on ([`crate::reference::DARK_WALK_SHARE`]).
    pub dark_walks: bool,
    /// Rays end their light before the unlit side of their surface: not where a style
    /// reshaped the map ([`crate::shadowed_end`]).
    pub shadowed_ends: bool,
}

/// The shaders' `box_medium` (march_common.glsl): which integral the march takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum BoxKind {
    None = 0,
    Attenuating = 1,
    /// A box whose sunlight is not attenuated ([`Sun::attenuated_by_medium`]).
    Unattenuating = 2,
}

impl BoxKind {
    pub fn of(medium: &Medium, sun: &Sun) -> Self {
        match (&medium.extent, sun.attenuated_by_medium) {
            (Extent::Unbounded, _) => Self::None,
            (Extent::Box { .. }, true) => Self::Attenuating,
            (Extent::Box { .. }, false) => Self::Unattenuating,
        }
    }
}

fn columns(m: &DMat4) -> [f32; 16] {
    m.to_cols_array().map(|v| v as f32)
}

/// The shader's `Params` block, in its std430 layout.
pub fn march_params(inputs: &MarchInputs) -> Vec<u8> {
    let camera = inputs.camera;
    let settings = inputs.settings;
    let medium = inputs.medium;
    let light_travel = inputs.sun.direction.as_dvec3().normalize();
    let tint =
        medium.albedo.as_dvec3() * medium.extinction as f64 * inputs.sun.irradiance().as_dvec3();
    let (cube_from_world, towards_sun) = match &medium.extent {
        Extent::Unbounded => (DMat4::IDENTITY, DVec3::ZERO),
        Extent::Box { world_from_cube } => {
            let cube_from_world = world_from_cube.as_dmat4().inverse();
            let towards_sun = cube_from_world.transform_vector3(-light_travel);
            (cube_from_world, towards_sun)
        }
    };
    let terms = camera.ray_terms();
    let stride = settings.downsample;
    let mut p = Std430::new();
    p.mat4(columns(&camera.world_from_camera))
        .mat4(columns(&inputs.shadow.texel_from_world))
        .mat4(columns(&cube_from_world));
    for v in terms.origin.iter().chain(&terms.direction) {
        p.vec3(v.to_array());
    }
    p.vec3(tint.to_array())
        .vec3(light_travel.to_array())
        .vec3(towards_sun.to_array())
        .f32(camera.clip_start as f32)
        .f32(settings.max_distance)
        .f32(medium.extinction)
        .f32(inputs.shadow.bias as f32)
        .f32(medium.anisotropy)
        .u32((medium.phase == PhaseModel::Isotropic) as u32)
        .u32(BoxKind::of(medium, inputs.sun) as u32)
        .u32(settings.steps)
        .u32(reduced_size(camera.width, stride))
        .u32(reduced_size(camera.height, stride))
        .u32(camera.width)
        .u32(camera.height)
        .u32(stride)
        .u32(inputs.supersampling)
        .u32(inputs.shadow.size)
        .u32(inputs.dark_walks as u32)
        .f32(inputs.shadow.texel_size as f32)
        .u32(inputs.shadowed_ends as u32);
    p.finish()
}

/// Background samples are stored as −1: the shader then needs no infinities.
pub fn surface_values(distances: &[f32]) -> Vec<f32> {
    distances
        .iter()
        .map(|&d| if d.is_finite() { d } else { -1.0 })
        .collect()
}

/// Marches every output pixel (at the reduced size when `downsample` > 1); returns the
/// layers and the GPU time of the dispatch in milliseconds.
pub fn march(device: &Arc<Device>, inputs: &MarchInputs) -> GpuResult<(Layers, Option<f64>)> {
    let stride = inputs.settings.downsample;
    let width = reduced_size(inputs.camera.width, stride);
    let height = reduced_size(inputs.camera.height, stride);
    let groups = groups_2d(width, height, LOCAL, device.physical.max_workgroup_count)?;
    let run = || -> GpuResult<(Layers, Option<f64>)> {
        let mut rec = Recorder::new(device, STAGE, 1, 6)?;
        let params = rec.upload(&march_params(inputs), "march parameters")?;
        let shadow = rec.upload(&inputs.shadow.depth, "shadow map")?;
        let surfaces = rec.upload(&surface_values(inputs.surfaces), "surface distances")?;
        let out = LayerBuffers::new(&rec, width, height)?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::March, 6);
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
                ],
                &[],
                groups,
            )
        })?;
        let back = out.download(&mut rec)?;
        let done = rec.submit_and_wait()?;
        let layers = back.read(&done)?;
        Ok((layers, done.milliseconds(STAGE)))
    };
    run().map_err(|err| err.in_stage(STAGE))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::builtin_scene;
    use crate::render::FlatGeometry;

    #[test]
    fn params_fill_the_shaders_block_with_the_frame_values() {
        let scene = builtin_scene("torus").unwrap();
        let mut settings = scene.render.clone();
        settings.steps = 77;
        settings.downsample = 2;
        let camera = CameraModel::new(&scene.camera);
        let geometry = FlatGeometry::from_scene(&scene);
        let shadow = ShadowMap::build(
            &camera,
            &scene.sun,
            &scene.medium,
            &settings,
            &geometry.view(),
        )
        .unwrap();
        let inputs = MarchInputs {
            camera: &camera,
            shadow: &shadow,
            sun: &scene.sun,
            medium: &scene.medium,
            settings: &settings,
            surfaces: &[],
            supersampling: 1,
            dark_walks: false,
            shadowed_ends: true,
        };
        let bytes = march_params(&inputs);
        assert_eq!(bytes.len(), PARAMS_BYTES);
        let word =
            |offset: usize| u32::from_le_bytes(bytes[offset..offset + 4].try_into().unwrap());
        let float = |offset: usize| f32::from_bits(word(offset));
        // Scalars start after three matrices and nine vectors: 3·64 + 9·16 = 336.
        assert_eq!(float(336), camera.clip_start as f32);
        assert_eq!(float(340), settings.max_distance);
        assert_eq!(word(364), 77, "steps");
        assert_eq!(word(368), scene.camera.width.div_ceil(2));
        assert_eq!(word(376), scene.camera.width);
        assert_eq!(word(384), 2, "stride");
        assert_eq!(word(392), shadow.size);
        assert_eq!(
            float(400),
            shadow.texel_size as f32,
            "texel size, after dark_walks"
        );
        // The texel matrix sits in the second mat4, column-major.
        assert_eq!(float(64 + 12 * 4), shadow.texel_from_world.w_axis.x as f32);
    }

    /// The shaders' `box_medium` word, just before the steps' (at 360).
    #[test]
    fn params_name_the_box_and_whether_it_dims_the_sun() {
        let mut scene = builtin_scene("torus").unwrap();
        let camera = CameraModel::new(&scene.camera);
        let geometry = FlatGeometry::from_scene(&scene);
        let box_word = |scene: &crate::scene::Scene| {
            let shadow = ShadowMap::build(
                &camera,
                &scene.sun,
                &scene.medium,
                &scene.render,
                &geometry.view(),
            )
            .unwrap();
            let bytes = march_params(&MarchInputs {
                camera: &camera,
                shadow: &shadow,
                sun: &scene.sun,
                medium: &scene.medium,
                settings: &scene.render,
                surfaces: &[],
                supersampling: 1,
                dark_walks: false,
                shadowed_ends: true,
            });
            u32::from_le_bytes(bytes[360..364].try_into().unwrap())
        };
        assert_eq!(box_word(&scene), BoxKind::None as u32);
        scene.medium.extent = Extent::Box {
            world_from_cube: glam::Mat4::from_scale(glam::Vec3::splat(5.0)),
        };
        assert_eq!(box_word(&scene), BoxKind::Attenuating as u32);
        scene.sun.attenuated_by_medium = false;
        assert_eq!(box_word(&scene), BoxKind::Unattenuating as u32);
        assert_eq!(BoxKind::Unattenuating as u32, 2);
    }

    #[test]
    fn background_samples_become_negative() {
        assert_eq!(
            surface_values(&[1.5, f32::INFINITY, 0.0]),
            vec![1.5, -1.0, 0.0]
        );
    }
}
