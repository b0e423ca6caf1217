//! The scene description: camera, sun, medium, meshes and render settings.
//!
//! It is what crosses every boundary (JSON files, Python dicts, the Blender and USD
//! exporters). Parsing rejects unknown keys by their path, and [`Scene::validate`] names
//! the offending field of any value the renderer cannot use.

use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};

use crate::backend::Backend;
use crate::cutout::{MaskFilter, Wrap};
use crate::error::{Error, Result};
use crate::style::Style;

/// The scene-description version this build reads and writes.
pub const SCENE_VERSION: u32 = 1;
/// Largest accepted image side, in pixels.
pub const MAX_IMAGE_SIZE: u32 = 16384;
/// Largest accepted shadow-map side, in texels (a 16384² f32 map plus ids is 2 GiB).
pub const MAX_SHADOW_MAP_SIZE: u32 = 16384;
/// Smallest accepted shadow-map side, in texels.
pub const MIN_SHADOW_MAP_SIZE: u32 = 16;
/// Largest accepted ray-march step count.
pub const MAX_STEPS: u32 = 1 << 20;
/// Largest accepted number of epipolar slices.
pub const MAX_EPIPOLAR_SLICES: u32 = 65536;
/// Largest accepted supersampling factor per axis.
pub const MAX_SUPERSAMPLING: u32 = 8;
/// Most camera-depth samples a frame may take (width × height × supersampling²): 4 GiB of
/// depth. The largest image at the largest supersampling would take 64 GiB.
pub const MAX_DEPTH_SAMPLES: u64 = 1 << 30;

/// A complete, self-contained frame description.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    pub version: u32,
    pub camera: Camera,
    pub sun: Sun,
    pub medium: Medium,
    #[serde(default)]
    pub meshes: Vec<Mesh>,
    #[serde(default)]
    pub render: RenderSettings,
    /// Departures from the physically based look (papers 000/001 §4).
    #[serde(default, skip_serializing_if = "Style::is_physical")]
    pub style: Style,
}

/// A camera looking down its local −Z axis with +Y up, as in Blender and USD.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Camera-to-world transform, 16 floats in column-major order.
    pub world_from_camera: Mat4,
    pub projection: Projection,
    /// Near clip distance, measured along the view axis as Blender and USD do.
    pub clip_start: f32,
    /// Far clip distance along the view axis; surfaces beyond it count as background.
    pub clip_end: f32,
    pub width: u32,
    pub height: u32,
    /// A pixel's width over its height: 1 for square pixels, 2 for a 2:1 anamorphic
    /// squeeze (Blender's `pixel_aspect_x / pixel_aspect_y`, USD's `pixelAspectRatio`).
    #[serde(default = "square_pixels", skip_serializing_if = "is_square")]
    pub pixel_aspect: f32,
    /// The pixels of the `width` × `height` frame that the layers cover (Blender's render
    /// region, USD's `dataWindowNDC`); the whole frame where absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<PixelWindow>,
}

/// A rectangle of a frame's pixels, from its top-left corner.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PixelWindow {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

fn square_pixels() -> f32 {
    1.0
}

fn is_square(pixel_aspect: &f32) -> bool {
    *pixel_aspect == 1.0
}

/// Which sensor dimension the sensor size (or ortho scale) applies to, as in Blender.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SensorFit {
    /// The larger image dimension, measured with the pixels' aspect, gets `sensor_width`.
    #[default]
    Auto,
    /// The image width gets `sensor_width`.
    Horizontal,
    /// The image height gets `sensor_height`.
    Vertical,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Projection {
    /// A pinhole camera. Lengths are in millimetres, shifts in units of the fitted
    /// sensor dimension (Blender's `shift_x`/`shift_y`).
    Perspective {
        focal_length: f32,
        #[serde(default = "default_sensor_width")]
        sensor_width: f32,
        #[serde(default = "default_sensor_height")]
        sensor_height: f32,
        #[serde(default)]
        sensor_fit: SensorFit,
        #[serde(default)]
        shift_x: f32,
        #[serde(default)]
        shift_y: f32,
    },
    /// A parallel projection; `ortho_scale` is the fitted image side in scene units.
    Orthographic {
        ortho_scale: f32,
        #[serde(default)]
        sensor_fit: SensorFit,
        #[serde(default)]
        shift_x: f32,
        #[serde(default)]
        shift_y: f32,
    },
}

impl Projection {
    /// A perspective projection of `focal_length` mm on the default 36 × 24 mm sensor,
    /// fitted automatically and unshifted.
    pub fn pinhole(focal_length: f32) -> Self {
        Self::Perspective {
            focal_length,
            sensor_width: default_sensor_width(),
            sensor_height: default_sensor_height(),
            sensor_fit: SensorFit::Auto,
            shift_x: 0.0,
            shift_y: 0.0,
        }
    }

    /// A parallel projection `ortho_scale` across the wider image side, unshifted.
    pub const fn orthographic(ortho_scale: f32) -> Self {
        Self::Orthographic {
            ortho_scale,
            sensor_fit: SensorFit::Auto,
            shift_x: 0.0,
            shift_y: 0.0,
        }
    }
}

fn default_sensor_width() -> f32 {
    36.0
}

fn default_sensor_height() -> f32 {
    24.0
}

/// A directional light.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sun {
    /// The direction the light travels, from the sun into the scene (a sun lamp's −Z axis).
    /// Need not be normalized.
    pub direction: Vec3,
    /// Linear RGB colour.
    #[serde(default = "white")]
    pub color: Vec3,
    /// Irradiance on a surface facing the sun, in W/m² as Blender's sun strength.
    #[serde(default = "one")]
    pub strength: f32,
    /// Apparent diameter of the sun disk in radians; shafts soften over it with
    /// `render.sun_disc_samples` above 1 ([`crate::sun_disc`]).
    #[serde(default = "default_sun_angle")]
    pub angular_diameter: f32,
    /// Whether the light fades through a `box` medium on its way in (the DESIGN's
    /// `T_light`). False for a light that casts no shadows: Cycles traces no shadow rays for
    /// it (its Cast Shadow off), through fog no more than through surfaces, and nor do
    /// renderers of a UsdLux light whose `inputs:shadow:enable` is false. What blocks the
    /// light is the geometry's own say (`blocks_sun`).
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub attenuated_by_medium: bool,
}

fn white() -> Vec3 {
    Vec3::ONE
}

fn one() -> f32 {
    1.0
}

fn default_sun_angle() -> f32 {
    0.526_f32.to_radians()
}

impl Sun {
    /// Unit vector of light travel. Only valid after [`Scene::validate`].
    pub fn travel_direction(&self) -> Vec3 {
        self.direction.normalize()
    }

    /// Colour × strength: the E of the scattering integral.
    pub fn irradiance(&self) -> Vec3 {
        self.color * self.strength
    }
}

/// A homogeneous participating medium.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Medium {
    /// Extinction coefficient σt, per scene unit.
    pub extinction: f32,
    /// Extinction per channel (RGB), per scene unit, where it is coloured: Cycles scales a
    /// Volume Scatter's σt by its colour. Where given, it is each channel's σt for the
    /// scattering ([`crate::channels`]), and `extinction` stands for the medium only where
    /// one value must (the stylization's operators and transfer function).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub channel_extinction: Option<Vec3>,
    /// Single-scattering albedo ρ per channel, so that σs = ρ·σt.
    #[serde(default = "white")]
    pub albedo: Vec3,
    /// Henyey–Greenstein mean cosine g (positive scatters forward).
    #[serde(default)]
    pub anisotropy: f32,
    #[serde(default)]
    pub phase: PhaseModel,
    #[serde(default)]
    pub extent: Extent,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhaseModel {
    #[default]
    HenyeyGreenstein,
    /// The constant 1/(4π), ignoring `anisotropy`.
    Isotropic,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Extent {
    /// The medium fills all space and sunlight reaches every point unattenuated.
    #[default]
    Unbounded,
    /// The medium fills an oriented box: the image of the cube [−1, 1]³ (Blender's default
    /// cube, USD's default `Cube`) under `world_from_cube`. Sunlight is attenuated inside.
    Box { world_from_cube: Mat4 },
}

/// Triangles of one object. Positions are in object space, placed by `world_from_object`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mesh {
    #[serde(default)]
    pub name: String,
    /// Written into the shadow map's id channel; stylization selects objects by it.
    pub object_id: u32,
    #[serde(default = "identity")]
    pub world_from_object: Mat4,
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    /// Texture coordinates, one per position: where `alpha_mask` reads its image.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uvs: Option<Vec<[f32; 2]>>,
    /// An alpha cutout ([`crate::cutout`]): the mesh's triangles are empty where this
    /// image's alpha is below the threshold (leaf cards, fences).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_mask: Option<AlphaMaskDesc>,
    /// Whether the mesh is in the sun's shadow map (false: hidden from shadow rays, as
    /// Blender's Shadow visibility or shadow linking hide an object).
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub blocks_sun: bool,
    /// Whether the mesh is in the camera's depth, hiding the fog behind it (false: hidden
    /// from camera rays).
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub seen_by_camera: bool,
}

fn yes() -> bool {
    true
}

fn is_true(value: &bool) -> bool {
    *value
}

/// The image of a mesh's alpha cutout: a .png or .exr file whose alpha channel is read
/// (rows from the image's top, as files store them, v = 0 being the bottom row), relative to
/// the scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AlphaMaskDesc {
    pub image: std::path::PathBuf,
    #[serde(default = "half")]
    pub threshold: f32,
    /// How the image is read past its edges: one mode for both axes (`"clip"`), or one
    /// each for u and v (`["repeat", "clip"]`).
    #[serde(default, skip_serializing_if = "MaskWrapDesc::is_default")]
    pub wrap: MaskWrapDesc,
    #[serde(default, skip_serializing_if = "is_default")]
    pub filter: MaskFilter,
    /// The alpha read past an edge clipped by `wrap` (0: empty there).
    #[serde(default, skip_serializing_if = "is_default")]
    pub border: f32,
}

/// [`AlphaMaskDesc::wrap`]: one mode, or one per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "a wrap mode (repeat, extend, mirror or clip) or a pair of them"
)]
pub enum MaskWrapDesc {
    Both(Wrap),
    PerAxis([Wrap; 2]),
}

impl Default for MaskWrapDesc {
    fn default() -> Self {
        Self::Both(Wrap::Repeat)
    }
}

impl MaskWrapDesc {
    /// Along u, then v.
    pub fn axes(self) -> [Wrap; 2] {
        match self {
            Self::Both(wrap) => [wrap; 2],
            Self::PerAxis(axes) => axes,
        }
    }

    fn is_default(&self) -> bool {
        self.axes() == [Wrap::Repeat; 2]
    }
}

fn is_default<T: Default + PartialEq>(value: &T) -> bool {
    *value == T::default()
}

fn half() -> f32 {
    0.5
}

fn identity() -> Mat4 {
    Mat4::IDENTITY
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Brute-force ray marching: the reference every faster method is measured against.
    Reference,
    /// 1D min-max mipmaps on the epipolar-rectified shadow map (Chen et al. 2011).
    #[serde(rename = "minmax")]
    MinMax,
    /// Fourier-basis prefiltering of the rectified shadow map (dissertation ch. 4): the
    /// default, as DESIGN has it.
    #[default]
    Prefiltered,
}

impl Method {
    pub const ALL: [Method; 3] = [Method::Reference, Method::MinMax, Method::Prefiltered];

    pub fn name(self) -> &'static str {
        match self {
            Method::Reference => "reference",
            Method::MinMax => "minmax",
            Method::Prefiltered => "prefiltered",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = Error;

    fn from_str(text: &str) -> Result<Self> {
        Method::ALL
            .into_iter()
            .find(|method| method.name() == text)
            .ok_or_else(|| {
                let known: Vec<_> = Method::ALL.iter().map(|m| m.name()).collect();
                Error::invalid(
                    "render.method",
                    format!("unknown method '{text}' (known: {})", known.join(", ")),
                )
            })
    }
}

/// How the fast methods rectify the shadow map, so that view rays run along its rows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rectification {
    /// Projective where the view allows it and it resolves shadows as finely as the
    /// regular shadow map, epipolar otherwise.
    #[default]
    Auto,
    /// Resample the regular shadow map along epipolar slices (dissertation §4.4.1).
    Epipolar,
    /// Rasterize straight into a projectively rectified map (dissertation §4.4.2); an error
    /// for views it cannot handle (orthographic cameras, the sun or the anti-sun point in
    /// or near the image).
    Projective,
}

impl Rectification {
    pub const ALL: [Rectification; 3] = [
        Rectification::Auto,
        Rectification::Epipolar,
        Rectification::Projective,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Rectification::Auto => "auto",
            Rectification::Epipolar => "epipolar",
            Rectification::Projective => "projective",
        }
    }
}

impl std::str::FromStr for Rectification {
    type Err = Error;

    fn from_str(text: &str) -> Result<Self> {
        Rectification::ALL
            .into_iter()
            .find(|r| r.name() == text)
            .ok_or_else(|| {
                let known: Vec<_> = Rectification::ALL.iter().map(|r| r.name()).collect();
                Error::invalid(
                    "render.rectification",
                    format!(
                        "unknown rectification '{text}' (known: {})",
                        known.join(", ")
                    ),
                )
            })
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderSettings {
    /// Side of the square light shadow map, in texels.
    pub shadow_map_size: u32,
    pub method: Method,
    /// Distance along the view ray integrated for background pixels, in scene units.
    pub max_distance: f32,
    /// Ray-march steps per view ray for the reference method.
    pub steps: u32,
    /// Camera-depth samples per pixel along each axis (1 = one sample at the pixel centre).
    pub supersampling: u32,
    /// Shadow-map depth bias in scene units; `None` picks 1.5 texel widths.
    pub shadow_bias: Option<f32>,
    /// Epipolar slices of the rectified shadow map (0: about one per texel at its far end).
    pub epipolar_slices: u32,
    /// Half-size in pixels of the block around an on-screen sun or anti-sun point that the
    /// fast methods ray-march instead, where rectification loses precision.
    pub epipole_block: u32,
    /// Evaluate scattering at 1/1, 1/2 or 1/4 of the resolution per axis, then upsample
    /// with the full-resolution depth as guide.
    pub downsample: u32,
    /// Fast methods: shade a sparse grid of pixels (sparser along the epipolar lines than
    /// across them), and the pixels between only where their shaded neighbours' RGBA
    /// spreads by more than this fraction of its mean (visibility: by more than this), or
    /// they end on another surface; the rest are interpolated ([`crate::adaptive`]). 0
    /// shades every pixel, as the reference method and the Vulkan backend always do.
    pub adaptive_tolerance: f32,
    /// Fourier basis coefficients M of the prefiltered method (even, 4 to 64).
    pub bases: u32,
    /// Prefiltered method: subtract the stretch between the camera and the near clip
    /// plane from each ray (dissertation §4.3.1), at the cost of a second lookup.
    pub near_plane_correction: bool,
    /// Prefiltered method: integrate exactly the stretch before each ray's end where the
    /// shadow map's samples close in on the ray (ground it grazes, views near the light's
    /// direction, surfaces nearly their own occluders), which lookups read about half lit.
    /// `auto`: in box media and under light from below (see [`ExactRayEnds::Auto`]).
    pub exact_ray_ends: ExactRayEnds,
    /// Prefiltered method: precision of the stored filtered basis.
    pub basis_storage: BasisStorage,
    /// Fast methods: how the shadow map is rectified.
    pub rectification: Rectification,
    /// Where the frame is computed: `auto` (a GPU if there is one), `cpu` or `vulkan`.
    #[serde(skip_serializing_if = "Backend::is_auto")]
    pub backend: Backend,
    /// Directions spread over the sun's disc (`sun.angular_diameter`) whose frames are
    /// averaged, so that shafts soften as under a path tracer's disc
    /// ([`crate::sun_disc`]); 1 keeps the hard shafts of a point sun.
    #[serde(skip_serializing_if = "crate::sun_disc::is_point_sun")]
    pub sun_disc_samples: u32,
}

/// Whether the prefiltered method integrates exactly the stretch before each ray's end
/// where the shadow map's samples close in on the ray, which lookups read about half lit.
///
/// Scene files may also give `true` (`on`) or `false` (`off`), as before this had `auto`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ExactRayEnds {
    /// On in a box medium, and under a sun below the horizon (light travelling upward),
    /// off otherwise. In a box a surface that is nearly its own occluder otherwise leaks
    /// a glow into fog that is dark around it, and the rule adds 2–11% to a box frame;
    /// light from below makes the ground the occluder of nearly every ray that ends on it
    /// (fuzzed views read 14–947% off the reference without, 3–37% with, min-max 0.6–17%
    /// on those dim frames); in open media under light from above it adds 2–24% (50–58%
    /// on `plane`), for errors of at most a few percent on grazed ground and views near
    /// the light.
    #[default]
    Auto,
    On,
    Off,
}

impl ExactRayEnds {
    pub const ALL: [ExactRayEnds; 3] = [ExactRayEnds::Auto, ExactRayEnds::On, ExactRayEnds::Off];

    pub fn name(self) -> &'static str {
        match self {
            ExactRayEnds::Auto => "auto",
            ExactRayEnds::On => "on",
            ExactRayEnds::Off => "off",
        }
    }

    fn named(text: &str) -> Option<Self> {
        ExactRayEnds::ALL
            .into_iter()
            .find(|setting| setting.name() == text)
    }

    /// Whether the rule runs for a medium that is a box (`box_medium`) or open, under
    /// light travelling upward (`from_below`) or not.
    pub fn applies(self, box_medium: bool, from_below: bool) -> bool {
        match self {
            ExactRayEnds::Auto => box_medium || from_below,
            ExactRayEnds::On => true,
            ExactRayEnds::Off => false,
        }
    }
}

impl From<bool> for ExactRayEnds {
    fn from(on: bool) -> Self {
        if on {
            ExactRayEnds::On
        } else {
            ExactRayEnds::Off
        }
    }
}

impl std::str::FromStr for ExactRayEnds {
    type Err = Error;

    fn from_str(text: &str) -> Result<Self> {
        let flag = text.parse::<bool>().ok().map(ExactRayEnds::from);
        flag.or_else(|| ExactRayEnds::named(text)).ok_or_else(|| {
            Error::invalid(
                "render.exact_ray_ends",
                format!("unknown setting '{text}' (known: auto, on, off, true, false)"),
            )
        })
    }
}

impl<'de> Deserialize<'de> for ExactRayEnds {
    fn deserialize<D: serde::Deserializer<'de>>(
        deserializer: D,
    ) -> std::result::Result<Self, D::Error> {
        struct Visitor;

        impl serde::de::Visitor<'_> for Visitor {
            type Value = ExactRayEnds;

            fn expecting(&self, formatter: &mut std::fmt::Formatter) -> std::fmt::Result {
                formatter.write_str("\"auto\", \"on\", \"off\", true or false")
            }

            fn visit_bool<E: serde::de::Error>(
                self,
                on: bool,
            ) -> std::result::Result<Self::Value, E> {
                Ok(on.into())
            }

            fn visit_str<E: serde::de::Error>(
                self,
                text: &str,
            ) -> std::result::Result<Self::Value, E> {
                ExactRayEnds::named(text)
                    .ok_or_else(|| E::invalid_value(serde::de::Unexpected::Str(text), &self))
            }
        }

        deserializer.deserialize_any(Visitor)
    }
}

/// How the prefiltered method stores its filtered basis. It is normalized to [−1, 1],
/// so 16 bits lose nothing visible and halve the memory and the bandwidth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BasisStorage {
    F32,
    /// 16-bit signed normalized integers.
    #[default]
    Snorm16,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            shadow_map_size: 1024,
            method: Method::Prefiltered,
            max_distance: 100.0,
            steps: 2048,
            supersampling: 1,
            shadow_bias: None,
            epipolar_slices: 0,
            epipole_block: 16,
            downsample: 1,
            adaptive_tolerance: crate::adaptive::DEFAULT_TOLERANCE,
            bases: 32,
            near_plane_correction: true,
            exact_ray_ends: ExactRayEnds::Auto,
            basis_storage: BasisStorage::default(),
            rectification: Rectification::default(),
            backend: Backend::default(),
            sun_disc_samples: 1,
        }
    }
}

impl Scene {
    /// Parses a JSON scene description; unknown keys and type errors name their path.
    pub fn from_json(text: &str) -> Result<Self> {
        let scene: Scene = parse_json_at("", text)?;
        scene.validate()?;
        Ok(scene)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a scene always serializes to JSON")
    }

    /// Reads a scene file; relative file paths in its style are taken relative to the file.
    pub fn load(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|err| Error::io(path, err))?;
        let mut scene = Self::from_json(&text)?;
        scene.rebase_paths(path.parent().unwrap_or(std::path::Path::new("")));
        Ok(scene)
    }

    /// Joins relative file paths (the style's images and the meshes' alpha masks) to
    /// `base`, the folder of the file the scene came from.
    pub fn rebase_paths(&mut self, base: &std::path::Path) {
        self.style.rebase_paths(base);
        for mask in self.meshes.iter_mut().filter_map(|m| m.alpha_mask.as_mut()) {
            if mask.image.is_relative() {
                mask.image = base.join(&mask.image);
            }
        }
    }

    /// The ids in `style.holes.objects` that no mesh of the scene has, sorted: hole
    /// creation makes no holes for them (a typo, or a preset written for another scene).
    pub fn hole_objects_without_mesh(&self) -> Vec<u32> {
        let Some(holes) = &self.style.holes else {
            return Vec::new();
        };
        let mut missing: Vec<u32> = holes
            .objects
            .iter()
            .copied()
            .filter(|&id| !self.meshes.iter().any(|mesh| mesh.object_id == id))
            .collect();
        missing.sort_unstable();
        missing.dedup();
        missing
    }

    /// The warning for [`Scene::hole_objects_without_mesh`], where there are any.
    pub fn hole_objects_warning(&self) -> Option<String> {
        let missing = self.hole_objects_without_mesh();
        (!missing.is_empty()).then(|| {
            let ids: Vec<String> = missing.iter().map(u32::to_string).collect();
            format!(
                "style.holes.objects names object ids that no mesh has ({}): no holes are \
                 made for them",
                ids.join(", ")
            )
        })
    }

    pub fn triangle_count(&self) -> usize {
        self.meshes.iter().map(|mesh| mesh.triangles.len()).sum()
    }

    /// Checks every value the renderer relies on and names the first offending field.
    pub fn validate(&self) -> Result<()> {
        if self.version != SCENE_VERSION {
            return Err(Error::invalid(
                "version",
                format!(
                    "scene version {} is not supported (this build reads version {SCENE_VERSION})",
                    self.version
                ),
            ));
        }
        self.camera.validate()?;
        self.sun.validate()?;
        self.medium.validate()?;
        self.render.validate()?;
        let ss = self.render.supersampling as u64;
        let (width, height) = self.camera.image_size();
        let samples = width as u64 * height as u64 * ss * ss;
        if samples > MAX_DEPTH_SAMPLES {
            return Err(Error::invalid(
                "render.supersampling",
                format!(
                    "{}×{} pixels at {ss}×{ss} samples each are {samples} camera-depth \
                     samples, more than the {MAX_DEPTH_SAMPLES} a frame may take; lower the \
                     supersampling or the resolution",
                    width, height
                ),
            ));
        }
        self.style.validate()?;
        for (index, mesh) in self.meshes.iter().enumerate() {
            mesh.validate(&format!("meshes[{index}]"))?;
        }
        if self.triangle_count() == 0 {
            return Err(Error::invalid(
                "meshes",
                "the scene is empty: it has no triangles (add at least a ground plane)",
            ));
        }
        Ok(())
    }
}

impl Camera {
    /// A pinhole camera on a 36 × 24 mm sensor at `eye`, looking at `target`, with the
    /// world's +Z up in the image and clip planes at 0.1 and 1000.
    pub fn pinhole_looking_at(
        eye: Vec3,
        target: Vec3,
        focal_length: f32,
        width: u32,
        height: u32,
    ) -> Self {
        let forward = (target - eye).normalize();
        let right = forward.cross(Vec3::Z).normalize();
        let up = right.cross(forward);
        Camera {
            world_from_camera: Mat4::from_cols(
                right.extend(0.0),
                up.extend(0.0),
                (-forward).extend(0.0),
                eye.extend(1.0),
            ),
            projection: Projection::pinhole(focal_length),
            clip_start: 0.1,
            clip_end: 1000.0,
            width,
            height,
            pixel_aspect: 1.0,
            window: None,
        }
    }

    /// An orthographic camera at `eye`, looking at `target`, `ortho_scale` across its
    /// wider side, otherwise as [`Camera::pinhole_looking_at`].
    pub fn orthographic_looking_at(
        eye: Vec3,
        target: Vec3,
        ortho_scale: f32,
        width: u32,
        height: u32,
    ) -> Self {
        Camera {
            projection: Projection::orthographic(ortho_scale),
            ..Camera::pinhole_looking_at(eye, target, 50.0, width, height)
        }
    }

    /// The layers' size: the window's, else the frame's.
    pub fn image_size(&self) -> (u32, u32) {
        self.window
            .map_or((self.width, self.height), |w| (w.width, w.height))
    }

    pub fn validate(&self) -> Result<()> {
        check_size("camera.width", self.width, 1, MAX_IMAGE_SIZE)?;
        check_size("camera.height", self.height, 1, MAX_IMAGE_SIZE)?;
        check_matrix("camera.world_from_camera", &self.world_from_camera)?;
        check_positive("camera.clip_start", self.clip_start)?;
        check_positive("camera.clip_end", self.clip_end)?;
        check_positive("camera.pixel_aspect", self.pixel_aspect)?;
        if let Some(window) = self.window {
            let fits = |start: u32, size: u32, side: u32| {
                size >= 1 && start.checked_add(size).is_some_and(|end| end <= side)
            };
            if !(fits(window.x, window.width, self.width)
                && fits(window.y, window.height, self.height))
            {
                return Err(Error::invalid(
                    "camera.window",
                    format!(
                        "{}×{} at ({}, {}) must hold a pixel and lie within the {}×{} frame",
                        window.width, window.height, window.x, window.y, self.width, self.height
                    ),
                ));
            }
        }
        if self.clip_end <= self.clip_start {
            return Err(Error::invalid(
                "camera.clip_end",
                format!(
                    "{} must be greater than clip_start {}",
                    self.clip_end, self.clip_start
                ),
            ));
        }
        match self.projection {
            Projection::Perspective {
                focal_length,
                sensor_width,
                sensor_height,
                shift_x,
                shift_y,
                ..
            } => {
                check_positive("camera.projection.focal_length", focal_length)?;
                check_positive("camera.projection.sensor_width", sensor_width)?;
                check_positive("camera.projection.sensor_height", sensor_height)?;
                check_finite("camera.projection.shift_x", shift_x)?;
                check_finite("camera.projection.shift_y", shift_y)?;
            }
            Projection::Orthographic {
                ortho_scale,
                shift_x,
                shift_y,
                ..
            } => {
                check_positive("camera.projection.ortho_scale", ortho_scale)?;
                check_finite("camera.projection.shift_x", shift_x)?;
                check_finite("camera.projection.shift_y", shift_y)?;
            }
        }
        Ok(())
    }
}

impl Sun {
    pub fn validate(&self) -> Result<()> {
        check_vec("sun.direction", self.direction)?;
        if self.direction.length() < 1e-12 {
            return Err(Error::invalid(
                "sun.direction",
                "has zero length; give the direction the light travels",
            ));
        }
        check_color("sun.color", self.color)?;
        check_non_negative("sun.strength", self.strength)?;
        check_non_negative("sun.angular_diameter", self.angular_diameter)?;
        // A disc wider than half the sky has no directions to spread over (USD's angle is
        // unbounded; a 10³⁰° disc rendered).
        if self.angular_diameter > std::f32::consts::PI {
            return Err(Error::invalid(
                "sun.angular_diameter",
                format!(
                    "{} rad ({:.1}°) is wider than the sky; at most π (180°)",
                    self.angular_diameter,
                    self.angular_diameter.to_degrees()
                ),
            ));
        }
        Ok(())
    }
}

impl Medium {
    /// Whether this is a box of fog that attenuates light and that no view ray of the frame
    /// rendered into `layers` crossed (every alpha 0): the box is out of view, behind
    /// surfaces or past the maximum distance, which a user should be told, as the frame
    /// shows no fog at all.
    pub fn box_unreached(&self, layers: &crate::Layers) -> bool {
        let densest = self
            .channel_extinction
            .map_or(self.extinction, |c| c.max_element().max(self.extinction));
        matches!(self.extent, Extent::Box { .. })
            && densest > 0.0
            && layers.volume.chunks_exact(4).all(|rgba| rgba[3] == 0.0)
    }

    pub fn validate(&self) -> Result<()> {
        check_non_negative("medium.extinction", self.extinction)?;
        if let Some(channels) = self.channel_extinction {
            check_color("medium.channel_extinction", channels)?;
        }
        check_color("medium.albedo", self.albedo)?;
        check_finite("medium.anisotropy", self.anisotropy)?;
        if self.anisotropy.abs() >= 1.0 {
            return Err(Error::invalid(
                "medium.anisotropy",
                format!("{} is outside (−1, 1)", self.anisotropy),
            ));
        }
        if let Extent::Box { world_from_cube } = &self.extent {
            check_matrix("medium.extent.world_from_cube", world_from_cube)?;
        }
        Ok(())
    }
}

impl Mesh {
    pub fn validate(&self, field: &str) -> Result<()> {
        check_matrix(
            &format!("{field}.world_from_object"),
            &self.world_from_object,
        )?;
        check_triangles(&format!("{field}."), &self.positions, &self.triangles)?;
        if let Some(uvs) = &self.uvs {
            if uvs.len() != self.positions.len() {
                return Err(Error::invalid(
                    format!("{field}.uvs"),
                    format!(
                        "has {} entries but there are {} positions (give one per position)",
                        uvs.len(),
                        self.positions.len()
                    ),
                ));
            }
            if let Some(k) = uvs.iter().position(|uv| !uv.iter().all(|c| c.is_finite())) {
                return Err(Error::invalid(
                    format!("{field}.uvs[{k}]"),
                    format!("{:?} is not finite", uvs[k]),
                ));
            }
        }
        if let Some(mask) = &self.alpha_mask {
            if self.uvs.is_none() {
                return Err(Error::invalid(
                    format!("{field}.alpha_mask"),
                    "needs the mesh's uvs (texture coordinates, one per position)",
                ));
            }
            if !mask.threshold.is_finite() {
                return Err(Error::invalid(
                    format!("{field}.alpha_mask.threshold"),
                    format!("{} is not finite", mask.threshold),
                ));
            }
        }
        Ok(())
    }
}

impl RenderSettings {
    /// The tolerance adaptive shading runs at: 0 (every pixel) for the reference method.
    pub fn effective_adaptive_tolerance(&self) -> f32 {
        match self.method {
            Method::Reference => 0.0,
            Method::MinMax | Method::Prefiltered => self.adaptive_tolerance,
        }
    }

    pub fn validate(&self) -> Result<()> {
        check_size(
            "render.shadow_map_size",
            self.shadow_map_size,
            MIN_SHADOW_MAP_SIZE,
            MAX_SHADOW_MAP_SIZE,
        )?;
        check_positive("render.max_distance", self.max_distance)?;
        check_size("render.steps", self.steps, 1, MAX_STEPS)?;
        check_size(
            "render.supersampling",
            self.supersampling,
            1,
            MAX_SUPERSAMPLING,
        )?;
        if let Some(bias) = self.shadow_bias {
            check_non_negative("render.shadow_bias", bias)?;
        }
        if self.epipolar_slices != 0 {
            check_size(
                "render.epipolar_slices",
                self.epipolar_slices,
                2,
                MAX_EPIPOLAR_SLICES,
            )?;
        }
        check_size(
            "render.epipole_block",
            self.epipole_block,
            0,
            MAX_IMAGE_SIZE,
        )?;
        use crate::prefiltered::{MAX_BASES, MIN_BASES};
        if !self.bases.is_multiple_of(2) || !(MIN_BASES..=MAX_BASES).contains(&self.bases) {
            return Err(Error::invalid(
                "render.bases",
                format!(
                    "{} is not an even number from {MIN_BASES} to {MAX_BASES}",
                    self.bases
                ),
            ));
        }
        if !(1..=crate::sun_disc::MAX_SUN_DISC_SAMPLES).contains(&self.sun_disc_samples) {
            return Err(Error::invalid(
                "render.sun_disc_samples",
                format!(
                    "{} is not a count from 1 to {}",
                    self.sun_disc_samples,
                    crate::sun_disc::MAX_SUN_DISC_SAMPLES
                ),
            ));
        }
        if !(0.0..=1.0).contains(&self.adaptive_tolerance) {
            return Err(Error::invalid(
                "render.adaptive_tolerance",
                format!("{} is not a fraction from 0 to 1", self.adaptive_tolerance),
            ));
        }
        if ![1, 2, 4].contains(&self.downsample) {
            return Err(Error::invalid(
                "render.downsample",
                format!("{} is not one of 1, 2 or 4", self.downsample),
            ));
        }
        Ok(())
    }
}

/// Parses JSON for the part of a scene description at `prefix` ("" for a whole scene);
/// syntax errors, unknown keys and wrong types name their full path.
pub fn parse_json_at<T: serde::de::DeserializeOwned>(prefix: &str, text: &str) -> Result<T> {
    let deserializer = &mut serde_json::Deserializer::from_str(text);
    let value = serde_path_to_error::deserialize(&mut *deserializer).map_err(|err| {
        let found = err.path().to_string();
        let inner = err.into_inner();
        let path = match (prefix, found.as_str()) {
            ("", ".") => return Error::SceneFormat(inner.to_string()),
            (prefix, ".") => prefix.to_owned(),
            ("", path) => path.to_owned(),
            (prefix, path) => format!("{prefix}.{path}"),
        };
        Error::SceneFormat(format!("at '{path}': {inner}"))
    })?;
    deserializer
        .end()
        .map_err(|err| Error::SceneFormat(format!("trailing characters: {err}")))?;
    Ok(value)
}

/// Positions must be finite and triangle indices in range; `prefix` leads the field names.
pub(crate) fn check_triangles(
    prefix: &str,
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
) -> Result<()> {
    use rayon::prelude::*;
    if let Some(index) = positions
        .par_iter()
        .position_first(|p| !p.iter().all(|c| c.is_finite()))
    {
        return Err(Error::invalid(
            format!("{prefix}positions[{index}]"),
            format!("{:?} is not finite", positions[index]),
        ));
    }
    let count = positions.len();
    if let Some(index) = triangles
        .par_iter()
        .position_first(|t| t.iter().any(|&v| v as usize >= count))
    {
        return Err(Error::invalid(
            format!("{prefix}triangles[{index}]"),
            format!("{:?} indexes past the {count} positions", triangles[index]),
        ));
    }
    Ok(())
}

pub(crate) fn check_size(field: &str, value: u32, min: u32, max: u32) -> Result<()> {
    if value < min || value > max {
        return Err(Error::invalid(
            field,
            format!("{value} is outside the supported range {min}..={max}"),
        ));
    }
    Ok(())
}

pub(crate) fn check_finite(field: &str, value: f32) -> Result<()> {
    if !value.is_finite() {
        return Err(Error::invalid(field, format!("{value} is not finite")));
    }
    Ok(())
}

pub(crate) fn check_positive(field: &str, value: f32) -> Result<()> {
    check_finite(field, value)?;
    if value <= 0.0 {
        return Err(Error::invalid(field, format!("{value} must be positive")));
    }
    Ok(())
}

pub(crate) fn check_non_negative(field: &str, value: f32) -> Result<()> {
    check_finite(field, value)?;
    if value < 0.0 {
        return Err(Error::invalid(
            field,
            format!("{value} must not be negative"),
        ));
    }
    Ok(())
}

fn check_vec(field: &str, value: Vec3) -> Result<()> {
    if !value.is_finite() {
        return Err(Error::invalid(field, format!("{value:?} is not finite")));
    }
    Ok(())
}

fn check_color(field: &str, value: Vec3) -> Result<()> {
    check_vec(field, value)?;
    if value.min_element() < 0.0 {
        return Err(Error::invalid(
            field,
            format!("{value:?} has a negative channel"),
        ));
    }
    Ok(())
}

/// A matrix must be finite and invertible to place anything in the world.
pub(crate) fn check_matrix(field: &str, matrix: &Mat4) -> Result<()> {
    if !matrix.is_finite() {
        return Err(Error::invalid(field, "contains NaN or infinity"));
    }
    let det = matrix.determinant();
    if !det.is_finite() {
        return Err(Error::invalid(
            field,
            format!("scales space beyond floats (determinant {det})"),
        ));
    }
    if det.abs() < 1e-20 {
        return Err(Error::invalid(field, "is singular (determinant is zero)"));
    }
    Ok(())
}
