//! Rectification of the shadow map: epipolar resampling (dissertation §4.4.1) or
//! projective rasterization (§4.4.2, see [`crate::projective`]).
//!
//! View rays projected into the shadow-map plane are lines: through the epipole (the
//! camera's position in the map) for a pinhole camera, parallel to each other for an
//! orthographic one. Each such line is a *slice*, sampled along a coordinate `s`: at
//! regular steps of `s` when resampling, at regular steps of `1/s` in a projective map.
//! A ray with the light-space depth `w(s) = w₀ + k·(s − s₀)` is lit at `s` when
//! `w(s) ≤ D(s) + bias`. The rectified map stores, per slice sample, a value `K(s)` with
//! a ray-dependent `threshold`, such that the test becomes `threshold ≤ K(s)`: one
//! constant per ray along the whole slice, which is what min-max mipmaps and prefiltering
//! need.
//! - Pinhole: `K(s) = (D(s) + bias − w_c)/s` and `threshold = k` (the ray's slope).
//! - Orthographic: `K(s) = D(s) + bias − k·s` and `threshold = w₀ − k·s₀` (all rays share k).
//! - Projective: `s` is the distance X from the camera along the bisectrix, the stored
//!   depth is Z/X (light depth from the camera over X), so `K(s) = (Z + bias)/s` and
//!   `threshold = Z/X` of the ray: the pinhole case with the camera's depth as origin.

use std::f64::consts::TAU;

use glam::{DMat4, DVec2, DVec3};
use rayon::prelude::*;

use crate::camera::{CameraModel, Ray};
use crate::error::{Result, Sizing};
use crate::projective::{choose, ProjectiveGrid};
use crate::raster::{rasterize, RasterDesc};
use crate::render::Geometry;
use crate::scene::Rectification;
use crate::shadow_map::ShadowMap;
use crate::spare::Spare;

/// How densely to rectify.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RectifyDesc {
    /// Number of slices; 0 chooses `slices_per_texel` at the far end of a radial map (and
    /// as dense as that halfway out for evenly spaced parallel slices), up to
    /// `max_auto_slices`.
    pub slices: u32,
    pub slices_per_texel: f64,
    pub max_auto_slices: u32,
    /// Samples along a slice per shadow-map texel.
    pub samples_per_texel: f64,
}

impl RectifyDesc {
    /// Min-max walks exact lit spans, so it affords dense samples: two per texel keep
    /// resampling from moving shadow edges by up to a texel. Slices two texels apart at
    /// the far end: blending neighbours keeps edges sharp, and denser slices measurably
    /// add nothing but memory.
    pub fn min_max(slices: u32) -> Self {
        Self {
            slices,
            slices_per_texel: 0.5,
            max_auto_slices: 8192,
            samples_per_texel: 2.0,
        }
    }

    /// Prefiltering stores 2M + 1 prefix sums per sample, so it samples once per texel
    /// and keeps at most 1024 slices.
    pub fn prefiltered(slices: u32) -> Self {
        Self {
            slices,
            slices_per_texel: 0.25,
            max_auto_slices: 1024,
            samples_per_texel: 2.0,
        }
    }
}

/// How slices are laid out in the shadow-map plane (texel units).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Layout {
    /// Slices radiate from `epipole` at angles `first_angle + j·angle_step`.
    Radial {
        epipole: DVec2,
        camera_depth: f64,
        first_angle: f64,
        angle_step: f64,
        full_circle: bool,
    },
    /// Slices are lines along `direction`, at offsets `first_offset + j·offset_step`
    /// along `normal`; `slope` is the shared depth change per texel along a ray.
    Parallel {
        direction: DVec2,
        normal: DVec2,
        first_offset: f64,
        offset_step: f64,
        slope: f64,
    },
    /// Slices are the planes Y/X = `first_tan + j·tan_step` of the projective frame
    /// `view_from_world` (X along its bisectrix, Z along the light, camera at 0); `s` is X.
    Projective {
        view_from_world: DMat4,
        first_tan: f64,
        tan_step: f64,
    },
}

impl Layout {
    /// Whether K = N/s within a sample (pinhole cameras), rather than affine in s.
    fn is_reciprocal(&self) -> bool {
        !matches!(self, Layout::Parallel { .. })
    }
}

/// Where samples sit along every slice.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Spacing {
    /// Sample i covers s ∈ [first + i·step, first + (i+1)·step).
    Uniform { first: f64, step: f64 },
    /// Uniform in 1/s, as a projective map's columns: sample i covers the s > 0 with
    /// 1/s ∈ (first − (i+1)·step, first − i·step].
    Reciprocal { first: f64, step: f64 },
}

impl Spacing {
    /// s at the continuous sample coordinate `x` (sample i spans x ∈ [i, i + 1]).
    #[inline]
    fn s_at(&self, x: f64) -> f64 {
        match *self {
            Spacing::Uniform { first, step } => first + x * step,
            Spacing::Reciprocal { first, step } => 1.0 / (first - x * step),
        }
    }

    /// The inverse of [`Spacing::s_at`]; −∞ for s at or behind the projective camera.
    #[inline]
    fn coordinate(&self, s: f64) -> f64 {
        match *self {
            Spacing::Uniform { first, step } => (s - first) / step,
            Spacing::Reciprocal { first, step } => {
                if s > 0.0 {
                    (first - 1.0 / s) / step
                } else {
                    f64::NEG_INFINITY
                }
            }
        }
    }
}

/// Rays crossing fewer shadow-map texels than this are declined by the fast methods and
/// computed exactly instead ([`crate::reference::Marcher::march_fallback`], one lookup per
/// texel). A ray ending on lit ground closes in on the ground's key over its last texels,
/// where prefiltering's smooth step reads it partly shadowed, and rectified lookups resolve
/// a ray's ends only to a sample: on a short ray those texels are much of its light. An
/// orthographic view of `tree` 10–30° off the light's travel, the sun behind the camera,
/// read 8.5–3.7% too dark with 16 texels (0–0.8% with 64), `colonnade` near its on-screen
/// sun 0.74% (0.24%). A walk costs about what a lookup does at this length: 1080p frames of
/// the default views took as long or less (exact neighbours agree, so adaptive shading
/// shades fewer pixels: `colonnade` 43% instead of 51%, and 23% less time with the sun in
/// view), orthographic and sideways views up to 12% more; 128 texels cost the default
/// views 8–10% more.
pub const SHORT_RAY_TEXELS: f64 = 64.0;
/// Fewest texels a stretch of a ray must cross to be looked up on its own: its first
/// [`LOOKUP_DEPTH`] of optical depth in dense fog ([`EpipolarMap::is_short_in_medium`]) and
/// each piece of it inside a box. Fewer than the whole ray needs, because such rays are
/// long and walking them exactly would cost more than their stretch's lookups.
pub const SHORT_STRETCH_TEXELS: f64 = 16.0;
/// Optical depth from a ray's entry into the medium within which it must cross
/// [`SHORT_STRETCH_TEXELS`] for the fast methods' lookups ([`EpipolarMap::is_short_in_medium`]).
/// In dense fog a ray's light comes from its first few optical depths, so it is as short
/// as that stretch however long it runs: `colonnade` seen towards the sun read 3.9% off
/// with prefiltering (2.7% with min-max) at σ = 0.6 /m and 9.4% (4.9%) at σ = 1.5 /m,
/// from ringing and texel-sized errors near the camera that a long ray averages out. With
/// one optical depth they read 1.6% (1.2%) and 0.4% (0.4%), and at σ = 0.2 /m 2.3 → 2.0%;
/// frames at the scenes' own 0.05 /m are unchanged, at 0.6 /m cost 0–7% more, and at
/// 1.5 /m up to 1.5× (`plane` and `torus`, most of whose rays are then walked). Half an
/// optical depth reads 0.2% at 0.6 /m but costs up to 3× there.
pub const LOOKUP_DEPTH: f64 = 1.0;

/// Where one view ray lies in the rectified map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RaySlice {
    /// Fractional slice coordinate: between slice `floor` and the next.
    pub slice: f64,
    /// Position along the slice at t = 0, and s per unit of t (texels for the epipolar
    /// layouts, scene units for the projective one).
    pub s_origin: f64,
    pub s_per_t: f64,
    /// The ray is lit at `s` when `threshold ≤ K(s)`.
    pub threshold: f64,
}

impl RaySlice {
    pub fn t_at(&self, s: f64) -> f64 {
        (s - self.s_origin) / self.s_per_t
    }

    /// Whether every coordinate is a finite number.
    fn is_finite(&self) -> bool {
        [self.slice, self.s_origin, self.s_per_t, self.threshold]
            .iter()
            .all(|v| v.is_finite())
    }
}

/// Fills an epipolar map's values from the shadow map: the CPU's loop or a GPU's.
pub trait Resampler {
    /// Fills `map.values` (the layout is set), slice by slice.
    fn resample(&self, map: &mut EpipolarMap, shadow: &ShadowMap) -> Result<()>;
}

/// The CPU backend's resampling.
pub struct CpuResampler;

impl Resampler for CpuResampler {
    fn resample(&self, map: &mut EpipolarMap, shadow: &ShadowMap) -> Result<()> {
        map.resample(shadow, None);
        Ok(())
    }
}

/// The CPU's resampling of each slice's first samples only, as many as `lengths` gives
/// per slice for the map's layout, the rest +∞ (lit): for a frame whose rays read no
/// farther.
pub struct CpuPartialResampler<F> {
    pub lengths: F,
}

impl<F: Fn(&EpipolarMap) -> Vec<usize>> Resampler for CpuPartialResampler<F> {
    fn resample(&self, map: &mut EpipolarMap, shadow: &ShadowMap) -> Result<()> {
        let lengths = (self.lengths)(map);
        map.resample(shadow, Some(&lengths));
        Ok(())
    }
}

/// How slices lie, for [`MapGeometry`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapLayout {
    Radial,
    Parallel,
    Projective,
}

/// [`EpipolarMap`]'s geometry as plain numbers: what [`EpipolarMap::locate`],
/// [`EpipolarMap::neighbours`], [`EpipolarMap::order_key`] and
/// [`EpipolarMap::sample_coordinate`] compute with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapGeometry {
    pub layout: MapLayout,
    /// Radial slices that go all the way round (an epipole in the image).
    pub full_circle: bool,
    /// Samples uniform in 1/s (projective maps) rather than in s.
    pub reciprocal_spacing: bool,
    pub spacing_first: f64,
    pub spacing_step: f64,
    /// The slice coordinate's origin and step: an angle (radial), an offset (parallel) or
    /// a tangent (projective).
    pub first: f64,
    pub step: f64,
    /// Parallel slices: their direction, normal, and the shared depth slope.
    pub along: DVec2,
    pub normal: DVec2,
    pub slope: f64,
    /// Radial slices: the epipole (texels) and the camera's light depth.
    pub epipole: DVec2,
    pub camera_depth: f64,
    /// texel_from_world (radial, parallel) or view_from_world (projective).
    pub from_world: glam::DMat4,
    /// What a pinhole camera's K is scaled by before its key is bounded.
    pub key_scale: f64,
}

/// The rectified shadow map: `slices` rows of `samples` values of K. Sample i of every
/// slice covers [`EpipolarMap::sample_interval`]`(i)` of s.
#[derive(Clone, Debug)]
pub struct EpipolarMap {
    pub slices: u32,
    pub samples: u32,
    spacing: Spacing,
    pub values: Vec<f32>,
    layout: Layout,
    texel_from_world: glam::DMat4,
    /// What turns a pinhole camera's K into a slope free of units before
    /// [`EpipolarMap::order_key`] bounds it ([`key_scale`]).
    key_scale: f64,
    /// Per sample index, what turns K at a sample's centre into K at its ends (see
    /// [`EpipolarMap::sample_bounds`]); shared by all slices.
    bound_factors: Vec<[f32; 2]>,
}

/// The key of a reciprocal layout's `value` made a slope by `key_scale`: −s/(1 + |s|),
/// bounded to [−1, 1], with ±∞ at ∓1 ([`EpipolarMap::order_key`]). The infinite case is
/// a select rather than a branch, so that loops over samples vectorize.
#[inline(always)]
fn bounded_key(value: f64, key_scale: f64) -> f64 {
    let slope = value * key_scale;
    let bounded = -slope / (1.0 + slope.abs());
    if value.is_infinite() {
        -value.signum()
    } else {
        bounded
    }
}

/// The factor [`EpipolarMap::order_key`] scales K by for `layout`, of a shadow map whose
/// texels are `texel_size` scene units wide. A radial map's K is light depth over texels
/// along the slice, in scene units per texel: over the texel's size it is the slope of the
/// view ray against the light, the same in metres as in centimetres, so that keys and the
/// warps built from them do not depend on the scene's unit (they did: the same scene at
/// 100× its size rendered 0.01–0.26% apart). A projective map's K is Z/X, already free of
/// units, and a parallel map's keys are K itself, whose linear warps any unit leaves alike.
fn key_scale(layout: &Layout, texel_size: f64) -> f64 {
    match layout {
        Layout::Radial { .. } => 1.0 / texel_size,
        Layout::Parallel { .. } | Layout::Projective { .. } => 1.0,
    }
}

/// Rays whose projection into the map is shorter than this (texels per scene unit) run
/// parallel to the light: they belong to the epipole.
const MIN_PROJECTED_LENGTH: f64 = 1e-9;

/// The smallest and largest K over a reciprocal-layout sample's interval, where K(s) =
/// K(s_c)·s_c/s: the centre value times each end's factor s_c/s. Both factors are
/// positive, so the two products bracket K whatever its sign; where one is NaN (0·∞) min
/// and max take the other, the centre itself. Without branches, so that loops over runs
/// vectorize.
#[inline]
fn reciprocal_bounds(centre: f32, near: f32, far: f32) -> (f32, f32) {
    let (a, b) = (centre * near, centre * far);
    (a.min(b), a.max(b))
}

// The last frame's rectified values, kept for the next (see `crate::spare`).
static SPARE_VALUES: Spare<f32> = Spare::on_huge_pages(Sizing::Rectified);

/// Lets go of the kept rectified values ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_VALUES.clear();
}

impl Drop for EpipolarMap {
    fn drop(&mut self) {
        SPARE_VALUES.keep(std::mem::take(&mut self.values));
    }
}

impl EpipolarMap {
    /// Rectifies `shadow` for `camera` as `desc` says. Returns `None` when the
    /// camera looks exactly along the light (an orthographic camera whose rays all
    /// project to points), where rectification is undefined.
    /// An error where the map's memory cannot be allocated.
    pub fn build(
        camera: &CameraModel,
        shadow: &ShadowMap,
        desc: &RectifyDesc,
    ) -> Result<Option<Self>> {
        let Some(mut map) = Self::layout_for(camera, shadow, desc)? else {
            return Ok(None);
        };
        map.resample(shadow, None);
        Ok(Some(map))
    }

    /// [`EpipolarMap::build`] with the resampling done by `resampler` (another backend).
    pub fn build_with(
        camera: &CameraModel,
        shadow: &ShadowMap,
        desc: &RectifyDesc,
        resampler: &dyn Resampler,
    ) -> Result<Option<Self>> {
        let Some(mut map) = Self::layout_for(camera, shadow, desc)? else {
            return Ok(None);
        };
        resampler.resample(&mut map, shadow)?;
        if map.values.len() != map.slices as usize * map.samples as usize {
            return Err(crate::error::Error::Internal(format!(
                "resampling returned {} values for {}×{} samples",
                map.values.len(),
                map.slices,
                map.samples
            )));
        }
        Ok(Some(map))
    }

    /// The map's layout and spacing for `desc`, its values not yet sampled (left as a kept
    /// buffer's: resampling sets every one).
    fn layout_for(
        camera: &CameraModel,
        shadow: &ShadowMap,
        desc: &RectifyDesc,
    ) -> Result<Option<Self>> {
        let texel_from_world = shadow.texel_from_world;
        let size = shadow.size as f64;
        let corners = [
            DVec2::ZERO,
            DVec2::new(size, 0.0),
            DVec2::new(0.0, size),
            DVec2::new(size, size),
        ];
        let (layout, s_first, s_last, span, texels_across) = if camera.is_perspective() {
            let position = texel_from_world.transform_point3(camera.position());
            let epipole = position.truncate();
            let s_last = corners
                .iter()
                .map(|c| c.distance(epipole))
                .fold(0.0, f64::max);
            let (first_angle, span, full_circle) = angular_range(camera, shadow);
            let layout = Layout::Radial {
                epipole,
                camera_depth: position.z,
                first_angle,
                angle_step: 0.0,
                full_circle,
            };
            let s_last = s_last.max(1.0);
            // Slices start where they enter the map: an epipole far outside it (a camera
            // far from a small box of fog, which the map then covers alone) otherwise
            // asked for samples over the whole way there, terabytes for a box 1 cm across
            // seen from 15 m. Inside the map the slices start at the epipole.
            let nearest = epipole.clamp(DVec2::ZERO, DVec2::splat(size));
            let s_first = epipole.distance(nearest).min(s_last - 1.0);
            (layout, s_first, s_last, span, span * s_last)
        } else {
            let view = texel_from_world.transform_vector3(camera.ray(0.0, 0.0).direction);
            let projected = view.truncate();
            let length = projected.length();
            if length < MIN_PROJECTED_LENGTH {
                return Ok(None);
            }
            let direction = projected / length;
            let normal = DVec2::new(-direction.y, direction.x);
            let (s_min, s_max) = extent(&corners, direction);
            let (o_min, o_max) = extent(&corners, normal);
            let layout = Layout::Parallel {
                direction,
                normal,
                first_offset: o_min,
                offset_step: 0.0,
                slope: view.z / length,
            };
            // Evenly spaced slices, as dense as radial ones halfway to their far end: at the
            // far end's spacing throughout, texel-scale shafts (a styled occluder's holes
            // under an orthographic camera) blurred across slices, 4.7% off the reference
            // against 2.0% at twice the slices.
            let across = o_max - o_min;
            (layout, s_min, s_max, across, 2.0 * across)
        };
        let slices = if desc.slices == 0 {
            ((texels_across * desc.slices_per_texel).ceil() as u32).clamp(16, desc.max_auto_slices)
        } else {
            desc.slices
        };
        let samples = (((s_last - s_first) * desc.samples_per_texel).ceil() as u32).max(1);
        let spacing = Spacing::Uniform {
            first: s_first,
            step: (s_last - s_first) / samples as f64,
        };
        let layout = match layout {
            Layout::Radial {
                epipole,
                camera_depth,
                first_angle,
                full_circle,
                ..
            } => Layout::Radial {
                epipole,
                camera_depth,
                first_angle,
                angle_step: if full_circle {
                    TAU / slices as f64
                } else {
                    span / (slices.max(2) - 1) as f64
                },
                full_circle,
            },
            Layout::Parallel {
                direction,
                normal,
                first_offset,
                slope,
                ..
            } => Layout::Parallel {
                direction,
                normal,
                first_offset,
                offset_step: span / (slices.max(2) - 1) as f64,
                slope,
            },
            projective @ Layout::Projective { .. } => projective,
        };
        let mut map = EpipolarMap {
            slices,
            samples,
            spacing,
            values: SPARE_VALUES.try_take(slices as usize * samples as usize, || {
                format!("the rectified shadow map ({slices} slices × {samples} samples)")
            })?,
            key_scale: key_scale(&layout, shadow.texel_size),
            layout,
            texel_from_world,
            bound_factors: Vec::new(),
        };
        map.bound_factors = map.compute_bound_factors();
        Ok(Some(map))
    }

    /// The rectified map `rectification` asks for: projective where it is forced, or
    /// where `auto` finds the view valid and the map sharp enough
    /// ([`crate::projective::choose`]), epipolar otherwise. `reach` is the longest planar
    /// depth a view ray is evaluated to. `Ok(None)` where nothing rectifies the view (an
    /// orthographic camera looking straight along the light).
    pub fn rectify(
        camera: &CameraModel,
        shadow: &ShadowMap,
        geometry: &Geometry,
        light_travel: DVec3,
        reach: f64,
        rectification: Rectification,
        desc: &RectifyDesc,
    ) -> Result<Option<Self>> {
        Self::rectify_with(
            camera,
            shadow,
            geometry,
            light_travel,
            reach,
            rectification,
            desc,
            &CpuResampler,
        )
    }

    /// [`EpipolarMap::rectify`] with epipolar maps resampled by `resampler`.
    #[allow(clippy::too_many_arguments)]
    pub fn rectify_with(
        camera: &CameraModel,
        shadow: &ShadowMap,
        geometry: &Geometry,
        light_travel: DVec3,
        reach: f64,
        rectification: Rectification,
        desc: &RectifyDesc,
        resampler: &dyn Resampler,
    ) -> Result<Option<Self>> {
        let grid = choose(
            rectification,
            camera,
            light_travel,
            reach,
            desc,
            shadow.texel_size,
        )?;
        match grid {
            Some(grid) => Ok(Some(Self::build_projective(&grid, shadow, geometry)?)),
            None => Self::build_with(camera, shadow, desc, resampler),
        }
    }

    /// Rasterizes `geometry` straight into the projective map `grid`. K per sample is the
    /// stored depth Z/X plus the shadow bias (scene units of light depth) over the X of
    /// the sample's centre, where the rasterizer sampled it.
    pub fn build_projective(
        grid: &ProjectiveGrid,
        shadow: &ShadowMap,
        geometry: &Geometry,
    ) -> Result<Self> {
        let frame = &grid.frame;
        let (samples, slices) = (grid.columns, grid.rows);
        // Nothing closer than the frustum's near X lands in a column; w stays positive.
        let desc = RasterDesc::projective(samples, slices, 0.5 * frame.near);
        let target = rasterize(geometry, &grid.clip_from_world(), &desc)?;
        let spacing = Spacing::Reciprocal {
            first: 1.0 / frame.near,
            step: grid.reciprocal_step(),
        };
        let layout = Layout::Projective {
            view_from_world: frame.view_from_world,
            first_tan: -frame.tan_max,
            tan_step: grid.tan_step(),
        };
        let bias_over_x: Vec<f64> = (0..samples as usize)
            .map(|i| shadow.bias / spacing.s_at(i as f64 + 0.5))
            .collect();
        let mut values = target.depth;
        values.par_chunks_mut(samples as usize).for_each(|row| {
            for (value, bias) in row.iter_mut().zip(&bias_over_x) {
                *value = (*value as f64 + bias) as f32;
            }
        });
        let mut map = EpipolarMap {
            slices,
            samples,
            spacing,
            values,
            key_scale: key_scale(&layout, shadow.texel_size),
            layout,
            texel_from_world: shadow.texel_from_world,
            bound_factors: Vec::new(),
        };
        map.bound_factors = map.compute_bound_factors();
        Ok(map)
    }

    /// Per sample, what turns K at its centre into K at its ends (see
    /// [`EpipolarMap::sample_bounds`]).
    fn compute_bound_factors(&self) -> Vec<[f32; 2]> {
        (0..self.samples as usize)
            .map(|i| {
                let (s0, s1) = self.sample_interval(i);
                let centre = self.sample_centre(i);
                match self.layout {
                    Layout::Parallel { slope, .. } => {
                        let half = (slope.abs() * 0.5 * (s1 - s0)) as f32;
                        [half, half]
                    }
                    _ => [(centre / s0) as f32, (centre / s1) as f32],
                }
            })
            .collect()
    }

    /// Whether the map was rasterized projectively rather than resampled.
    pub fn is_projective(&self) -> bool {
        matches!(self.layout, Layout::Projective { .. })
    }

    /// Whether the ray `located`, from `t_start` to `t_end`, is too short for the fast
    /// methods' rectified lookups ([`SHORT_RAY_TEXELS`]); the projective layout resolves any
    /// length.
    pub fn is_short(&self, located: &RaySlice, t_start: f64, t_end: f64) -> bool {
        self.crosses_fewer_than(located, t_start, t_end, SHORT_RAY_TEXELS)
    }

    /// Whether a stretch [`t_start`, `t_end`] of a ray is too short for a lookup of its own
    /// ([`SHORT_STRETCH_TEXELS`]).
    pub fn is_short_stretch(&self, located: &RaySlice, t_start: f64, t_end: f64) -> bool {
        self.crosses_fewer_than(located, t_start, t_end, SHORT_STRETCH_TEXELS)
    }

    /// [`EpipolarMap::is_short_stretch`] for the stretch of medium from `a` to `b` of a ray,
    /// counting only its first [`LOOKUP_DEPTH`] of optical depth at `extinction`.
    pub fn is_short_in_medium(&self, located: &RaySlice, a: f64, b: f64, extinction: f64) -> bool {
        let end = if extinction > 0.0 {
            b.min(a + LOOKUP_DEPTH / extinction)
        } else {
            b
        };
        self.is_short_stretch(located, a, end)
    }

    fn crosses_fewer_than(
        &self,
        located: &RaySlice,
        t_start: f64,
        t_end: f64,
        texels: f64,
    ) -> bool {
        !self.is_projective() && located.s_per_t * (t_end - t_start) < texels
    }

    /// Slice line: a point at s = 0 and the unit direction of growing s.
    fn slice_line(&self, slice: u32) -> (DVec2, DVec2) {
        match self.layout {
            Layout::Radial {
                epipole,
                first_angle,
                angle_step,
                ..
            } => {
                let angle = first_angle + slice as f64 * angle_step;
                (epipole, DVec2::new(angle.cos(), angle.sin()))
            }
            Layout::Parallel {
                direction,
                normal,
                first_offset,
                offset_step,
                ..
            } => (
                normal * (first_offset + slice as f64 * offset_step),
                direction,
            ),
            // Projective maps are rasterized, never resampled: no lines to follow.
            Layout::Projective { .. } => (DVec2::ZERO, DVec2::X),
        }
    }

    /// Sets every value from `shadow`: per slice its first `lengths` (all where `None`),
    /// the rest +∞.
    fn resample(&mut self, shadow: &ShadowMap, lengths: Option<&[usize]>) {
        let samples = self.samples as usize;
        let (spacing, layout) = (self.spacing, self.layout);
        let lines: Vec<_> = (0..self.slices).map(|j| self.slice_line(j)).collect();
        let size = shadow.size as f64;
        self.values
            .par_chunks_mut(samples)
            .zip(lines.par_iter())
            .enumerate()
            .for_each(|(slice, (row, &(base, direction)))| {
                let length = lengths.map_or(samples, |lengths| lengths[slice].min(samples));
                let (row, unread) = row.split_at_mut(length);
                unread.fill(f32::INFINITY);
                for (i, value) in row.iter_mut().enumerate() {
                    let s = spacing.s_at(i as f64 + 0.5);
                    let p = base + direction * s;
                    let occluder = if p.x >= 0.0 && p.y >= 0.0 && p.x < size && p.y < size {
                        shadow.depth[p.y as usize * shadow.size as usize + p.x as usize] as f64
                    } else {
                        f64::INFINITY
                    };
                    let lit_below = occluder + shadow.bias;
                    *value = match layout {
                        Layout::Radial { camera_depth, .. } => (lit_below - camera_depth) / s,
                        Layout::Parallel { slope, .. } => lit_below - slope * s,
                        // Projective maps are rasterized, never resampled.
                        Layout::Projective { .. } => f64::INFINITY,
                    } as f32;
                }
            });
    }

    /// Locates a view ray, or `None` when it runs along the light (at the epipole) or its
    /// coordinates are past f64's reach (a camera 10³⁰ m from the scene): the methods
    /// decline such a ray, and it is walked.
    pub fn locate(&self, ray: &Ray) -> Option<RaySlice> {
        self.place(ray).filter(RaySlice::is_finite)
    }

    /// [`EpipolarMap::locate`] before the finiteness test.
    fn place(&self, ray: &Ray) -> Option<RaySlice> {
        if let Layout::Projective {
            view_from_world,
            first_tan,
            tan_step,
        } = self.layout
        {
            // Camera rays start at the frame's origin, so Z/X is the same all along them.
            let d = view_from_world.transform_vector3(ray.direction);
            if d.x < MIN_PROJECTED_LENGTH {
                return None;
            }
            return Some(RaySlice {
                slice: (d.y / d.x - first_tan) / tan_step,
                s_origin: view_from_world.transform_point3(ray.origin).x,
                s_per_t: d.x,
                threshold: d.z / d.x,
            });
        }
        let origin = self.texel_from_world.transform_point3(ray.origin);
        let direction = self.texel_from_world.transform_vector3(ray.direction);
        let projected = direction.truncate();
        let s_per_t = projected.length();
        if s_per_t < MIN_PROJECTED_LENGTH {
            return None;
        }
        let slope = direction.z / s_per_t;
        match self.layout {
            Layout::Radial {
                first_angle,
                angle_step,
                full_circle,
                ..
            } => {
                let angle = projected.y.atan2(projected.x);
                let mut turns = angle - first_angle;
                if full_circle {
                    turns = wrap_from(turns, 0.0);
                } else {
                    turns = wrap_angle(turns);
                }
                Some(RaySlice {
                    slice: turns / angle_step,
                    s_origin: 0.0,
                    s_per_t,
                    threshold: slope,
                })
            }
            Layout::Parallel {
                direction: along,
                normal,
                first_offset,
                offset_step,
                slope: shared_slope,
            } => {
                let s_origin = along.dot(origin.truncate());
                let offset = normal.dot(origin.truncate());
                Some(RaySlice {
                    slice: (offset - first_offset) / offset_step,
                    s_origin,
                    s_per_t,
                    threshold: origin.z - shared_slope * s_origin,
                })
            }
            // Located above, without the regular shadow map.
            Layout::Projective { .. } => None,
        }
    }

    /// Whether slice coordinates go round a full turn, the last slice beside the first.
    pub fn wraps_around(&self) -> bool {
        matches!(
            self.layout,
            Layout::Radial {
                full_circle: true,
                ..
            }
        )
    }

    /// The slice of whole index `k`, which may lie past either end: wrapped where the
    /// slices go round a full turn, else clamped, as [`EpipolarMap::neighbours`] does.
    pub fn slice_of(&self, k: i64) -> usize {
        let count = self.slices as i64;
        if self.wraps_around() {
            k.rem_euclid(count) as usize
        } else {
            k.clamp(0, count - 1) as usize
        }
    }

    /// Whole slice index `k` brought within a slice of the map's ends where the map does
    /// not wrap ([`bounded_slice_index`]).
    pub fn bounded_slice_index(&self, k: i64) -> i64 {
        bounded_slice_index(k, self.slices, self.wraps_around())
    }

    /// The two slices to blend for a fractional slice coordinate, with their weights.
    pub fn neighbours(&self, slice: f64) -> [(u32, f64); 2] {
        let last = self.slices - 1;
        let full_circle = self.wraps_around();
        let clamped = if full_circle {
            let count = self.slices as f64;
            // Slice coordinates come from angles in one turn: one wrap at most.
            if slice < 0.0 {
                slice + count
            } else if slice >= count {
                slice - count
            } else {
                slice
            }
            .clamp(0.0, count)
        } else {
            slice.clamp(0.0, last as f64)
        };
        // Non-negative, so truncation is the floor, without a libm call.
        let lower = (clamped as u32).min(last);
        let fraction = clamped - lower as f64;
        let upper = if lower == last {
            if full_circle {
                0
            } else {
                last
            }
        } else {
            lower + 1
        };
        [(lower, 1.0 - fraction), (upper, fraction)]
    }

    /// A monotone key with: a ray is lit at a sample when key(threshold) ≥ key(K). For a
    /// pinhole camera it is bounded to [−1, 1] (like the angle between view ray and light,
    /// without the arctangent: K is first made a slope free of units, `key_scale`), so
    /// that ±∞ map to finite keys.
    #[inline]
    pub fn order_key(&self, value: f64) -> f64 {
        if self.layout.is_reciprocal() {
            bounded_key(value, self.key_scale)
        } else {
            -value
        }
    }

    /// [`EpipolarMap::order_key`] of each of `values`, with the layout chosen once, in a
    /// loop the compiler vectorizes: the prefiltered plan keys every sample its bands
    /// read, and keying them one at a time took 10 million more of `torus`'s 1080p frame's
    /// instructions.
    pub fn order_keys(&self, values: &[f32]) -> Vec<f64> {
        if self.layout.is_reciprocal() {
            let scale = self.key_scale;
            values
                .iter()
                .map(|&value| bounded_key(value as f64, scale))
                .collect()
        } else {
            values.iter().map(|&value| -(value as f64)).collect()
        }
    }

    /// The value whose [`EpipolarMap::order_key`] is `key`, ±∞ beyond the keys' range:
    /// keys fall as values rise.
    #[inline]
    pub fn value_of_key(&self, key: f64) -> f64 {
        if !self.layout.is_reciprocal() {
            -key
        } else if key <= -1.0 {
            f64::INFINITY
        } else if key >= 1.0 {
            f64::NEG_INFINITY
        } else {
            -key / (1.0 - key.abs()) / self.key_scale
        }
    }

    /// Sample i's interval along its slice.
    #[inline]
    pub fn sample_interval(&self, i: usize) -> (f64, f64) {
        (
            self.spacing.s_at(i as f64),
            self.spacing.s_at((i + 1) as f64),
        )
    }

    /// Where sample i's value was taken.
    #[inline]
    pub fn sample_centre(&self, i: usize) -> f64 {
        self.spacing.s_at(i as f64 + 0.5)
    }

    /// The continuous, increasing sample coordinate of `s`: sample i spans [i, i + 1].
    /// Below the first sample it is negative (−∞ behind a projective map's camera), past
    /// the last one above `samples`.
    #[inline]
    pub fn sample_coordinate(&self, s: f64) -> f64 {
        self.spacing.coordinate(s)
    }

    /// The s covered by the samples: from the first one's start to the last one's end.
    pub fn s_range(&self) -> (f64, f64) {
        (
            self.spacing.s_at(0.0),
            self.spacing.s_at(self.samples as f64),
        )
    }

    /// The common length of all samples, where they are evenly spaced.
    pub fn uniform_step(&self) -> Option<f64> {
        match self.spacing {
            Spacing::Uniform { step, .. } => Some(step),
            Spacing::Reciprocal { .. } => None,
        }
    }

    /// K along sample i's interval is monotone in s, determined by its centre value:
    /// returns (a, b) such that the ray with `threshold` is lit at s where a·s ≤ b.
    fn lit_condition(&self, i: usize, centre: f32, threshold: f64) -> (f64, f64) {
        let s_centre = self.sample_centre(i);
        match self.layout {
            // K(s) = M − slope·s with M = K(s_c) + slope·s_c: lit where slope·s ≤ M − threshold.
            Layout::Parallel { slope, .. } => (slope, centre as f64 + slope * s_centre - threshold),
            // K(s) = N/s with N = K(s_c)·s_c: lit where threshold·s ≤ N.
            _ => (threshold, centre as f64 * s_centre),
        }
    }

    /// The smallest and largest K over sample i's interval.
    #[inline]
    pub fn sample_bounds(&self, i: usize, centre: f32) -> (f32, f32) {
        let [near, far] = self.bound_factors[i];
        if !self.layout.is_reciprocal() {
            // K(s) = K(s_c) + slope·(s_c − s): the ends differ by ±|slope|·step/2.
            return (centre - near, centre + near);
        }
        reciprocal_bounds(centre, near, far)
    }

    /// Per sample index, what turns K at its centre into K at its ends
    /// ([`EpipolarMap::sample_bounds`]), for backends that bound samples themselves.
    pub fn bound_factors(&self) -> &[[f32; 2]] {
        &self.bound_factors
    }

    /// The smallest and largest K over the intervals of samples `range` of `row` (one of
    /// this map's slices): [`EpipolarMap::sample_bounds`] over a run, with the layout
    /// matched once.
    #[inline]
    pub fn run_bounds(&self, row: &[f32], range: std::ops::Range<usize>) -> [f32; 2] {
        let (values, factors) = (&row[range.clone()], &self.bound_factors[range]);
        let (mut low, mut high) = (f32::INFINITY, f32::NEG_INFINITY);
        if !self.layout.is_reciprocal() {
            for (&centre, &[near, _]) in values.iter().zip(factors) {
                low = low.min(centre - near);
                high = high.max(centre + near);
            }
        } else {
            for (&centre, &[near, far]) in values.iter().zip(factors) {
                let (a, b) = reciprocal_bounds(centre, near, far);
                low = low.min(a);
                high = high.max(b);
            }
        }
        [low, high]
    }

    /// The part of sample i's interval where a ray with `threshold` is lit.
    pub fn lit_part(&self, i: usize, centre: f32, threshold: f64) -> Option<(f64, f64)> {
        let (s0, s1) = self.sample_interval(i);
        let (a, b) = self.lit_condition(i, centre, threshold);
        let (lo, hi) = if a > 0.0 {
            (s0, s1.min(b / a))
        } else if a < 0.0 {
            (s0.max(b / a), s1)
        } else if b >= 0.0 {
            (s0, s1)
        } else {
            return None;
        };
        (hi > lo).then_some((lo, hi))
    }

    /// The map's layout and spacing as plain numbers, for backends that locate rays
    /// themselves (see [`MapGeometry`]).
    pub fn geometry(&self) -> MapGeometry {
        let (reciprocal_spacing, spacing_first, spacing_step) = match self.spacing {
            Spacing::Uniform { first, step } => (false, first, step),
            Spacing::Reciprocal { first, step } => (true, first, step),
        };
        let mut geometry = MapGeometry {
            layout: MapLayout::Radial,
            full_circle: false,
            reciprocal_spacing,
            spacing_first,
            spacing_step,
            first: 0.0,
            step: 1.0,
            along: DVec2::X,
            normal: DVec2::Y,
            slope: 0.0,
            epipole: DVec2::ZERO,
            camera_depth: 0.0,
            from_world: self.texel_from_world,
            key_scale: self.key_scale,
        };
        match self.layout {
            Layout::Radial {
                epipole,
                camera_depth,
                first_angle,
                angle_step,
                full_circle,
            } => {
                geometry.epipole = epipole;
                geometry.camera_depth = camera_depth;
                geometry.full_circle = full_circle;
                geometry.first = first_angle;
                geometry.step = angle_step;
            }
            Layout::Parallel {
                direction,
                normal,
                first_offset,
                offset_step,
                slope,
            } => {
                geometry.layout = MapLayout::Parallel;
                geometry.first = first_offset;
                geometry.step = offset_step;
                geometry.along = direction;
                geometry.normal = normal;
                geometry.slope = slope;
            }
            Layout::Projective {
                view_from_world,
                first_tan,
                tan_step,
            } => {
                geometry.layout = MapLayout::Projective;
                geometry.first = first_tan;
                geometry.step = tan_step;
                geometry.from_world = view_from_world;
            }
        }
        geometry
    }

    pub fn row(&self, slice: u32) -> &[f32] {
        let start = slice as usize * self.samples as usize;
        &self.values[start..start + self.samples as usize]
    }

    pub fn memory_bytes(&self) -> usize {
        self.values.len() * std::mem::size_of::<f32>()
    }
}

/// First slice angle and angular span of the image's view rays around the epipole, and
/// whether they cover the full circle (the sun or the anti-sun point is in the image).
fn angular_range(camera: &CameraModel, shadow: &ShadowMap) -> (f64, f64, bool) {
    if epipoles_in_image(camera, shadow, 1.0).next().is_some() {
        return (0.0, TAU, true);
    }
    let (w, h) = (camera.width as f64, camera.height as f64);
    let angle_of = |px: f64, py: f64| {
        let d = shadow
            .texel_from_world
            .transform_vector3(camera.ray(px, py).direction);
        d.y.atan2(d.x)
    };
    let centre = angle_of(0.5 * w, 0.5 * h);
    let offsets: Vec<f64> = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|&(px, py)| wrap_angle(angle_of(px, py) - centre))
        .collect();
    let low = offsets.iter().copied().fold(f64::INFINITY, f64::min);
    let high = offsets.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    (centre + low, (high - low).max(1e-9), false)
}

/// Image positions of the sun and the anti-sun point, for those within `margin` pixels
/// of the image (pinhole cameras only; parallel projections have no epipole).
pub fn epipoles_in_image<'a>(
    camera: &'a CameraModel,
    shadow: &'a ShadowMap,
    margin: f64,
) -> impl Iterator<Item = [f64; 2]> + 'a {
    // The light's direction in world space: texel-space +z pulled back.
    let travel = shadow
        .texel_from_world
        .inverse()
        .transform_vector3(DVec3::Z)
        .normalize();
    [-travel, travel].into_iter().filter_map(move |direction| {
        if !camera.is_perspective() {
            return None;
        }
        // A point at infinity (w = 0) in front of the camera has a positive clip w.
        let clip = camera.pixel_from_world() * direction.extend(0.0);
        if clip.w <= 0.0 {
            return None;
        }
        let (px, py) = (clip.x / clip.w, clip.y / clip.w);
        let inside = px >= -margin
            && py >= -margin
            && px <= camera.width as f64 + margin
            && py <= camera.height as f64 + margin;
        inside.then_some([px, py])
    })
}

/// The angle in [−π, π).
fn wrap_angle(angle: f64) -> f64 {
    wrap_from(angle, -std::f64::consts::PI)
}

/// The angle in [low, low + 2π); angles here are differences of a few turns at most, so
/// whole turns are taken off by steps rather than a division.
#[inline]
fn wrap_from(mut angle: f64, low: f64) -> f64 {
    if !angle.is_finite() {
        return low;
    }
    while angle < low {
        angle += TAU;
    }
    while angle >= low + TAU {
        angle -= TAU;
    }
    angle
}

fn extent(points: &[DVec2], axis: DVec2) -> (f64, f64) {
    points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            let d = p.dot(axis);
            (lo.min(d), hi.max(d))
        })
}

/// Whole slice index `k` of a map of `slices` brought within [−1, `slices`] where the map
/// does not `wrap`: off such a map, coordinates may lie far past its ends (a view billions
/// of metres wide), and every index past an end reads its end slice
/// ([`EpipolarMap::slice_of`]), so that loops over the indices between two coordinates
/// stay as short as the map. Indices of a wrapping map are left as they are.
pub fn bounded_slice_index(k: i64, slices: u32, wraps: bool) -> i64 {
    if wraps {
        k
    } else {
        k.clamp(-1, slices as i64)
    }
}

/// What unit tests of the rectified methods start from.
#[cfg(test)]
pub(crate) mod test_support {
    use super::*;
    use crate::render::FlatGeometry;
    use crate::scene::Scene;

    /// `scene`'s camera, shadow map and rectified map, built as a frame builds them.
    pub(crate) fn rectified(
        scene: &Scene,
        rectification: Rectification,
        desc: &RectifyDesc,
    ) -> (CameraModel, ShadowMap, EpipolarMap) {
        let camera = CameraModel::new(&scene.camera);
        let geometry = FlatGeometry::from_scene(scene);
        let shadow = ShadowMap::of_scene_geometry(scene, &camera, &geometry).unwrap();
        let map = EpipolarMap::rectify(
            &camera,
            &shadow,
            &geometry.view(),
            scene.sun.direction.as_dvec3().normalize(),
            scene.render.max_distance as f64,
            rectification,
            desc,
        )
        .expect("a valid view")
        .expect("a view that rectifies");
        (camera, shadow, map)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::FlatGeometry;
    use crate::scene::{Camera, Medium, RenderSettings, Sun};
    use glam::Vec3;
    use rand::{RngExt, SeedableRng};

    /// A tilted square occluder over x, y ∈ [−HALF, HALF].
    const HALF: f64 = 3.0;
    const BIAS: f64 = 0.05;

    fn occluder_height(x: f64, y: f64) -> f64 {
        4.0 + 0.2 * x + 0.1 * y
    }

    /// Where the light line through `p` meets the occluder's plane: how far towards the
    /// sun, and where.
    fn towards_occluder(p: DVec3, light: DVec3) -> (f64, DVec3) {
        // The gap to the plane is linear in u along p − u·light.
        let gap = |u: f64| {
            let q = p - light * u;
            q.z - occluder_height(q.x, q.y)
        };
        let (g0, g1) = (gap(0.0), gap(1.0));
        let u = g0 / (g0 - g1);
        (u, p - light * u)
    }

    /// Whether the map says the point at `t` along `ray` is lit.
    fn lit_in_map(map: &EpipolarMap, ray: &Ray, t: f64) -> bool {
        let located = map.locate(ray).expect("a ray of the frustum");
        let slice = (located.slice.round() as u32).min(map.slices - 1);
        let s = located.s_origin + located.s_per_t * t;
        let i = map.sample_coordinate(s) as usize;
        assert!(
            i < map.samples as usize,
            "inside the frustum, inside the map"
        );
        map.lit_part(i, map.row(slice)[i], located.threshold)
            .is_some_and(|(a, b)| a <= s && s <= b)
    }

    /// Torus at 64×36 rectified as `desc` says, seen by its pinhole camera (a radial map)
    /// and by an orthographic one (a parallel map), with its own shadow map size unless
    /// `shadow_map_size` is given.
    fn torus_seen_both_ways(desc: &RectifyDesc, shadow_map_size: Option<u32>) -> [EpipolarMap; 2] {
        let mut scene = crate::builtin::builtin_scene("torus").expect("built-in scene");
        scene.camera.width = 64;
        scene.camera.height = 36;
        if let Some(size) = shadow_map_size {
            scene.render.shadow_map_size = size;
        }
        let (_, _, radial) = test_support::rectified(&scene, Rectification::Epipolar, desc);
        scene.camera.projection = crate::scene::Projection::orthographic(20.0);
        let (_, _, parallel) = test_support::rectified(&scene, Rectification::Epipolar, desc);
        [radial, parallel]
    }

    /// A radial map's slices run from the epipole where it lies on the map, else from where
    /// they enter the map: a camera far from a small box of fog, which the map covers alone,
    /// has its epipole far off the map, and the samples cover the map's square and no more.
    #[test]
    fn radial_slices_start_where_they_enter_the_map() {
        let desc = RectifyDesc::prefiltered(0);
        let [on_map, _] = torus_seen_both_ways(&desc, Some(256));
        let mut scene = crate::builtin::builtin_scene("torus").expect("built-in scene");
        (scene.camera.width, scene.camera.height) = (64, 36);
        scene.medium.extent = crate::scene::Extent::Box {
            world_from_cube: glam::Mat4::from_translation(Vec3::new(1.0, -2.5, 3.5))
                * glam::Mat4::from_scale(Vec3::splat(0.05)),
        };
        scene.render.shadow_map_size = 256;
        let (_, shadow, off_map) = test_support::rectified(&scene, Rectification::Epipolar, &desc);
        let size = shadow.size as f64;
        for map in [&on_map, &off_map] {
            let Layout::Radial { epipole, .. } = map.layout else {
                panic!("a pinhole camera's map is radial");
            };
            let nearest = epipole.clamp(DVec2::ZERO, DVec2::splat(size));
            let farthest = [[0.0, 0.0], [size, 0.0], [0.0, size], [size, size]]
                .map(|c| DVec2::from(c).distance(epipole))
                .into_iter()
                .fold(0.0, f64::max);
            let (first, last) = map.s_range();
            assert!((first - epipole.distance(nearest)).abs() < 1e-6 * farthest);
            assert!((last - farthest).abs() < 1e-6 * farthest);
            let diagonal = std::f64::consts::SQRT_2 * size;
            assert!(map.samples as f64 <= (diagonal * desc.samples_per_texel).ceil());
        }
        let Layout::Radial { epipole, .. } = off_map.layout else {
            unreachable!()
        };
        assert!(
            epipole.length() > 50.0 * size,
            "the epipole {epipole} lies far off"
        );
    }

    /// Automatic slice counts: a radial map's slices lie 1/`slices_per_texel` texels apart
    /// at its far end, closer nearer the epipole; evenly spaced parallel slices (an
    /// orthographic camera's) lie as close as radial ones halfway out, everywhere.
    #[test]
    fn automatic_slices_are_as_dense_as_radial_ones_halfway_out() {
        let desc = RectifyDesc::prefiltered(0);
        let far_spacing = 1.0 / desc.slices_per_texel;
        // n slices have n − 1 gaps over the span that asked for n.
        let gaps = |map: &EpipolarMap| map.slices as f64 / (map.slices - 1) as f64;
        let [radial, parallel] = torus_seen_both_ways(&desc, Some(256));
        let Layout::Radial { angle_step, .. } = radial.layout else {
            panic!("a pinhole camera's map is radial");
        };
        let far = radial.sample_interval(radial.samples as usize - 1).1;
        let spacing = angle_step * far;
        assert!(
            spacing <= far_spacing * gaps(&radial) + 1e-9 && spacing > 0.5 * far_spacing,
            "radial slices {spacing} texels apart at the far end"
        );
        let Layout::Parallel { offset_step, .. } = parallel.layout else {
            panic!("an orthographic camera's map is parallel");
        };
        assert!(parallel.slices < desc.max_auto_slices, "not capped");
        assert!(
            offset_step <= 0.5 * far_spacing * gaps(&parallel) + 1e-9
                && offset_step > 0.25 * far_spacing,
            "parallel slices {offset_step} texels apart"
        );
    }

    /// `value_of_key` inverts `order_key` for the radial (reciprocal) and parallel layouts,
    /// and takes keys at or past ±1 to the infinite values they stand for.
    #[test]
    fn value_of_key_inverts_order_key() {
        let [radial, parallel] = torus_seen_both_ways(&RectifyDesc::prefiltered(64), None);
        assert!(radial.layout.is_reciprocal() && !parallel.layout.is_reciprocal());
        for map in [&radial, &parallel] {
            for value in [-1e6, -3.5, -1.0, -0.01, 0.0, 0.2, 1.0, 7.0, 1e6] {
                let back = map.value_of_key(map.order_key(value));
                assert!(
                    (back - value).abs() <= 1e-9 * (1.0 + value.abs()),
                    "{value}: {back}"
                );
            }
        }
        assert_eq!(radial.value_of_key(-1.0), f64::INFINITY);
        assert_eq!(radial.value_of_key(1.0), f64::NEG_INFINITY);
        assert_eq!(
            radial.value_of_key(radial.order_key(f64::INFINITY)),
            f64::INFINITY
        );
    }

    /// The batch keys every value as one at a time does, bit for bit: ±∞, signed zeros,
    /// the map's own samples and values far past f32's usual range of depths.
    #[test]
    fn order_keys_are_order_key_of_each_value() {
        let [radial, parallel] = torus_seen_both_ways(&RectifyDesc::prefiltered(64), None);
        let mut values = vec![
            f32::INFINITY,
            f32::NEG_INFINITY,
            0.0,
            -0.0,
            f32::MAX,
            f32::MIN,
            f32::MIN_POSITIVE,
            -1e-30,
            3.5,
            -7.25,
        ];
        values.extend(radial.values.iter().step_by(97));
        for map in [&radial, &parallel] {
            let keys = map.order_keys(&values);
            assert_eq!(keys.len(), values.len());
            for (&value, key) in values.iter().zip(keys) {
                let one = map.order_key(value as f64);
                assert_eq!(key.to_bits(), one.to_bits(), "{value}: {key} against {one}");
            }
        }
    }

    /// Seen from the side by a shallow frustum, with the shadow bias given in scene units.
    #[test]
    fn the_projective_map_shadows_exactly_what_the_occluder_shadows() {
        let corners = [[-HALF, -HALF], [HALF, -HALF], [HALF, HALF], [-HALF, HALF]];
        let positions: Vec<[f32; 3]> = corners
            .iter()
            .map(|&[x, y]| [x as f32, y as f32, occluder_height(x, y) as f32])
            .collect();
        let geometry = FlatGeometry {
            positions,
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            object_ids: vec![2, 2],
            origin: glam::DVec3::ZERO,
            ..FlatGeometry::default()
        };
        let mut scene_camera = Camera::pinhole_looking_at(
            Vec3::new(-10.0, -1.0, 2.0),
            Vec3::new(0.0, 0.0, 2.0),
            30.0,
            64,
            48,
        );
        scene_camera.clip_start = 6.0;
        let camera = CameraModel::new(&scene_camera);
        let sun = Sun {
            direction: Vec3::new(0.3, 0.2, -1.0),
            color: Vec3::ONE,
            strength: 1.0,
            angular_diameter: 0.0,
            attenuated_by_medium: true,
        };
        let light = sun.direction.as_dvec3().normalize();
        let medium = Medium {
            extinction: 0.1,
            channel_extinction: None,
            albedo: Vec3::ONE,
            anisotropy: 0.0,
            phase: Default::default(),
            extent: Default::default(),
        };
        let settings = RenderSettings {
            shadow_map_size: 256,
            max_distance: 14.0,
            shadow_bias: Some(BIAS as f32),
            ..RenderSettings::default()
        };
        let shadow = ShadowMap::build(&camera, &sun, &medium, &settings, &geometry.view()).unwrap();
        let map = EpipolarMap::rectify(
            &camera,
            &shadow,
            &geometry.view(),
            light,
            14.0,
            Rectification::Projective,
            &RectifyDesc::min_max(0),
        )
        .expect("a valid view")
        .expect("a map");
        assert!(map.is_projective());
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let (mut lit, mut shadowed) = (0, 0);
        for _ in 0..20000 {
            let ray = camera.ray(rng.random_range(0.0..64.0), rng.random_range(0.0..48.0));
            let t = rng.random_range(6.0..14.0) * ray.distance_per_depth;
            let p = ray.at(t);
            let (u, hit) = towards_occluder(p, light);
            // Within a few of the map's texels of an edge, or of the biased surface, the
            // decision is the sampling's to make.
            let margin = 0.15;
            let near_edge =
                (hit.x.abs() - HALF).abs() < margin || (hit.y.abs() - HALF).abs() < margin;
            if near_edge || (u - BIAS).abs() < margin {
                continue;
            }
            let truth = !(hit.x.abs() < HALF && hit.y.abs() < HALF && u > BIAS);
            assert_eq!(lit_in_map(&map, &ray, t), truth, "at {p} (u = {u})");
            if truth {
                lit += 1;
            } else {
                shadowed += 1;
            }
        }
        assert!(
            lit > 1000 && shadowed > 1000,
            "{lit} lit, {shadowed} shadowed"
        );
    }
}
