//! The per-frame pipeline: geometry → depth maps → scattering → layers.

use std::sync::atomic::{AtomicUsize, Ordering};

use glam::{DMat4, DVec3};
use rayon::prelude::*;

use crate::adaptive::{shade_adaptively, AdaptivePasses, EpipolarLines, SurfaceCoordinate};
use crate::camera::{CameraModel, Ray};
use crate::control::RenderControl;
use crate::cutout::{AlphaMask, Cutouts};
use crate::epipolar::{
    epipoles_in_image, CpuPartialResampler, CpuResampler, EpipolarMap, RectifyDesc, Resampler,
};
use crate::error::{Error, Result};
use crate::layers::{Layers, Pixel};
use crate::minmax::{MinMaxMethod, MinMaxMipmap};
use crate::phase;
use crate::prefiltered::{
    samples_read, CpuPrefixSums, Prefiltered, PrefilteredDesc, PrefilteredPlan, PrefixSums,
    DARK_LOOKUP_VISIBILITY,
};
use crate::raster::{keep_camera_depth, keep_map_targets, rasterize_depth, RasterDesc, Rasterizer};
use crate::reference::{integral_exp, Marcher, RaySample};
use crate::scene::{
    check_triangles, Camera, Extent, Medium, Method, Rectification, RenderSettings, Scene, Sun,
};
use crate::shadow_map::ShadowMap;
use crate::shadowed_end::{lit_end, DepthSamples};
use crate::slice_reach::{slice_reaches, FarthestPerBlock};
use crate::style::Style;
use crate::upsample::{
    joint_bilateral_into, keep_opacity_guide, opacity_guide, reduced_size, sample_pixel,
};
use crate::visibility::VisibilitySplit;

/// Triangles, borrowed so that hosts can pass their buffers without copies.
#[derive(Clone, Copy, Debug)]
pub struct Geometry<'a> {
    /// Positions relative to `origin`.
    pub positions: &'a [[f32; 3]],
    pub triangles: &'a [[u32; 3]],
    /// One object id per triangle.
    pub object_ids: &'a [u32],
    /// The world point the positions are relative to: near the camera, an f32 position
    /// keeps its precision however far the scene lies from the world's origin (at 100 km
    /// f32 world positions are 8 mm apart, and colonnade's frame moved by 1.7%). Hosts that
    /// pass world positions give zero.
    pub origin: DVec3,
    /// Triangles cut by alpha masks, if any ([`crate::cutout`]).
    pub cutouts: Option<Cutouts<'a>>,
}

/// How a renderer's depth pass measures distance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum DepthKind {
    /// Distance along the camera's view axis (Blender's and Cycles' Z pass).
    #[default]
    Planar,
    /// Distance along each pixel's view ray.
    RayDistance,
}

/// A renderer-supplied camera depth at the camera's resolution, rows top to bottom.
/// Values at or beyond `clip_end`, and +∞, are background.
#[derive(Clone, Copy, Debug)]
pub struct CameraDepth<'a> {
    pub values: &'a [f32],
    pub kind: DepthKind,
}

/// Everything one frame needs, borrowed.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    pub camera: &'a Camera,
    pub sun: &'a Sun,
    pub medium: &'a Medium,
    pub settings: &'a RenderSettings,
    /// The triangles that block the sun (the shadow map's).
    pub geometry: Geometry<'a>,
    /// The triangles the camera sees, where they are not `geometry`'s
    /// ([`crate::visibility`]): an object hidden from shadow rays still hides the fog behind
    /// it, and one hidden from the camera still casts shafts. None: `geometry`'s.
    pub camera_geometry: Option<Geometry<'a>>,
    pub camera_depth: Option<CameraDepth<'a>>,
    pub style: &'a Style,
}

/// A scene's meshes flattened into one geometry, relative to the camera's position.
#[derive(Clone, Debug, Default)]
pub struct FlatGeometry {
    /// Relative to `origin`.
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    pub object_ids: Vec<u32>,
    pub origin: DVec3,
    /// The meshes' alpha cutouts, once loaded ([`FlatGeometry::load_cutouts`]): texture
    /// coordinates per position, a mask per triangle, the masks' images. Empty without.
    pub uvs: Vec<[f32; 2]>,
    pub triangle_masks: Vec<u32>,
    pub masks: Vec<AlphaMask<'static>>,
    /// The triangles that block the sun and those the camera sees, where meshes differ
    /// ([`FlatGeometry::split_visibility`]); None: all do both.
    pub split: Option<VisibilitySplit>,
}

impl FlatGeometry {
    pub fn from_scene(scene: &Scene) -> Self {
        let origin = scene.camera.world_from_camera.w_axis.truncate().as_dvec3();
        let mut flat = FlatGeometry {
            origin,
            ..FlatGeometry::default()
        };
        for mesh in &scene.meshes {
            let base = flat.positions.len() as u32;
            // In f64, then made relative, so that only the offset from the camera is rounded.
            let local_from_object =
                DMat4::from_translation(-origin) * mesh.world_from_object.as_dmat4();
            flat.positions.extend(mesh.positions.iter().map(|&p| {
                local_from_object
                    .transform_point3(glam::Vec3::from(p).as_dvec3())
                    .as_vec3()
                    .to_array()
            }));
            flat.triangles.extend(
                mesh.triangles
                    .iter()
                    .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
            );
            flat.object_ids
                .extend(std::iter::repeat_n(mesh.object_id, mesh.triangles.len()));
        }
        flat
    }

    /// Splits the triangles by their meshes' `blocks_sun` and `seen_by_camera` (after
    /// [`FlatGeometry::load_cutouts`], whose masks the split keeps).
    pub fn split_visibility(&mut self, scene: &Scene) -> Result<()> {
        self.split = None;
        if scene
            .meshes
            .iter()
            .all(|m| m.blocks_sun && m.seen_by_camera)
        {
            return Ok(());
        }
        let visibility: Vec<u8> = scene
            .meshes
            .iter()
            .flat_map(|mesh| {
                let flags = u8::from(mesh.blocks_sun) * crate::visibility::BLOCKS_SUN
                    + u8::from(mesh.seen_by_camera) * crate::visibility::SEEN_BY_CAMERA;
                std::iter::repeat_n(flags, mesh.triangles.len())
            })
            .collect();
        self.split = VisibilitySplit::new(&self.whole(), &visibility, "meshes")?;
        Ok(())
    }

    /// Reads the images of the scene's alpha masks (meshes with `alpha_mask`), in the
    /// order of `from_scene`'s triangles; a mesh without keeps no mask.
    pub fn load_cutouts(&mut self, scene: &Scene) -> Result<()> {
        if scene.meshes.iter().all(|mesh| mesh.alpha_mask.is_none()) {
            return Ok(());
        }
        self.uvs.clear();
        self.triangle_masks.clear();
        self.masks.clear();
        for (index, mesh) in scene.meshes.iter().enumerate() {
            let uvs = mesh.uvs.as_deref().unwrap_or_default();
            match uvs.len() {
                0 => self
                    .uvs
                    .extend(std::iter::repeat_n([0.0; 2], mesh.positions.len())),
                _ => self.uvs.extend_from_slice(uvs),
            }
            let mask = match &mesh.alpha_mask {
                None => crate::cutout::OPAQUE,
                Some(desc) => {
                    let field = format!("meshes[{index}].alpha_mask.image");
                    let mut mask = crate::transfer_function::load_alpha_mask(
                        &field,
                        &desc.image,
                        desc.threshold,
                    )?;
                    mask.wrap = desc.wrap.axes();
                    mask.filter = desc.filter;
                    mask.border = desc.border;
                    self.masks.push(mask);
                    (self.masks.len() - 1) as u32
                }
            };
            self.triangle_masks
                .extend(std::iter::repeat_n(mask, mesh.triangles.len()));
        }
        Ok(())
    }

    /// The triangles that block the sun.
    pub fn view(&self) -> Geometry<'_> {
        match &self.split {
            Some(split) => split.sun.view(&self.whole()),
            None => self.whole(),
        }
    }

    /// The triangles the camera sees, where they differ from [`FlatGeometry::view`]'s.
    pub fn camera_view(&self) -> Option<Geometry<'_>> {
        self.split
            .as_ref()
            .map(|split| split.camera.view(&self.whole()))
    }

    fn whole(&self) -> Geometry<'_> {
        Geometry {
            positions: &self.positions,
            triangles: &self.triangles,
            object_ids: &self.object_ids,
            origin: self.origin,
            cutouts: (!self.triangle_masks.is_empty()).then_some(Cutouts {
                uvs: &self.uvs,
                triangle_masks: &self.triangle_masks,
                masks: &self.masks,
            }),
        }
    }
}

/// Renders a validated scene description.
pub fn render_scene(scene: &Scene, control: &RenderControl) -> Result<Layers> {
    render_scene_timed(scene, control).map(|(layers, _)| layers)
}

/// [`render_scene`], also reporting how long each stage took.
pub fn render_scene_timed(scene: &Scene, control: &RenderControl) -> Result<(Layers, StageTimes)> {
    scene.validate()?;
    let mut geometry = FlatGeometry::from_scene(scene);
    geometry.load_cutouts(scene)?;
    geometry.split_visibility(scene)?;
    render_timed(&Frame::of_scene(scene, &geometry), control)
}

/// Wall time of each stage of one frame, in seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes {
    pub shadow_map: f64,
    pub camera_depth: f64,
    /// Rectification of the shadow map (fast methods), projective rasterization included.
    pub rectify: f64,
    /// The method's acceleration structure: min-max mipmap or filtered basis.
    pub prepare: f64,
    /// Of `prepare`, prefiltering's plan on the CPU: each slice's sampled rays, bands and
    /// sample weights; the rest is its filtered basis (the prefix sums and the tables
    /// over them). 0 for the other methods.
    pub planning: f64,
    /// Per-pixel evaluation, upsampling included.
    pub shading: f64,
    /// Of `shading`, adaptive shading's passes (all 0 where every pixel is shaded).
    pub passes: AdaptivePasses,
    /// Occluder manipulation of the scattering's shadow-map copy.
    pub occluders: f64,
    /// Transfer-function application, baking included.
    pub transfer_function: f64,
    /// Bytes held by the rectified shadow map (fast methods).
    pub rectified_bytes: usize,
    /// Bytes held by the method's own structure: the min-max mipmap or the filtered
    /// basis with its cumulative weights.
    pub structure_bytes: usize,
    /// Pixels evaluated (at the reduced size with downsampling) and how many of them were
    /// shaded rather than interpolated (adaptive shading); 0 where not counted (the
    /// Vulkan backend's reference march).
    pub pixels: usize,
    pub shaded_pixels: usize,
    /// Rays of the shaded pixels that a fast method was asked for, and of those, how many
    /// it declined (too short for its lookups, along the light, too imprecise, or near an
    /// on-screen epipole) and the exact walk computed instead; 0 for the reference, for a
    /// view straight along the light (which the reference renders), and on the Vulkan
    /// backend.
    pub fast_rays: usize,
    pub walked_rays: usize,
}

impl StageTimes {
    /// The scattering stage alone: everything after the two depth maps.
    pub fn scattering(&self) -> f64 {
        self.rectify + self.prepare + self.shading
    }

    /// Adds the stages of another pass of the same frame ([`crate::channels`]): times and
    /// counts add up, memory is the larger pass's.
    pub(crate) fn accumulate(&mut self, other: &StageTimes) {
        self.shadow_map += other.shadow_map;
        self.camera_depth += other.camera_depth;
        self.rectify += other.rectify;
        self.prepare += other.prepare;
        self.planning += other.planning;
        self.shading += other.shading;
        self.passes.accumulate(&other.passes);
        self.occluders += other.occluders;
        self.transfer_function += other.transfer_function;
        self.rectified_bytes = self.rectified_bytes.max(other.rectified_bytes);
        self.structure_bytes = self.structure_bytes.max(other.structure_bytes);
        self.pixels += other.pixels;
        self.shaded_pixels += other.shaded_pixels;
        self.fast_rays += other.fast_rays;
        self.walked_rays += other.walked_rays;
    }
}

/// Renders one frame from borrowed inputs, validating them first.
pub fn render(frame: &Frame, control: &RenderControl) -> Result<Layers> {
    render_timed(frame, control).map(|(layers, _)| layers)
}

/// [`render`], also reporting how long each stage took. Runs on the backend that
/// `render.backend` selects; a Vulkan failure falls back to the CPU with one message on
/// standard error. A medium with coloured extinction takes a pass per distinct channel
/// ([`crate::channels`]), and a sun disc a pass per direction over it
/// ([`crate::sun_disc`]).
pub fn render_timed(frame: &Frame, control: &RenderControl) -> Result<(Layers, StageTimes)> {
    // Once a pass falls back, the frame's other passes go straight to the CPU: one message.
    let fell_back = std::cell::Cell::new(false);
    let render_pass = |frame: &Frame, control: &RenderControl| {
        let device = match fell_back.get() {
            true => None,
            false => crate::backend::vulkan_device(frame.settings.backend),
        };
        if let Some(device) = device {
            match crate::gpu::frame::render_timed(&device, frame, control) {
                Ok((layers, times, _)) => return Ok((layers, times)),
                Err(Error::Gpu(err)) => {
                    crate::backend::report_fallback(&err);
                    fell_back.set(true);
                }
                Err(other) => return Err(other),
            }
        }
        render_grey_cpu(frame, control)
    };
    let (layers, times) = crate::channels::by_channel(frame, control, |frame, control| {
        crate::sun_disc::by_sun_direction(frame, control, render_pass)
    })?;
    Ok((with_camera_pixels(layers, frame), times))
}

/// `layers` marked with the camera's pixel aspect.
fn with_camera_pixels(mut layers: Layers, frame: &Frame) -> Layers {
    layers.pixel_aspect = frame.camera.pixel_aspect;
    layers
}

/// [`render_timed`] on the CPU backend, the oracle.
pub fn render_timed_cpu(frame: &Frame, control: &RenderControl) -> Result<(Layers, StageTimes)> {
    let (layers, times) = crate::channels::by_channel(frame, control, |frame, control| {
        crate::sun_disc::by_sun_direction(frame, control, render_grey_cpu)
    })?;
    Ok((with_camera_pixels(layers, frame), times))
}

/// [`render_timed_cpu`] of a frame whose medium has one extinction.
fn render_grey_cpu(frame: &Frame, control: &RenderControl) -> Result<(Layers, StageTimes)> {
    let (mut layers, mut times) = scatter_timed(frame, control, &CpuPrefixSums)?;
    apply_transfer_function_timed(frame, &mut layers, &mut times)?;
    Ok((layers, times))
}

/// The frame's transfer function, if any, on the CPU over `layers`, its time added to
/// `times`.
pub(crate) fn apply_transfer_function_timed(
    frame: &Frame,
    layers: &mut Layers,
    times: &mut StageTimes,
) -> Result<()> {
    if frame.style.tf.is_some() {
        let started = std::time::Instant::now();
        let light = frame.sun.irradiance() * frame.medium.albedo;
        frame.style.apply_transfer_function(
            layers,
            &CameraModel::new(frame.camera),
            light.to_array(),
        )?;
        times.transfer_function += started.elapsed().as_secs_f64();
    }
    Ok(())
}

/// Wall time of consecutive stages: each lap is the time since the previous one.
pub(crate) struct Stopwatch(std::time::Instant);

impl Stopwatch {
    pub(crate) fn start() -> Self {
        Self(std::time::Instant::now())
    }

    /// Seconds since the start or the last lap, without starting a new lap.
    pub(crate) fn elapsed(&self) -> f64 {
        self.0.elapsed().as_secs_f64()
    }

    /// Seconds since the start or the last lap.
    pub(crate) fn lap(&mut self) -> f64 {
        let now = std::time::Instant::now();
        let seconds = (now - self.0).as_secs_f64();
        self.0 = now;
        seconds
    }
}

/// Everything up to the per-pixel layers: depth maps, occluder manipulation, scattering.
/// `prefix` computes prefiltering's filtered basis (on the CPU or a GPU).
pub(crate) fn scatter_timed(
    frame: &Frame,
    control: &RenderControl,
    prefix: &dyn PrefixSums,
) -> Result<(Layers, StageTimes)> {
    let mut times = StageTimes::default();
    let mut stopwatch = Stopwatch::start();
    frame.validate()?;
    control.begin(reduced_size(frame.camera.image_size().1, frame.settings.downsample) as u64);
    control.check()?;
    let camera = CameraModel::new(frame.camera);
    let shadow = FrameShadowMap(ShadowMap::build(
        &camera,
        frame.sun,
        frame.medium,
        frame.settings,
        &frame.geometry,
    )?);
    control.check()?;
    times.shadow_map = stopwatch.lap();
    // Rays end their light before the unlit side of their surface
    // ([`crate::shadowed_end`]) unless a style reshaped the map: it then no longer holds
    // the surfaces the camera sees, and the light there is the style's.
    let (shadow, shadowed_ends) = if frame.style.manipulates_occluders() {
        let manipulated = frame.style.scattering_map(&shadow, &camera)?;
        times.occluders = stopwatch.lap();
        let unchanged = manipulated.depth == shadow.depth;
        (FrameShadowMap(manipulated), unchanged)
    } else {
        (shadow, true)
    };
    let surfaces = SurfaceDistances::new(&camera, frame)?;
    times.camera_depth = stopwatch.lap();
    let dark_frame = frame_is_dark(frame, &camera, &shadow, &surfaces);
    let marcher = Marcher::new(&shadow, frame.sun, frame.medium, frame.settings.steps)
        .with_dark_walks(dark_frame);
    let tint = frame.medium.albedo.as_dvec3()
        * frame.medium.extinction as f64
        * frame.sun.irradiance().as_dvec3();
    let light_travel = frame.sun.direction.as_dvec3().normalize();
    let to_pixel = |sample: RaySample, ray: &Ray| PixelSample {
        radiance: tint
            * (sample.scattering * phase::evaluate(frame.medium, light_travel, ray.direction)),
        alpha: sample.alpha,
        visibility: sample.visibility,
    };
    let reference =
        |ray: &Ray, t_start: f64, t_end: f64| to_pixel(marcher.march(ray, t_start, t_end), ray);
    // The fast methods' fallback near epipoles and for rays they decline.
    let fallback = |ray: &Ray, t_start: f64, t_end: f64| {
        to_pixel(marcher.march_fallback(ray, t_start, t_end), ray)
    };
    let rectify = match frame.settings.method {
        Method::Reference => None,
        Method::MinMax => Some(RectifyDesc::min_max(frame.settings.epipolar_slices)),
        Method::Prefiltered => Some(RectifyDesc::prefiltered(frame.settings.epipolar_slices)),
    };
    let max_distance = frame.settings.max_distance as f64;
    // Prefiltering reads each slice only as far as the frame's rays reach along it.
    let reaches = std::cell::Cell::new(None);
    let partial = CpuPartialResampler {
        lengths: |map: &EpipolarMap| {
            let along = slice_reaches(map, &camera, &surfaces.farthest, max_distance);
            let read = along.iter().map(|&s| samples_read(map, s)).collect();
            reaches.set(Some(along));
            read
        },
    };
    let resampler: &dyn Resampler = match frame.settings.method {
        Method::Prefiltered => &partial,
        _ => &CpuResampler,
    };
    let map = match rectify {
        Some(desc) => EpipolarMap::rectify_with(
            &camera,
            &shadow,
            &frame.geometry,
            light_travel,
            max_distance,
            frame.rectification(),
            &desc,
            resampler,
        )?,
        None => None,
    };
    // Rectification is undefined for an orthographic camera looking straight along the
    // light; the reference handles that view as it does any other.
    let Some(map) = map else {
        let layers = shade_pixels(
            &camera,
            &surfaces,
            &marcher,
            frame.settings,
            light_travel,
            shadowed_ends,
            frame.settings.effective_adaptive_tolerance(),
            control,
            |queries, out| {
                for (query, out) in queries.iter().zip(out) {
                    *out = reference(&query.ray, query.t_start, query.t_end);
                }
            },
            &mut times,
        )?;
        times.shading = stopwatch.lap();
        return Ok((layers, times));
    };
    control.check()?;
    times.rectify = stopwatch.lap();
    times.rectified_bytes = map.memory_bytes();
    let block = frame.settings.epipole_block as f64;
    let epipoles: Vec<[f64; 2]> = epipoles_in_image(&camera, &shadow, block).collect();
    let near_epipole = |pixel: [f64; 2]| {
        epipoles
            .iter()
            .any(|e| (pixel[0] - e[0]).abs() <= block && (pixel[1] - e[1]).abs() <= block)
    };
    let mipmap;
    let prefiltered;
    // A batch of rays at a time, `None` for each the method declines.
    type FastMethod<'f> = Box<dyn Fn(&[RayQuery], &mut [Option<RaySample>]) + Sync + 'f>;
    let fast: FastMethod = match frame.settings.method {
        Method::Reference => Box::new(|_, out| out.fill(None)),
        Method::MinMax => {
            mipmap = MinMaxMipmap::build(&map)?;
            times.structure_bytes = mipmap.memory_bytes();
            let method = MinMaxMethod::new(&map, &mipmap, frame.sun, frame.medium);
            Box::new(move |queries, out| {
                for (query, out) in queries.iter().zip(out) {
                    *out = method.march(&query.ray, query.t_start, query.t_end);
                }
            })
        }
        Method::Prefiltered => {
            // Every epipole ahead of the camera, however far off the image.
            let ahead: Vec<[f64; 2]> = epipoles_in_image(&camera, &shadow, f64::INFINITY).collect();
            // A projective map was rasterized whole.
            let reaches = reaches
                .into_inner()
                .unwrap_or_else(|| slice_reaches(&map, &camera, &surfaces.farthest, max_distance));
            let planning = Stopwatch::start();
            let plan = PrefilteredPlan::new(
                &map,
                &camera,
                &ahead,
                &prefiltered_desc(frame, dark_frame),
                frame.sun,
                frame.medium,
                Some(&reaches),
            )?;
            times.planning = planning.elapsed();
            prefiltered = Prefiltered::from_plan(plan, prefix)?;
            times.structure_bytes = prefiltered.memory_bytes();
            let method = &prefiltered;
            Box::new(move |queries, out| {
                method.march_many(
                    queries.len(),
                    |i| (&queries[i].ray, queries[i].t_start, queries[i].t_end),
                    out,
                )
            })
        }
    };
    times.prepare = stopwatch.lap();
    let (fast_rays, walked_rays) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let layers = shade_pixels(
        &camera,
        &surfaces,
        &marcher,
        frame.settings,
        light_travel,
        shadowed_ends,
        frame.settings.effective_adaptive_tolerance(),
        control,
        |queries, out| {
            let mut fast_samples = vec![None; queries.len()];
            fast(queries, &mut fast_samples);
            let mut walked = 0;
            for ((query, fast_sample), out) in queries.iter().zip(fast_samples).zip(out) {
                let (ray, t0, t1) = (&query.ray, query.t_start, query.t_end);
                *out = match fast_sample {
                    Some(sample) if !near_epipole(query.pixel) => to_pixel(sample, ray),
                    _ => {
                        walked += 1;
                        fallback(ray, t0, t1)
                    }
                };
            }
            fast_rays.fetch_add(queries.len(), Ordering::Relaxed);
            walked_rays.fetch_add(walked, Ordering::Relaxed);
        },
        &mut times,
    )?;
    times.shading = stopwatch.lap();
    (times.fast_rays, times.walked_rays) = (fast_rays.into_inner(), walked_rays.into_inner());
    Ok((layers, times))
}

/// The prefiltered method's description for `frame`, with whether the frame is nearly
/// dark ([`frame_is_dark`]): the CPU and GPU frames plan alike.
pub(crate) fn prefiltered_desc(frame: &Frame, dark_frame: bool) -> PrefilteredDesc {
    PrefilteredDesc {
        dark_frame,
        ..PrefilteredDesc::from_settings(frame.settings)
    }
}

/// Whether a prefiltered frame in open fog under light from above is nearly dark: nine in
/// ten or more of a sparse grid of its rays, walked exactly, see less than
/// [`DARK_LOOKUP_VISIBILITY`] of the sun. Prefiltering's residue, about 0.002–0.01 of visibility where a ray crosses
/// shadows, is then as large as the frame's light, and its dark lookups are walked instead
/// ([`crate::prefiltered::dark_lookup_limit`], which already walks them in a box and under
/// light from below): inside `colonnade` with light through a few gaps, a frame read 18.7%
/// off the reference, 4.6% so. In the built-in scenes' views dark rays are a few among lit
/// ones, and the probe finds no dark frame. Each ray is walked in lengthening pieces, and
/// stops once it has seen enough light: a lit frame's probe ends near the camera.
pub(crate) fn frame_is_dark(
    frame: &Frame,
    camera: &CameraModel,
    shadow: &ShadowMap,
    surfaces: &SurfaceDistances,
) -> bool {
    const ACROSS: u32 = 16;
    const DOWN: u32 = 9;
    const PIECES: i32 = 8;
    let medium = frame.medium;
    if frame.settings.method != Method::Prefiltered
        || !matches!(medium.extent, Extent::Unbounded)
        || frame.sun.direction.z > 0.0
    {
        return false;
    }
    let marcher = Marcher::new(shadow, frame.sun, medium, frame.settings.steps);
    let max_distance = frame.settings.max_distance as f64;
    let sigma = medium.extinction as f64;
    let ss = surfaces.supersampling as usize;
    let sample_width = camera.width as usize * ss;
    // Whether the ray sees at least the dark limit of its unshadowed light; `None` where
    // it crosses no medium.
    let lit_enough = |k: u32| {
        let x = (((k % ACROSS) as f64 + 0.5) * camera.width as f64 / ACROSS as f64).floor();
        let y = (((k / ACROSS) as f64 + 0.5) * camera.height as f64 / DOWN as f64).floor();
        let surface = surfaces.distances[y as usize * ss * sample_width + x as usize * ss];
        let ray = camera.ray(x + 0.5, y + 0.5);
        let t_start = camera.clip_start * ray.distance_per_depth;
        let length = (surface as f64).min(max_distance) - t_start;
        let unshadowed = integral_exp(sigma, length);
        if !(length > 0.0 && unshadowed > 0.0) {
            return None;
        }
        let (mut seen, mut from) = (0.0, t_start);
        for piece in (0..PIECES).rev() {
            let to = t_start + length * 0.5f64.powi(piece);
            let attenuation = (-sigma * (from - t_start)).exp();
            seen += attenuation * marcher.walk_texels(&ray, from, to).scattering;
            if seen >= DARK_LOOKUP_VISIBILITY * unshadowed {
                return Some(true);
            }
            from = to;
        }
        Some(false)
    };
    let (dark, through_medium) = (0..ACROSS * DOWN)
        .into_par_iter()
        .filter_map(lit_enough)
        .map(|lit| (usize::from(!lit), 1))
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    through_medium > 0 && 10 * dark >= 9 * through_medium
}

/// One depth sample's ray, from the camera's clip start to its surface or the max
/// distance, and the pixel position it was shot through.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RayQuery {
    pub pixel: [f64; 2],
    pub ray: Ray,
    pub t_start: f64,
    /// Where shading integrates the light to: `ray_end`, or before it where the ray ends
    /// on the unlit side of a surface ([`crate::shadowed_end`]).
    pub t_end: f64,
    /// Where the ray ends: at its surface or the max distance.
    pub ray_end: f64,
}

/// One sample's result, before averaging into its pixel.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PixelSample {
    pub radiance: DVec3,
    pub alpha: f64,
    pub visibility: f64,
}

/// A frame's shadow map, whose targets are kept for the next frame's when the frame is
/// done with it. `ShadowMap` hands its fields out to callers, so it cannot keep them
/// itself when dropped.
struct FrameShadowMap(ShadowMap);

impl std::ops::Deref for FrameShadowMap {
    type Target = ShadowMap;

    fn deref(&self) -> &ShadowMap {
        &self.0
    }
}

impl Drop for FrameShadowMap {
    fn drop(&mut self) {
        keep_map_targets(
            std::mem::take(&mut self.0.depth),
            std::mem::take(&mut self.0.ids),
        );
    }
}

/// Ray distance to the first surface for every depth sample, +∞ for background.
pub(crate) struct SurfaceDistances {
    /// Samples per pixel along each axis.
    pub supersampling: u32,
    pub distances: Vec<f32>,
    /// The farthest per block of pixels, which bounds how far rays read the rectified map.
    pub farthest: FarthestPerBlock,
}

impl Drop for SurfaceDistances {
    fn drop(&mut self) {
        keep_camera_depth(std::mem::take(&mut self.distances));
    }
}

impl SurfaceDistances {
    pub(crate) fn new(camera: &CameraModel, frame: &Frame) -> Result<Self> {
        Ok(match frame.camera_depth {
            Some(given) => Self::from_given(camera, given),
            None => Self::rasterized(camera, frame)?,
        })
    }

    /// [`SurfaceDistances::new`] with a rasterized camera depth from `rasterizer`.
    pub(crate) fn new_with(
        camera: &CameraModel,
        frame: &Frame,
        rasterizer: &dyn Rasterizer,
    ) -> Result<Self> {
        Ok(match frame.camera_depth {
            Some(given) => Self::from_given(camera, given),
            None => {
                let ss = frame.settings.supersampling;
                let (pixel_from_world, desc) = camera_raster(camera, ss);
                let target =
                    rasterizer.rasterize(frame.seen_geometry(), &pixel_from_world, &desc)?;
                Self::from_planar(camera, ss, target.depth)
            }
        })
    }

    fn rasterized(camera: &CameraModel, frame: &Frame) -> Result<Self> {
        let ss = frame.settings.supersampling;
        let (pixel_from_world, desc) = camera_raster(camera, ss);
        let planar = rasterize_depth(frame.seen_geometry(), &pixel_from_world, &desc)?.depth;
        Ok(Self::from_planar(camera, ss, planar))
    }

    /// Ray distances from a planar depth of `ss`² samples per pixel, converted in place.
    fn from_planar(camera: &CameraModel, ss: u32, mut planar: Vec<f32>) -> Self {
        let width = (camera.width * ss) as usize;
        let mut farthest = FarthestPerBlock::for_image(camera.width, camera.height);
        let band_rows = FarthestPerBlock::band_rows(ss);
        // Row by row, so that a sample's column is a count rather than a division, and
        // the row's stretches vectorize; a band of blocks' rows at a time, whose farthest
        // distances are then found while the band is in cache.
        planar
            .par_chunks_mut((width * band_rows).max(1))
            .zip(farthest.values.par_chunks_mut(farthest.across.max(1)))
            .enumerate()
            .for_each(|(band, (rows, far))| {
                for (r, row) in rows.chunks_mut(width.max(1)).enumerate() {
                    let y = band * band_rows + r;
                    let py = (y as f64 + 0.5) / ss as f64;
                    for (x, depth) in row.iter_mut().enumerate() {
                        let stretch = camera.distance_per_depth((x as f64 + 0.5) / ss as f64, py);
                        *depth = (*depth as f64 * stretch) as f32;
                    }
                }
                FarthestPerBlock::fold_band(rows, width, ss, far);
            });
        Self {
            supersampling: ss,
            distances: planar,
            farthest,
        }
    }

    fn from_given(camera: &CameraModel, given: CameraDepth) -> Self {
        let width = camera.width;
        let distances: Vec<f32> = given
            .values
            .par_iter()
            .enumerate()
            .map(|(i, &value)| {
                let (x, y) = ((i as u32 % width) as f64, (i as u32 / width) as f64);
                let stretch = camera.distance_per_depth(x + 0.5, y + 0.5);
                let (planar, distance) = match given.kind {
                    DepthKind::Planar => (value as f64, value as f64 * stretch),
                    DepthKind::RayDistance => (value as f64 / stretch, value as f64),
                };
                if planar > camera.clip_end {
                    f32::INFINITY
                } else {
                    distance as f32
                }
            })
            .collect();
        let farthest = FarthestPerBlock::of(&distances, camera.width, camera.height, 1);
        Self {
            supersampling: 1,
            distances,
            farthest,
        }
    }
}

/// The camera depth's projection and target with `ss`² samples per pixel: planar depth
/// (w for a pinhole camera) clipped to the camera's clip range.
pub fn camera_raster(camera: &CameraModel, ss: u32) -> (DMat4, RasterDesc) {
    let (width, height) = (camera.width * ss, camera.height * ss);
    let scale = DMat4::from_scale(DVec3::new(ss as f64, ss as f64, 1.0));
    let pixel_from_world = scale * camera.pixel_from_world();
    let desc = if camera.is_perspective() {
        RasterDesc::perspective(width, height, camera.clip_start, camera.clip_end)
    } else {
        RasterDesc {
            depth_range: (camera.clip_start, camera.clip_end),
            ..RasterDesc::orthographic(width, height)
        }
    };
    (pixel_from_world, desc)
}

/// Rows per parallel task and columns per tile when shading: neighbouring pixels share
/// epipolar slices, so a tile's rectified data stays in cache, where a whole image row
/// would not.
pub(crate) const SHADING_TILE: usize = 16;

/// Calls `visit(column, row)` for a band of `rows` rows and `width` columns in shading
/// order: tile by tile of [`SHADING_TILE`] columns, row by row within a tile. (Nested
/// `flat_map`s cost the adaptive pass a third more time.)
#[inline(always)]
pub(crate) fn for_each_in_tiles(width: usize, rows: usize, mut visit: impl FnMut(usize, usize)) {
    for tile_x in (0..width).step_by(SHADING_TILE) {
        for row in 0..rows {
            for x in tile_x..(tile_x + SHADING_TILE).min(width) {
                visit(x, row);
            }
        }
    }
}

/// Relative spread of a pixel's depth samples below which no edge runs through it.
pub const EDGE_DEPTH_SPREAD: f64 = 0.02;

/// The depth layer's value for a ray ending at `surface`: the max distance for background.
pub(crate) fn layer_depth(surface: f64, max_distance: f64) -> f64 {
    if surface.is_finite() {
        surface
    } else {
        max_distance
    }
}

/// The mean of a pixel's depth samples when they agree (all background, +∞, or all
/// surfaces within [`EDGE_DEPTH_SPREAD`] of each other); `None` at a depth edge.
pub fn uniform_surface(depths: impl Iterator<Item = f32>) -> Option<f64> {
    let (mut low, mut high, mut sum, mut count) = (f64::INFINITY, 0.0f64, 0.0, 0);
    for depth in depths {
        let depth = depth as f64;
        (low, high) = (low.min(depth), high.max(depth));
        sum += depth;
        count += 1;
    }
    if count == 0 {
        return None;
    }
    if low.is_infinite() {
        return Some(f64::INFINITY);
    }
    (high <= low * (1.0 + EDGE_DEPTH_SPREAD)).then(|| sum / count as f64)
}

/// Runs `shade(queries, out)` on batches of depth samples' rays ([`RayQuery`]), averaging
/// samples into pixels, in parallel over rows.
/// With supersampling, a pixel whose depth samples agree ([`uniform_surface`]) is shaded
/// once at its centre, as MSAA shades once per pixel: only pixels at depth edges pay for
/// every sample. With a `tolerance` above 0, pixels are shaded adaptively
/// ([`shade_adaptively`]). Each pixel depends only on its own inputs (and adaptively, on
/// the shaded pixels next to it), so the output is bit-identical for any thread count.
/// Returns the layers, and records in `times` how many pixels were evaluated (at the
/// reduced size, if any), how many of those were shaded, and adaptive shading's passes.
#[allow(clippy::too_many_arguments)]
pub(crate) fn shade_pixels(
    camera: &CameraModel,
    surfaces: &SurfaceDistances,
    marcher: &Marcher,
    settings: &RenderSettings,
    light_travel: DVec3,
    shadowed_ends: bool,
    tolerance: f32,
    control: &RenderControl,
    shade: impl Fn(&[RayQuery], &mut [PixelSample]) + Sync,
    times: &mut StageTimes,
) -> Result<Layers> {
    let stride = settings.downsample;
    let ss = surfaces.supersampling as usize;
    let max_distance = settings.max_distance as f64;
    let rays = SampleRays {
        camera,
        surfaces,
        max_distance,
    };
    let tails = ShadowedTails {
        samples: DepthSamples::new(
            camera,
            &surfaces.distances,
            surfaces.supersampling,
            light_travel,
        ),
        shadow: marcher.shadow(),
        light_travel,
        max_distance,
    };
    // Queries end their light where they end on a surface's unlit side, and their
    // samples are completed over the whole ray, whichever method shades them.
    let shade = |queries: &mut [RayQuery], samples: &mut [PixelSample]| {
        if !shadowed_ends {
            return shade(queries, samples);
        }
        for query in queries.iter() {
            tails.prefetch(query);
        }
        for query in queries.iter_mut() {
            query.t_end = tails.lit_end(query);
        }
        shade(queries, samples);
        for (query, sample) in queries.iter().zip(samples) {
            if query.t_end < query.ray_end {
                (sample.alpha, sample.visibility) = marcher.dark_tail(
                    &query.ray,
                    query.t_start,
                    query.t_end,
                    query.ray_end,
                    sample.visibility,
                );
            }
        }
    };
    // Output sample (x, y) is one exact full-size pixel, also with downsampling.
    let full_pixel = |x: usize, y: usize| {
        (
            sample_pixel(x as u32, stride, camera.width) as usize,
            sample_pixel(y as u32, stride, camera.height) as usize,
        )
    };
    // Without supersampling, one ray a pixel: shaded straight into the pixels. The values
    // are the averaging's below, bit for bit: its sums start at zero (so each value is
    // added to zero here too, which turns −0 into +0 as there) and divide by one.
    let shade_one_ray_each = |pixels: &[(usize, usize)], out: &mut [Pixel]| {
        let mut queries: Vec<RayQuery> = pixels
            .iter()
            .map(|&(x, y)| {
                let (full_x, full_y) = full_pixel(x, y);
                let centre = [full_x as f64 + 0.5, full_y as f64 + 0.5];
                rays.query(centre, rays.surface(full_x, full_y, 0, 0) as f64)
            })
            .collect();
        let mut samples = vec![PixelSample::default(); queries.len()];
        shade(&mut queries, &mut samples);
        for ((out, sample), &(x, y)) in out.iter_mut().zip(&samples).zip(pixels) {
            let (full_x, full_y) = full_pixel(x, y);
            let surface = rays.surface(full_x, full_y, 0, 0) as f64;
            let radiance = DVec3::ZERO + sample.radiance;
            *out = Pixel {
                volume: [
                    radiance.x as f32,
                    radiance.y as f32,
                    radiance.z as f32,
                    (0.0 + sample.alpha) as f32,
                ],
                visibility: (0.0 + sample.visibility) as f32,
                depth: (0.0 + layer_depth(surface, max_distance)) as f32,
            };
        }
    };
    // The pixels' rays, shaded together, then averaged per pixel.
    let shade_batch = |pixels: &[(usize, usize)], out: &mut [Pixel]| {
        if ss == 1 {
            return shade_one_ray_each(pixels, out);
        }
        let mut queries = Vec::with_capacity(pixels.len());
        // Per ray: its pixel's index in the batch and its depth for the depth layer.
        let mut owners = Vec::with_capacity(pixels.len());
        for (n, &(x, y)) in pixels.iter().enumerate() {
            let (full_x, full_y) = full_pixel(x, y);
            match rays.uniform(full_x, full_y) {
                // Shaded once, like MSAA: no edge runs through the pixel.
                Some(surface) => {
                    let centre = [full_x as f64 + 0.5, full_y as f64 + 0.5];
                    queries.push(rays.query(centre, surface));
                    owners.push((n, layer_depth(surface, max_distance)));
                }
                None => {
                    for sy in 0..ss {
                        for sx in 0..ss {
                            let pixel = [
                                full_x as f64 + (sx as f64 + 0.5) / ss as f64,
                                full_y as f64 + (sy as f64 + 0.5) / ss as f64,
                            ];
                            let surface = rays.surface(full_x, full_y, sx, sy) as f64;
                            queries.push(rays.query(pixel, surface));
                            owners.push((n, layer_depth(surface, max_distance)));
                        }
                    }
                }
            }
        }
        let mut samples = vec![PixelSample::default(); queries.len()];
        shade(&mut queries, &mut samples);
        let mut sums = vec![(PixelSample::default(), 0.0, 0.0); pixels.len()];
        for (&(n, depth), sample) in owners.iter().zip(&samples) {
            let (sum, depth_sum, count) = &mut sums[n];
            sum.radiance += sample.radiance;
            sum.alpha += sample.alpha;
            sum.visibility += sample.visibility;
            *depth_sum += depth;
            *count += 1.0;
        }
        for (out, (sum, depth_sum, count)) in out.iter_mut().zip(sums) {
            let radiance = sum.radiance / count;
            *out = Pixel {
                volume: [
                    radiance.x as f32,
                    radiance.y as f32,
                    radiance.z as f32,
                    (sum.alpha / count) as f32,
                ],
                visibility: (sum.visibility / count) as f32,
                depth: (depth_sum / count) as f32,
            };
        }
    };
    let width = reduced_size(camera.width, stride) as usize;
    let height = reduced_size(camera.height, stride) as usize;
    let (layers, shaded, passes) = if tolerance > 0.0 {
        // One depth sample a pixel: its surface is one load, which the passes between
        // shaded pixels make for every pixel they interpolate. Looked up through the
        // downsampling and the supersampling, it was a fifth of the last pass.
        let gathered: Vec<f32>;
        let one_sample_each = match (ss, stride) {
            (1, 1) => Some(&surfaces.distances[..width * height]),
            (1, _) => {
                gathered = (0..height)
                    .flat_map(|y| (0..width).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        let (full_x, full_y) = full_pixel(x, y);
                        rays.surface(full_x, full_y, 0, 0)
                    })
                    .collect();
                Some(gathered.as_slice())
            }
            _ => None,
        };
        shade_adaptively(
            width,
            height,
            tolerance,
            settings.max_distance,
            Some(EpipolarLines::of_view(camera, light_travel, stride)),
            SurfaceCoordinate::of_camera(camera),
            control,
            |x, y| match one_sample_each {
                Some(distances) => Some(distances[y * width + x] as f64),
                None => {
                    let (full_x, full_y) = full_pixel(x, y);
                    rays.uniform(full_x, full_y)
                }
            },
            shade_batch,
        )?
    } else {
        let mut layers = Layers::for_overwrite(width as u32, height as u32)?;
        layers.par_bands_mut(SHADING_TILE).for_each(|mut band| {
            if control.is_cancelled() {
                return;
            }
            // A tile at a time: a whole band's pixels, rays and results took buffers large
            // enough to be mapped afresh every band, whose page faults were 7% of the
            // profile of `torus` shaded every pixel; tile by tile its frame took about a
            // fifth less time.
            let (first_row, rows) = (band.first_row, band.rows);
            let tile_len = SHADING_TILE * rows;
            let mut pixels = Vec::with_capacity(tile_len);
            let mut shaded = vec![Pixel::default(); tile_len];
            let mut flush = |pixels: &mut Vec<(usize, usize)>| {
                if pixels.is_empty() {
                    return;
                }
                let shaded = &mut shaded[..pixels.len()];
                shade_batch(pixels, shaded);
                for (&(x, y), pixel) in pixels.iter().zip(shaded.iter()) {
                    band.set((y - first_row) * width + x, pixel);
                }
                pixels.clear();
            };
            for_each_in_tiles(width, rows, |x, row| {
                pixels.push((x, first_row + row));
                if pixels.len() == tile_len {
                    flush(&mut pixels);
                }
            });
            flush(&mut pixels);
            control.advance(rows as u64);
        });
        (layers, width * height, AdaptivePasses::default())
    };
    control.check()?;
    (times.pixels, times.shaded_pixels, times.passes) = (width * height, shaded, passes);
    if stride == 1 {
        return Ok(layers);
    }
    let mut upsampled = Layers::for_overwrite(camera.width, camera.height)?;
    upsampled
        .depth
        .par_iter_mut()
        .zip(&surfaces.distances)
        .for_each(|(out, &d)| *out = layer_depth(d as f64, max_distance) as f32);
    let opacity = marcher
        .in_box()
        .then(|| {
            opacity_guide(&layers, camera.width, camera.height, stride, |x, y| {
                rays.opacity(marcher, x as usize, y as usize)
            })
        })
        .transpose()?
        .flatten();
    let upsampled = joint_bilateral_into(&layers, upsampled, opacity.as_deref(), stride);
    if let Some(guide) = opacity {
        keep_opacity_guide(guide);
    }
    Ok(upsampled)
}

/// The rays of a frame's depth samples, as shading casts them: one per pixel, or with
/// supersampling one per depth sample where a depth edge runs through the pixel.
pub(crate) struct SampleRays<'a> {
    pub camera: &'a CameraModel,
    pub surfaces: &'a SurfaceDistances,
    pub max_distance: f64,
}

impl SampleRays<'_> {
    /// The ray through `pixel` (continuous full-size coordinates) to `surface`.
    fn query(&self, pixel: [f64; 2], surface: f64) -> RayQuery {
        let ray = self.camera.ray(pixel[0], pixel[1]);
        let t_start = self.camera.clip_start * ray.distance_per_depth;
        let ray_end = surface.min(self.max_distance);
        RayQuery {
            pixel,
            ray,
            t_start,
            t_end: ray_end,
            ray_end,
        }
    }

    /// The surface distance of depth sample (sx, sy) of full-size pixel (x, y).
    #[inline]
    fn surface(&self, x: usize, y: usize, sx: usize, sy: usize) -> f32 {
        let ss = self.surfaces.supersampling as usize;
        let sample_width = self.camera.width as usize * ss;
        self.surfaces.distances[(y * ss + sy) * sample_width + x * ss + sx]
    }

    /// The surface a whole pixel sees; `None` where a depth edge runs through it.
    fn uniform(&self, x: usize, y: usize) -> Option<f64> {
        let ss = self.surfaces.supersampling as usize;
        if ss == 1 {
            return Some(self.surface(x, y, 0, 0) as f64);
        }
        uniform_surface(
            (0..ss)
                .flat_map(|sy| (0..ss).map(move |sx| (sx, sy)))
                .map(|(sx, sy)| self.surface(x, y, sx, sy)),
        )
    }

    /// The opacity shading gives full-size pixel (x, y) in a box medium
    /// ([`Marcher::box_opacity`]). Only reduced frames ask, and they do not supersample
    /// ([`RenderSettings::validate`]): one ray a pixel.
    pub(crate) fn opacity(&self, marcher: &Marcher, x: usize, y: usize) -> f32 {
        debug_assert_eq!(self.surfaces.supersampling, 1);
        let query = self.query(
            [x as f64 + 0.5, y as f64 + 0.5],
            self.surface(x, y, 0, 0) as f64,
        );
        marcher
            .box_opacity(&query.ray, query.t_start, query.t_end)
            .unwrap_or(0.0) as f32
    }
}

/// Where shading's rays end their light ([`crate::shadowed_end::lit_end`]).
struct ShadowedTails<'a> {
    samples: DepthSamples<'a>,
    shadow: &'a ShadowMap,
    light_travel: DVec3,
    max_distance: f64,
}

impl ShadowedTails<'_> {
    /// Fetches what [`ShadowedTails::lit_end`] reads first, a batch ahead: the rows
    /// beside sparse shaded pixels' depth samples are rarely in cache.
    fn prefetch(&self, query: &RayQuery) {
        if query.ray_end < self.max_distance {
            self.samples.prefetch_around(query.pixel);
        }
    }

    fn lit_end(&self, query: &RayQuery) -> f64 {
        // A ray that ends in the fog (background, or at the max distance) ends on no
        // surface.
        if !(query.ray_end > query.t_start && query.ray_end < self.max_distance) {
            return query.ray_end;
        }
        lit_end(
            &self.samples,
            self.shadow,
            self.light_travel,
            query.pixel,
            &query.ray,
            query.t_start,
            query.ray_end,
        )
    }
}

impl<'a> Frame<'a> {
    /// The triangles the camera sees.
    pub fn seen_geometry(&self) -> &Geometry<'a> {
        self.camera_geometry.as_ref().unwrap_or(&self.geometry)
    }

    /// The frame a scene description describes, with the camera depth rasterized.
    pub fn of_scene(scene: &'a Scene, geometry: &'a FlatGeometry) -> Self {
        Frame {
            camera: &scene.camera,
            sun: &scene.sun,
            medium: &scene.medium,
            settings: &scene.render,
            geometry: geometry.view(),
            camera_geometry: geometry.camera_view(),
            camera_depth: None,
            style: &scene.style,
        }
    }

    /// Checks every input, naming the first offending field.
    pub fn validate(&self) -> Result<()> {
        self.camera.validate()?;
        self.sun.validate()?;
        self.medium.validate()?;
        self.settings.validate()?;
        self.style.validate()?;
        let seen = self.seen_geometry();
        if self.geometry.triangles.is_empty() && seen.triangles.is_empty() {
            return Err(Error::invalid(
                "triangles",
                "the scene is empty: it has no triangles (add at least a ground plane)",
            ));
        }
        self.geometry.validate()?;
        if let Some(camera_geometry) = &self.camera_geometry {
            camera_geometry.validate()?;
        }
        if self.settings.downsample > 1
            && self.camera_depth.is_none()
            && self.settings.supersampling > 1
        {
            return Err(Error::invalid(
                "render.downsample",
                "cannot be combined with supersampling: evaluate at reduced size or supersample, not both",
            ));
        }
        if let Some(depth) = &self.camera_depth {
            let (width, height) = self.camera.image_size();
            depth.validate(width, height)?;
        }
        if self.style.manipulates_occluders()
            && self.settings.rectification == Rectification::Projective
        {
            return Err(Error::invalid(
                "render.rectification",
                "'projective' rasterizes the geometry into the rectified map, so the style's \
                 occluder operators (hole filling, silhouettes, hole creation), which act on \
                 the shadow map, would be lost; use 'auto' or 'epipolar' with them",
            ));
        }
        Ok(())
    }

    /// How the fast methods rectify. A projective map is rasterized from the geometry
    /// rather than resampled from the shadow map, so it cannot carry the style's occluder
    /// operators: with any, `auto` resamples epipolarly.
    pub fn rectification(&self) -> Rectification {
        if self.style.manipulates_occluders() {
            Rectification::Epipolar
        } else {
            self.settings.rectification
        }
    }
}

impl Geometry<'_> {
    /// `pixel_from_world` applied to the positions as they are stored, relative to the
    /// origin: composed in f64, so that its translation is small where the origin is near
    /// what it looks at.
    pub fn pixel_from_local(&self, pixel_from_world: &DMat4) -> DMat4 {
        *pixel_from_world * DMat4::from_translation(self.origin)
    }

    /// Checks the arrays against each other (a frame checks that it has triangles).
    pub fn validate(&self) -> Result<()> {
        if self.object_ids.len() != self.triangles.len() {
            return Err(Error::invalid(
                "object_ids",
                format!(
                    "has {} entries but there are {} triangles (give one id per triangle)",
                    self.object_ids.len(),
                    self.triangles.len()
                ),
            ));
        }
        check_triangles("", self.positions, self.triangles)?;
        match &self.cutouts {
            Some(cutouts) => cutouts.validate(self.positions.len(), self.triangles.len()),
            None => Ok(()),
        }
    }
}

impl CameraDepth<'_> {
    pub fn validate(&self, width: u32, height: u32) -> Result<()> {
        let expected = width as usize * height as usize;
        if self.values.len() != expected {
            return Err(Error::invalid(
                "camera_depth",
                format!(
                    "has {} values, expected {width}×{height} = {expected}",
                    self.values.len()
                ),
            ));
        }
        let pixel = |index: usize| (index as u32 % width, index as u32 / width);
        if let Some(index) = self.values.par_iter().position_first(|v| v.is_nan()) {
            let (x, y) = pixel(index);
            return Err(Error::invalid(
                "camera_depth",
                format!("contains NaN at pixel ({x}, {y})"),
            ));
        }
        if let Some(index) = self.values.par_iter().position_first(|&v| v < 0.0) {
            let (x, y) = pixel(index);
            return Err(Error::invalid(
                "camera_depth",
                format!(
                    "contains the negative distance {} at pixel ({x}, {y})",
                    self.values[index]
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::builtin_scene;

    /// Whether [`frame_is_dark`] finds `scene` dark.
    fn probed_dark(scene: &Scene) -> bool {
        let geometry = FlatGeometry::from_scene(scene);
        let frame = Frame::of_scene(scene, &geometry);
        let camera = CameraModel::new(frame.camera);
        let shadow = ShadowMap::build(
            &camera,
            frame.sun,
            frame.medium,
            frame.settings,
            &frame.geometry,
        )
        .unwrap();
        let surfaces = SurfaceDistances::new(&camera, &frame).unwrap();
        frame_is_dark(&frame, &camera, &shadow, &surfaces)
    }

    /// The built-in scenes' views are lit, so their frames keep looking dark rays up. In a
    /// box, and under light from below, dark lookups are walked anyway, and no probe is
    /// needed: `plane` lit from below is nearly black (mean radiance 0.00015). A dark frame
    /// in open fog: `a_nearly_dark_frame_in_thin_fog_walks_its_dark_lookups`.
    #[test]
    fn only_frames_in_open_fog_lit_from_above_are_probed_and_lit_ones_are_not_dark() {
        for name in crate::BUILTIN_SCENES {
            let mut scene = builtin_scene(name).unwrap();
            (scene.camera.width, scene.camera.height) = (320, 180);
            assert!(!probed_dark(&scene), "{name}");
        }
        let mut scene = builtin_scene("plane").unwrap();
        (scene.camera.width, scene.camera.height) = (320, 180);
        scene.sun.direction.z = scene.sun.direction.z.abs().max(0.3);
        assert!(!probed_dark(&scene));
    }

    /// What the bench splits a frame's stages into: prefiltering's plan within its
    /// preparation and adaptive shading's passes within the shading, each taking some of
    /// it; the min-max method plans nothing, and shading every pixel has no passes.
    #[test]
    fn stage_times_split_preparation_and_shading_where_they_apply() {
        let mut scene = builtin_scene("torus").unwrap();
        (scene.camera.width, scene.camera.height) = (320, 180);
        let timed = |scene: &Scene| render_scene_timed(scene, &RenderControl::new()).unwrap().1;
        scene.render.method = Method::Prefiltered;
        let times = timed(&scene);
        assert!(
            times.planning > 0.0 && times.planning < times.prepare,
            "{times:?}"
        );
        let passes = times.passes;
        assert!(
            passes.lattice > 0.0 && passes.finer_grid > 0.0 && passes.between > 0.0,
            "{times:?}"
        );
        let total = passes.lattice + passes.finer_grid + passes.between;
        assert!(total <= times.shading, "{times:?}");
        // Every pass shades some points, and together they shade the frame's shaded
        // pixels, one ray each, all asked of the method.
        let each = [
            passes.lattice_shaded,
            passes.finer_grid_shaded,
            passes.between_shaded,
        ];
        assert!(each.iter().all(|&n| n > 0), "{times:?}");
        assert_eq!(each.iter().sum::<usize>(), times.shaded_pixels);
        assert_eq!(times.fast_rays, times.shaded_pixels);
        assert!(times.walked_rays < times.fast_rays, "{times:?}");
        scene.render.method = Method::MinMax;
        let times = timed(&scene);
        assert!(
            times.planning == 0.0 && times.passes.lattice > 0.0,
            "{times:?}"
        );
        scene.render.adaptive_tolerance = 0.0;
        let times = timed(&scene);
        assert_eq!(times.passes, AdaptivePasses::default());
        assert_eq!(times.fast_rays, times.pixels);
        scene.render.method = Method::Reference;
        assert_eq!(timed(&scene).fast_rays, 0);
    }

    /// Rays the fast methods decline are counted: near an on-screen sun (colonnade's
    /// default view) the block around the epipole and the short rays beside it are all
    /// walked exactly; with 2×2 samples, a pixel that a depth edge runs through asks for
    /// four rays and any other for one.
    #[test]
    fn walked_rays_are_counted_where_the_fast_methods_decline_them() {
        let mut scene = builtin_scene("colonnade").unwrap();
        (scene.camera.width, scene.camera.height) = (320, 180);
        scene.render.adaptive_tolerance = 0.0;
        let times = render_scene_timed(&scene, &RenderControl::new()).unwrap().1;
        let block = scene.render.epipole_block as usize;
        assert!(
            times.walked_rays >= block * block && times.walked_rays < times.fast_rays / 2,
            "{times:?}"
        );
        scene.render.supersampling = 2;
        let times = render_scene_timed(&scene, &RenderControl::new()).unwrap().1;
        assert!(
            times.pixels < times.fast_rays && times.fast_rays < 4 * times.pixels,
            "{times:?}"
        );
    }
}
