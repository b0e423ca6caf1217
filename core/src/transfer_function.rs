//! 2D transfer functions (papers 000 §4.2 and 001 §4.2; DESIGN §4 step 5, "Color").
//!
//! A transfer function (TF) maps two properties of a view ray to a colour: the average light
//! visibility V̄ ∈ [0, 1] along the ray (the `visibility` layer) and its depth normalized by a
//! user range, `u = clamp((s − near)/(far − near), 0, 1)` with `s` the `depth` layer. It is
//! stored as a square RGBA texture ([`TfTexture`]) whose first axis is V̄ and second axis is
//! `u`, and it is built from a stack of layers ([`TfLayer`]: solid, gradient, image,
//! diffusion), each blended onto the ones below it with an opacity and a [`BlendMode`]. Stacks
//! can be key-framed in time ([`TransferFunction::keyframes`], [`BakedKeyframes`]).
//!
//! # Applying a TF to the per-pixel layers
//!
//! The baked texture holds **premultiplied** RGBA `(P, a)`: `a` is how strongly the TF
//! overrides physically based scattering at that (V̄, u), and `P = a·C` with `C` its colour.
//! An empty stack is transparent everywhere. With `L` the physically based in-scattered
//! radiance of a pixel (`volume.rgb`) and `(P, a)` the TF sampled at its (V̄, u), [`apply`]
//! writes
//!
//! * [`TfMode::Monochrome`]: `rgb = (1 − a)·L + Y(P)·L`, with `Y` the Rec. 709 luminance.
//!   The TF scales the radiance and keeps its colour: the light's colour stays that of the
//!   source, so surfaces lit by it and the shafts stay consistent (papers 000 §4, 001 §4.2).
//! * [`TfMode::Color`]: `rgb = (1 − a)·L + P ⊙ K`, where `K = L ⊘ Ĉ` is the radiance per unit
//!   light colour and `Ĉ` the light's colour scaled so that its largest channel is 1. The TF
//!   colour replaces the light's colour (the paper's "TF maps a view ray to the scattering
//!   component's output colour") while the physically based intensity — medium density,
//!   phase function, falloff with distance, V̄ itself — is kept. A channel the light lacks
//!   (`Ĉ_c < 1e-4`) takes the intensity of the channels it has, `Σ L / Σ Ĉ` over them.
//! * In both modes `volume.a` is kept (clamped to [0, 1], NaN read as 0). The TF recolours
//!   in-scattered light; it does not change how much the medium attenuates what is behind it.
//!   So the compositing contract `out = volume.rgb + (1 − volume.a)·beauty` holds unchanged,
//!   with the stylized radiance in `volume.rgb`.
//! * Non-finite radiance reads as 0. Both rules are linear in `L` and affine in the sample,
//!   so [`apply`] folds them into a per-texel gain before the bilinear lookup; results match
//!   the formulas up to f32 rounding, and the identities below exactly.
//!
//! **Identity.** A TF sample with `a = 0` leaves the pixel exactly as it was, in both modes.
//! So does an opaque white sample `(1, 1, 1, 1)` in monochrome mode, and in colour mode for a
//! white (or grey) light; for a coloured light the opaque identity is the light's own colour
//! `Ĉ`. The paper's TFs map V̄ and depth to the whole output colour, dropping the physical
//! falloff; here the TF multiplies the physical radiance instead, so that a neutral TF is
//! exactly the physically based render (DESIGN: every stylization is a departure the artist
//! chooses). A TF value can exceed 1 to brighten, or vary along `u` to reshape the falloff.
//! Rays with V̄ = 0 carry no radiance and stay dark whatever the TF says.
//!
//! # Layers and blending
//!
//! Layer colours are straight (not premultiplied) linear RGBA. A layer with colour `Cs`,
//! alpha `as` and opacity `o` has coverage `α = o·as`, and is composited onto the stack below,
//! `(Pb, αb)` premultiplied, as in the W3C compositing model with separable blend `B`:
//! `P = α·((1 − αb)·Cs + αb·B(Cb, Cs)) + (1 − α)·Pb`, `a = α + (1 − α)·αb`. So:
//!
//! * `alpha` (over): `P = α·Cs + (1 − α)·Pb`;
//! * `add`: `P = α·Cs + Pb` (unclamped, linear light);
//! * `multiply`: `P = α·(1 − αb)·Cs + α·Cs ⊙ Pb + (1 − α)·Pb`.
//!
//! On an empty (transparent) stack every mode shows the layer as it is.
//!
//! Texel `(i, j)` of an `n × n` texture sits at TF position `((i + 0.5)/n, (j + 0.5)/n)`;
//! layers are evaluated at texel centres and the texture is looked up bilinearly with
//! clamp-to-edge. Images are drawn as the TF is: V̄ from left to right and `u` from the
//! bottom row (near) to the top row (far), so the image's first (top) row is `u` ≈ 1.
//!
//! # Diffusion layers
//!
//! Constraints (TF position, RGBA) are rasterized to the nearest texel (the one containing
//! the position; several on one texel are averaged) and held fixed, and every channel,
//! alpha included, is made harmonic elsewhere with natural boundaries at the texture edges
//! (see [`crate::diffusion`]). One constraint gives a uniform layer, two a smooth gradient.
//! A constraint can be anchored to a world point (a 3D constraint): the integrator finds
//! where the point lands each frame and calls [`constraint_position`] to move it in TF space.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::diffusion::{self, Pin};
use crate::error::{Error, Result};
use crate::layers::Layers;

/// Default side of a baked TF texture.
pub const DEFAULT_RESOLUTION: u32 = 256;
/// Largest accepted side of a TF texture.
pub const MAX_RESOLUTION: u32 = 4096;
/// Largest accepted image layer, in pixels (e.g. 8192²).
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;
/// Field path under which a style preset embeds its TF; [`TransferFunction::validate`] uses it.
pub const FIELD: &str = "style.tf";

/// Straight (not premultiplied) linear RGBA.
pub type Rgba = [f32; 4];

/// How the TF changes the physically based radiance; see the module docs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TfMode {
    /// The TF colour replaces the light's colour.
    #[default]
    Color,
    /// The TF's luminance scales the radiance, whose colour stays the light's.
    Monochrome,
}

/// How a layer is composited onto the layers below it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BlendMode {
    /// Porter–Duff over.
    #[default]
    Alpha,
    Add,
    Multiply,
}

/// The depths mapped to `u = 0` and `u = 1`, in scene units along the view ray.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthRange {
    pub near: f32,
    pub far: f32,
}

impl DepthRange {
    /// `u = clamp((depth − near)/(far − near), 0, 1)`; NaN reads as 0.
    #[inline]
    pub fn normalize(&self, depth: f32) -> f32 {
        // A reciprocal, which the per-pixel loops hoist out.
        unit((depth - self.near) * (1.0 / (self.far - self.near)))
    }

    pub fn validate_at(&self, field: &str) -> Result<()> {
        for (name, value) in [("near", self.near), ("far", self.far)] {
            if !value.is_finite() {
                return Err(Error::invalid(
                    format!("{field}.{name}"),
                    format!("must be finite, got {value}"),
                ));
            }
        }
        if self.near >= self.far || !(self.far - self.near).is_finite() {
            return Err(Error::invalid(
                format!("{field}.far"),
                format!(
                    "must be greater than near ({}), got {}",
                    self.near, self.far
                ),
            ));
        }
        Ok(())
    }
}

/// A gradient colour stop.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColorStop {
    /// Position along the gradient, in [0, 1].
    pub position: f32,
    pub color: Rgba,
}

/// Where a gradient runs in TF space, positions given as `[V̄, u]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum GradientShape {
    /// Position 0 at `from`, 1 at `to`, constant across the line between them.
    Linear { from: [f32; 2], to: [f32; 2] },
    /// Position 0 at `center`, 1 at `radius` from it.
    Radial { center: [f32; 2], radius: f32 },
}

/// The pixels of an image layer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ImageSource {
    /// A PNG (8 or 16 bit, read as sRGB-encoded, straight alpha) or an OpenEXR file (linear,
    /// premultiplied as EXR specifies; `R`, `G`, `B` and optional `A` channels, negative
    /// values and alpha above 1 clamped). Chosen by the extension. Relative paths are
    /// relative to the preset or scene file that holds them, and to the working directory
    /// for JSON given as text.
    File { path: PathBuf },
    /// Straight linear RGBA, rows top to bottom.
    Pixels {
        width: u32,
        height: u32,
        rgba: Vec<Rgba>,
    },
}

/// A diffusion constraint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConstraint {
    /// TF-space position `[V̄, u]`, in [0, 1]².
    pub position: [f32; 2],
    pub color: Rgba,
    /// For a 3D constraint, the world point whose pixel sets `position` each frame (see
    /// [`TransferFunction::resolve_world_constraints`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world_point: Option<[f32; 3]>,
}

fn one() -> f32 {
    1.0
}

/// One layer of a TF stack.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TfLayer {
    Solid {
        #[serde(default = "one")]
        opacity: f32,
        #[serde(default)]
        blend: BlendMode,
        color: Rgba,
    },
    Gradient {
        #[serde(default = "one")]
        opacity: f32,
        #[serde(default)]
        blend: BlendMode,
        shape: GradientShape,
        /// Linearly interpolated in straight RGBA; before the first and after the last stop
        /// the end colours continue. Stops need not be sorted; equal positions make a step.
        stops: Vec<ColorStop>,
    },
    Image {
        #[serde(default = "one")]
        opacity: f32,
        #[serde(default)]
        blend: BlendMode,
        image: ImageSource,
    },
    Diffusion {
        #[serde(default = "one")]
        opacity: f32,
        #[serde(default)]
        blend: BlendMode,
        /// With no constraints the layer is transparent.
        constraints: Vec<DiffusionConstraint>,
    },
}

/// The TF stack at one time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TfKeyframe {
    /// In the host's time unit (frames or seconds; only the order and ratios matter).
    pub time: f32,
    pub layers: Vec<TfLayer>,
}

/// A transfer function as a style preset holds it (`style.tf`): a static layer stack, or
/// key-framed stacks interpolated linearly in time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferFunction {
    #[serde(default)]
    pub mode: TfMode,
    pub depth_range: DepthRange,
    /// Side of the baked texture, in texels.
    #[serde(default = "default_resolution")]
    pub resolution: u32,
    /// The stack, bottom first. Used when there are no key frames.
    #[serde(default)]
    pub layers: Vec<TfLayer>,
    /// Stacks at increasing times; when present, `layers` must be empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub keyframes: Vec<TfKeyframe>,
}

fn default_resolution() -> u32 {
    DEFAULT_RESOLUTION
}

/// A baked TF: `size × size` premultiplied linear RGBA texels, row `j` holding `u` at
/// `(j + 0.5)/size` and column `i` holding V̄ at `(i + 0.5)/size`.
#[derive(Clone, Debug, PartialEq)]
pub struct TfTexture {
    size: u32,
    texels: Vec<Rgba>,
    /// The texels with a one-texel border repeating the edges, `(size + 2)²`: bilinear
    /// lookups then need no index clamping (clamp-to-edge comes from the border).
    padded: Vec<Rgba>,
}

/// Baked key frames: the TF at any time, interpolated linearly between the two keys around
/// it and clamped to the first and last.
#[derive(Clone, Debug, PartialEq)]
pub struct BakedKeyframes {
    keys: Vec<(f32, TfTexture)>,
}

/// How a TF is applied to the per-pixel layers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ApplySettings {
    pub mode: TfMode,
    pub depth_range: DepthRange,
    /// Colour of the physically based scattered light (the sun's colour times the medium's
    /// albedo; only its hue matters). Used by [`TfMode::Color`]; black reads as white.
    pub light_color: [f32; 3],
}

/// Where a 3D constraint's world point lands in the current frame, as the integrator finds it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ProjectedPoint {
    /// The point is the first surface at a pixel with these layer values.
    Visible { visibility: f32, depth: f32 },
    /// The point projects outside the image or behind the camera.
    OffScreen,
    /// Another surface is in front of the point.
    Occluded,
}

/// Rec. 709 luminance. The weights' f32 sum is exactly 1, so `Y(1, 1, 1) = 1`.
#[inline(always)]
pub fn luminance(rgb: [f32; 3]) -> f32 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// TF-space position `[V̄, u]` of a pixel: V̄ clamped to [0, 1] and the depth normalized by
/// `range` (NaN reads as 0).
pub fn tf_position(visibility: f32, depth: f32, range: &DepthRange) -> [f32; 2] {
    [unit(visibility), range.normalize(depth)]
}

/// The TF-space position of a 3D constraint from where its point landed, or an error naming
/// `field` (the constraint's path) when it is off screen or occluded in this frame.
pub fn constraint_position(
    field: &str,
    point: ProjectedPoint,
    range: &DepthRange,
) -> Result<[f32; 2]> {
    match point {
        ProjectedPoint::Visible { visibility, depth } => Ok(tf_position(visibility, depth, range)),
        ProjectedPoint::OffScreen => Err(Error::invalid(
            field,
            "constraint point is off screen in this frame (outside the image or behind the \
             camera), so it has no view ray to read V̄ and depth from",
        )),
        ProjectedPoint::Occluded => Err(Error::invalid(
            field,
            "constraint point is occluded in this frame (another surface is in front of it), \
             so its pixel's V̄ and depth belong to that surface",
        )),
    }
}

/// `[f(0), f(1), f(2), f(3)]`, written out so that it always inlines in per-pixel loops.
#[inline(always)]
fn lanes<T>(f: impl Fn(usize) -> T) -> [T; 4] {
    [f(0), f(1), f(2), f(3)]
}

/// Clamps to [0, 1]; NaN gives 0.
#[inline(always)]
#[allow(clippy::manual_clamp)] // `clamp` keeps NaN; `max` returns the other operand.
fn unit(v: f32) -> f32 {
    v.max(0.0).min(1.0)
}

impl TfLayer {
    pub fn opacity(&self) -> f32 {
        match self {
            TfLayer::Solid { opacity, .. }
            | TfLayer::Gradient { opacity, .. }
            | TfLayer::Image { opacity, .. }
            | TfLayer::Diffusion { opacity, .. } => *opacity,
        }
    }

    pub fn blend(&self) -> BlendMode {
        match self {
            TfLayer::Solid { blend, .. }
            | TfLayer::Gradient { blend, .. }
            | TfLayer::Image { blend, .. }
            | TfLayer::Diffusion { blend, .. } => *blend,
        }
    }

    /// Checks the layer's values; `field` is its path, e.g. `style.tf.layers[2]`. Image files
    /// are not opened here; baking reports their errors.
    pub fn validate_at(&self, field: &str) -> Result<()> {
        let opacity = self.opacity();
        if !(0.0..=1.0).contains(&opacity) {
            return Err(Error::invalid(
                format!("{field}.opacity"),
                format!("must be in [0, 1], got {opacity}"),
            ));
        }
        match self {
            TfLayer::Solid { color, .. } => check_color(&format!("{field}.color"), color),
            TfLayer::Gradient { shape, stops, .. } => {
                check_shape(&format!("{field}.shape"), shape)?;
                if stops.is_empty() {
                    return Err(Error::invalid(
                        format!("{field}.stops"),
                        "a gradient needs at least one colour stop",
                    ));
                }
                for (k, stop) in stops.iter().enumerate() {
                    if !(0.0..=1.0).contains(&stop.position) {
                        return Err(Error::invalid(
                            format!("{field}.stops[{k}].position"),
                            format!("must be in [0, 1], got {}", stop.position),
                        ));
                    }
                    check_color(&format!("{field}.stops[{k}].color"), &stop.color)?;
                }
                Ok(())
            }
            TfLayer::Image { image, .. } => match image {
                ImageSource::File { path } => {
                    if path.as_os_str().is_empty() {
                        return Err(Error::invalid(
                            format!("{field}.image.path"),
                            "is empty; give a .png or .exr file",
                        ));
                    }
                    image_format(&format!("{field}.image.path"), path).map(|_| ())
                }
                ImageSource::Pixels {
                    width,
                    height,
                    rgba,
                } => check_pixels(&format!("{field}.image"), *width, *height, rgba),
            },
            TfLayer::Diffusion { constraints, .. } => {
                for (k, constraint) in constraints.iter().enumerate() {
                    let at = format!("{field}.constraints[{k}]");
                    let [v, u] = constraint.position;
                    if !((0.0..=1.0).contains(&v) && (0.0..=1.0).contains(&u)) {
                        return Err(Error::invalid(
                            format!("{at}.position"),
                            format!("must be inside the TF square [0, 1]², got [{v}, {u}]"),
                        ));
                    }
                    check_color(&format!("{at}.color"), &constraint.color)?;
                    if let Some(point) = constraint.world_point {
                        if point.iter().any(|c| !c.is_finite()) {
                            return Err(Error::invalid(
                                format!("{at}.world_point"),
                                format!("must be finite, got {point:?}"),
                            ));
                        }
                    }
                }
                Ok(())
            }
        }
    }

    /// The layer's straight RGBA at every texel of an `n × n` texture. `field` names the
    /// layer in errors.
    fn evaluate(&self, n: usize, field: &str) -> Result<Vec<Rgba>> {
        let center = |i: usize| (i as f32 + 0.5) / n as f32;
        match self {
            TfLayer::Solid { color, .. } => Ok(vec![*color; n * n]),
            TfLayer::Gradient { shape, stops, .. } => {
                let mut sorted = stops.clone();
                // Stable, so equal positions keep their order and make a step.
                sorted.sort_by(|a, b| a.position.total_cmp(&b.position));
                let mut out = vec![[0.0; 4]; n * n];
                out.par_chunks_mut(n).enumerate().for_each(|(j, row)| {
                    for (i, texel) in row.iter_mut().enumerate() {
                        *texel = gradient_color(&sorted, shape.parameter([center(i), center(j)]));
                    }
                });
                Ok(out)
            }
            TfLayer::Image { image, .. } => {
                let (width, height, pixels) = match image {
                    ImageSource::File { path } => load_image(&format!("{field}.image.path"), path)?,
                    ImageSource::Pixels {
                        width,
                        height,
                        rgba,
                    } => (*width, *height, rgba.clone()),
                };
                Ok(resample(width as usize, height as usize, &pixels, n))
            }
            TfLayer::Diffusion { constraints, .. } => {
                let texel = |p: f32| ((p * n as f32) as u32).min(n as u32 - 1);
                let pins: Vec<Pin> = constraints
                    .iter()
                    .map(|c| Pin {
                        x: texel(c.position[0]),
                        y: texel(c.position[1]),
                        value: c.color,
                    })
                    .collect();
                let solution =
                    diffusion::solve(n as u32, n as u32, &pins, diffusion::DEFAULT_TOLERANCE)
                        .map_err(|e| match e {
                            Error::InvalidInput { field: f, reason } => {
                                Error::invalid(format!("{field}.{f}"), reason)
                            }
                            other => other,
                        })?;
                Ok(solution.values)
            }
        }
    }
}

impl GradientShape {
    /// The gradient position at TF point `p`, clamped to [0, 1].
    fn parameter(&self, p: [f32; 2]) -> f32 {
        match *self {
            GradientShape::Linear { from, to } => {
                let d = [to[0] - from[0], to[1] - from[1]];
                let t = ((p[0] - from[0]) * d[0] + (p[1] - from[1]) * d[1])
                    / (d[0] * d[0] + d[1] * d[1]);
                unit(t)
            }
            GradientShape::Radial { center, radius } => {
                unit((p[0] - center[0]).hypot(p[1] - center[1]) / radius)
            }
        }
    }
}

/// Piecewise-linear interpolation of sorted stops.
fn gradient_color(stops: &[ColorStop], t: f32) -> Rgba {
    let (Some(first), Some(last)) = (stops.first(), stops.last()) else {
        return [0.0; 4];
    };
    if t <= first.position {
        return first.color;
    }
    if t >= last.position {
        return last.color;
    }
    for pair in stops.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        if t < b.position {
            let span = b.position - a.position;
            let w = if span > 0.0 {
                (t - a.position) / span
            } else {
                1.0
            };
            return lanes(|c| (1.0 - w) * a.color[c] + w * b.color[c]);
        }
    }
    last.color
}

/// Bilinear resampling of a straight-RGBA image (rows top to bottom) to the `n × n` TF
/// grid, texel centres to texel centres, clamped at the edges. TF row `j` (u rising) reads
/// the image from its bottom row up. Interpolation runs on premultiplied values so that
/// transparent pixels do not bleed their colour, and the result is straight again.
fn resample(width: usize, height: usize, pixels: &[Rgba], n: usize) -> Vec<Rgba> {
    let premultiplied: Vec<Rgba> = pixels
        .iter()
        .map(|p| [p[0] * p[3], p[1] * p[3], p[2] * p[3], p[3]])
        .collect();
    let axis = |i: usize, size: usize| {
        let x = ((i as f32 + 0.5) / n as f32 * size as f32 - 0.5).clamp(0.0, (size - 1) as f32);
        let i0 = (x as usize).min(size - 1);
        (i0, (i0 + 1).min(size - 1), x - i0 as f32)
    };
    let mut out = vec![[0.0; 4]; n * n];
    out.par_chunks_mut(n).enumerate().for_each(|(j, row)| {
        let (y0, y1, fy) = axis(n - 1 - j, height);
        for (i, texel) in row.iter_mut().enumerate() {
            let (x0, x1, fx) = axis(i, width);
            let p = |x: usize, y: usize| &premultiplied[y * width + x];
            let (a, b, c, d) = (p(x0, y0), p(x1, y0), p(x0, y1), p(x1, y1));
            let v: Rgba = lanes(|k| {
                (1.0 - fy) * ((1.0 - fx) * a[k] + fx * b[k]) + fy * ((1.0 - fx) * c[k] + fx * d[k])
            });
            *texel = if v[3] > 0.0 {
                [v[0] / v[3], v[1] / v[3], v[2] / v[3], v[3]]
            } else {
                [0.0; 4]
            };
        }
    });
    out
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum ImageFormat {
    Png,
    Exr,
}

fn image_format(field: &str, path: &Path) -> Result<ImageFormat> {
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match extension.as_deref() {
        Some("png") => Ok(ImageFormat::Png),
        Some("exr") => Ok(ImageFormat::Exr),
        _ => Err(Error::invalid(
            field,
            format!(
                "{} is not a .png or .exr file, the image formats a TF layer reads",
                path.display()
            ),
        )),
    }
}

/// A mesh's alpha mask from a .png or .exr file (`field` names it in errors): the alpha
/// channel, rows turned to run from v = 0, the image's bottom row, up.
pub fn load_alpha_mask(
    field: &str,
    path: &Path,
    threshold: f32,
) -> Result<crate::cutout::AlphaMask<'static>> {
    let (width, height, rgba) = load_image(field, path).map_err(|error| match error {
        Error::InvalidInput { .. } => error,
        other => Error::invalid(field, format!("cannot read {}: {other}", path.display())),
    })?;
    let alpha: Vec<f32> = rgba
        .chunks_exact(width as usize)
        .rev()
        .flat_map(|row| row.iter().map(|texel| texel[3]))
        .collect();
    Ok(crate::cutout::AlphaMask::repeating(
        width,
        height,
        std::borrow::Cow::Owned(alpha),
        threshold,
    ))
}

/// Reads an image layer's file as straight linear RGBA, rows top to bottom.
fn load_image(field: &str, path: &Path) -> Result<(u32, u32, Vec<Rgba>)> {
    let (width, height, rgba) = match image_format(field, path)? {
        ImageFormat::Png => load_png(path)?,
        ImageFormat::Exr => load_exr(path)?,
    };
    check_pixels(field, width, height, &rgba).map_err(|e| match e {
        Error::InvalidInput { reason, .. } => {
            Error::invalid(field, format!("image {}: {reason}", path.display()))
        }
        other => other,
    })?;
    Ok((width, height, rgba))
}

fn load_png(path: &Path) -> Result<(u32, u32, Vec<Rgba>)> {
    let bytes = std::fs::read(path).map_err(|source| Error::io(path, source))?;
    let png_error = |reason: String| Error::Png {
        path: path.to_path_buf(),
        reason,
    };
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    // Palettes, low bit depths and tRNS transparency become 8-bit gray/RGB(A).
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| png_error(e.to_string()))?;
    let (width, height) = reader.info().size();
    if u64::from(width) * u64::from(height) > MAX_IMAGE_PIXELS {
        return Err(png_error(format!(
            "{width}x{height} is larger than the {MAX_IMAGE_PIXELS} pixels a TF image may have"
        )));
    }
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| png_error("image too large to decode".into()))?;
    let mut buffer = vec![0u8; size];
    let frame = reader
        .next_frame(&mut buffer)
        .map_err(|e| png_error(e.to_string()))?;
    let channels = frame.color_type.samples();
    let wide = frame.bit_depth == png::BitDepth::Sixteen;
    let sample_bytes = if wide { 2 } else { 1 };
    let max = if wide { 65535.0 } else { 255.0 };
    let mut rgba = Vec::with_capacity(width as usize * height as usize);
    for line in buffer
        .chunks_exact(frame.line_size)
        .take(frame.height as usize)
    {
        for pixel in line
            .chunks_exact(channels * sample_bytes)
            .take(frame.width as usize)
        {
            let sample = |k: usize| -> f32 {
                let v = if wide {
                    u16::from_be_bytes([pixel[2 * k], pixel[2 * k + 1]])
                } else {
                    u16::from(pixel[k])
                };
                f32::from(v) / max
            };
            let (rgb, a) = match channels {
                1 => ([sample(0); 3], 1.0),
                2 => ([sample(0); 3], sample(1)),
                3 => ([sample(0), sample(1), sample(2)], 1.0),
                _ => ([sample(0), sample(1), sample(2)], sample(3)),
            };
            let rgb = rgb.map(srgb_eotf);
            rgba.push([rgb[0], rgb[1], rgb[2], a]);
        }
    }
    Ok((frame.width, frame.height, rgba))
}

/// Decodes an sRGB-encoded value in [0, 1] to linear.
fn srgb_eotf(v: f32) -> f32 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

fn load_exr(path: &Path) -> Result<(u32, u32, Vec<Rgba>)> {
    let image = crate::exr_file::read_exr(path)?;
    let rgba = image.beauty_rgba().ok_or_else(|| Error::Exr {
        path: path.to_path_buf(),
        reason: "no R, G, B channels (nor a view layer's Combined pass) to read a TF image from"
            .into(),
    })?;
    let width = image.width as usize;
    if let Some(k) = rgba.iter().position(|v| !v.is_finite()) {
        let pixel = k / 4;
        return Err(Error::Exr {
            path: path.to_path_buf(),
            reason: format!(
                "pixel ({}, {}) has a non-finite value, which a TF image cannot hold",
                pixel % width.max(1),
                pixel / width.max(1)
            ),
        });
    }
    // EXR stores premultiplied colour; TF layers hold straight colour. Renders may hold small
    // negative values (filter ringing) or alpha above 1: those are clamped.
    let straight = rgba
        .chunks_exact(4)
        .map(|p| {
            let a = unit(p[3]);
            if a > 0.0 {
                [p[0] / a, p[1] / a, p[2] / a, a].map(|v| v.max(0.0))
            } else {
                [0.0; 4]
            }
        })
        .collect();
    Ok((image.width, image.height, straight))
}

fn check_color(field: &str, color: &Rgba) -> Result<()> {
    if let Some(c) = color.iter().position(|v| !v.is_finite()) {
        return Err(Error::invalid(
            field,
            format!("channel {c} must be finite, got {}", color[c]),
        ));
    }
    if let Some(c) = color[..3].iter().position(|&v| v < 0.0) {
        return Err(Error::invalid(
            field,
            format!("channel {c} must not be negative, got {}", color[c]),
        ));
    }
    if !(0.0..=1.0).contains(&color[3]) {
        return Err(Error::invalid(
            field,
            format!("alpha must be in [0, 1], got {}", color[3]),
        ));
    }
    Ok(())
}

fn check_point(field: &str, p: [f32; 2]) -> Result<()> {
    if p.iter().any(|c| !c.is_finite()) {
        return Err(Error::invalid(field, format!("must be finite, got {p:?}")));
    }
    Ok(())
}

fn check_shape(field: &str, shape: &GradientShape) -> Result<()> {
    match *shape {
        GradientShape::Linear { from, to } => {
            check_point(&format!("{field}.from"), from)?;
            check_point(&format!("{field}.to"), to)?;
            let length = (to[0] - from[0]).hypot(to[1] - from[1]);
            if !(length > 1e-6 && length.is_finite()) {
                return Err(Error::invalid(
                    format!("{field}.to"),
                    format!("must differ from `from` ({from:?}), got {to:?}"),
                ));
            }
        }
        GradientShape::Radial { center, radius } => {
            check_point(&format!("{field}.center"), center)?;
            if !(radius > 1e-6 && radius.is_finite()) {
                return Err(Error::invalid(
                    format!("{field}.radius"),
                    format!("must be a positive number, got {radius}"),
                ));
            }
        }
    }
    Ok(())
}

fn check_pixels(field: &str, width: u32, height: u32, rgba: &[Rgba]) -> Result<()> {
    if width == 0 || height == 0 || u64::from(width) * u64::from(height) > MAX_IMAGE_PIXELS {
        return Err(Error::invalid(
            format!("{field}.width"),
            format!(
                "the image must have between 1 and {MAX_IMAGE_PIXELS} pixels, got \
                 {width}x{height}"
            ),
        ));
    }
    let expected = width as usize * height as usize;
    if rgba.len() != expected {
        return Err(Error::invalid(
            format!("{field}.rgba"),
            format!(
                "has {} pixels, expected {expected} for {width}x{height}",
                rgba.len()
            ),
        ));
    }
    for (k, pixel) in rgba.iter().enumerate() {
        check_color(&format!("{field}.rgba[{k}]"), pixel).map_err(|e| match e {
            Error::InvalidInput { reason, .. } => Error::invalid(
                format!("{field}.rgba[{k}]"),
                format!(
                    "pixel ({}, {}): {reason}",
                    k % width as usize,
                    k / width as usize
                ),
            ),
            other => other,
        })?;
    }
    Ok(())
}

/// Composites layers, bottom first, into a premultiplied texture; see the module docs.
/// `field` leads the layers' paths in errors (e.g. `style.tf.layers`).
pub fn bake_layers(layers: &[TfLayer], resolution: u32, field: &str) -> Result<TfTexture> {
    check_resolution(&format!("{field}.resolution"), resolution)?;
    for (k, layer) in layers.iter().enumerate() {
        layer.validate_at(&format!("{field}[{k}]"))?;
    }
    let n = resolution as usize;
    let mut texels = vec![[0.0f32; 4]; n * n];
    for (k, layer) in layers.iter().enumerate() {
        let colors = layer.evaluate(n, &format!("{field}[{k}]"))?;
        let (opacity, mode) = (layer.opacity(), layer.blend());
        texels
            .par_chunks_mut(n)
            .zip(colors.par_chunks(n))
            .for_each(|(row, colors)| {
                for (dst, src) in row.iter_mut().zip(colors) {
                    *dst = blend(*dst, *src, opacity, mode);
                }
            });
    }
    Ok(TfTexture::with_texels(resolution, texels))
}

/// Composites straight `src` with layer `opacity` onto premultiplied `dst`.
pub fn blend(dst: Rgba, src: Rgba, opacity: f32, mode: BlendMode) -> Rgba {
    let alpha = unit(opacity * src[3]);
    let below = dst[3];
    let mut out = [0.0; 4];
    for c in 0..3 {
        let (s, d) = (src[c].max(0.0), dst[c]);
        out[c] = match mode {
            BlendMode::Alpha => alpha * s + (1.0 - alpha) * d,
            BlendMode::Add => alpha * s + d,
            BlendMode::Multiply => alpha * (1.0 - below) * s + alpha * s * d + (1.0 - alpha) * d,
        };
    }
    out[3] = unit(alpha + (1.0 - alpha) * below);
    out
}

fn check_resolution(field: &str, resolution: u32) -> Result<()> {
    if resolution == 0 || resolution > MAX_RESOLUTION {
        return Err(Error::invalid(
            field,
            format!("must be between 1 and {MAX_RESOLUTION} texels, got {resolution}"),
        ));
    }
    Ok(())
}

impl TransferFunction {
    /// A static stack at the default resolution.
    pub fn new(mode: TfMode, depth_range: DepthRange, layers: Vec<TfLayer>) -> Self {
        TransferFunction {
            mode,
            depth_range,
            resolution: DEFAULT_RESOLUTION,
            layers,
            keyframes: Vec::new(),
        }
    }

    /// Parses JSON; unknown keys and type errors name their path under `style.tf`.
    pub fn from_json(text: &str) -> Result<Self> {
        let tf: TransferFunction = crate::scene::parse_json_at(FIELD, text)?;
        tf.validate()?;
        Ok(tf)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a transfer function always serializes to JSON")
    }

    /// Makes relative image paths relative to `base` (the directory of the file that named
    /// them) rather than to whatever the working directory is when the TF is baked: a
    /// preset must find its images from a farm job or a Blender session alike.
    pub fn rebase_image_paths(&mut self, base: &std::path::Path) {
        let keyframed = self
            .keyframes
            .iter_mut()
            .flat_map(|key| key.layers.iter_mut());
        for layer in self.layers.iter_mut().chain(keyframed) {
            if let TfLayer::Image {
                image: ImageSource::File { path },
                ..
            } = layer
            {
                if path.is_relative() {
                    *path = base.join(&*path);
                }
            }
        }
    }

    /// [`Self::validate_at`] under `style.tf`.
    pub fn validate(&self) -> Result<()> {
        self.validate_at(FIELD)
    }

    /// Checks every value and names the first offending field under `field`.
    pub fn validate_at(&self, field: &str) -> Result<()> {
        check_resolution(&format!("{field}.resolution"), self.resolution)?;
        self.depth_range
            .validate_at(&format!("{field}.depth_range"))?;
        if !self.keyframes.is_empty() && !self.layers.is_empty() {
            return Err(Error::invalid(
                format!("{field}.layers"),
                "must be empty when keyframes are given (each key frame holds its own layers)",
            ));
        }
        for (k, layer) in self.layers.iter().enumerate() {
            layer.validate_at(&format!("{field}.layers[{k}]"))?;
        }
        let mut previous: Option<f32> = None;
        for (k, key) in self.keyframes.iter().enumerate() {
            let at = format!("{field}.keyframes[{k}]");
            if !key.time.is_finite() {
                return Err(Error::invalid(
                    format!("{at}.time"),
                    format!("must be finite, got {}", key.time),
                ));
            }
            if let Some(before) = previous {
                if key.time <= before {
                    return Err(Error::invalid(
                        format!("{at}.time"),
                        format!(
                            "key frames must be in increasing time order, got {} after {before}",
                            key.time
                        ),
                    ));
                }
            }
            previous = Some(key.time);
            for (j, layer) in key.layers.iter().enumerate() {
                layer.validate_at(&format!("{at}.layers[{j}]"))?;
            }
        }
        Ok(())
    }

    /// The settings [`apply`] needs, with the scene's light colour.
    pub fn apply_settings(&self, light_color: [f32; 3]) -> ApplySettings {
        ApplySettings {
            mode: self.mode,
            depth_range: self.depth_range,
            light_color,
        }
    }

    /// The texture at `time`: the static stack, or the linear mix of the two key frames
    /// around `time` (only those two are baked).
    pub fn bake(&self, time: f32) -> Result<TfTexture> {
        self.validate()?;
        if self.keyframes.is_empty() {
            return bake_layers(&self.layers, self.resolution, &format!("{FIELD}.layers"));
        }
        let times: Vec<f32> = self.keyframes.iter().map(|k| k.time).collect();
        let (a, b, w) = bracket(&times, time);
        let bake_key = |k: usize| {
            bake_layers(
                &self.keyframes[k].layers,
                self.resolution,
                &format!("{FIELD}.keyframes[{k}].layers"),
            )
        };
        let first = bake_key(a)?;
        if a == b || w == 0.0 {
            return Ok(first);
        }
        let second = bake_key(b)?;
        first.lerp(&second, w)
    }

    /// Every key frame baked, for animation: see [`BakedKeyframes::at`]. A static stack gives
    /// one key at time 0.
    pub fn bake_keyframes(&self) -> Result<BakedKeyframes> {
        self.validate()?;
        if self.keyframes.is_empty() {
            let texture = bake_layers(&self.layers, self.resolution, &format!("{FIELD}.layers"))?;
            return BakedKeyframes::new(vec![(0.0, texture)]);
        }
        let keys = self
            .keyframes
            .iter()
            .enumerate()
            .map(|(k, key)| {
                let field = format!("{FIELD}.keyframes[{k}].layers");
                Ok((key.time, bake_layers(&key.layers, self.resolution, &field)?))
            })
            .collect::<Result<Vec<_>>>()?;
        BakedKeyframes::new(keys)
    }

    /// Moves every 3D constraint (one with a `world_point`) to where its point lands in the
    /// current frame; `locate` projects a world point and reads the layers at its pixel.
    /// An off-screen or occluded point is an error naming the constraint.
    pub fn resolve_world_constraints(
        &mut self,
        mut locate: impl FnMut([f32; 3]) -> ProjectedPoint,
    ) -> Result<()> {
        let range = self.depth_range;
        let stacks = std::iter::once((format!("{FIELD}.layers"), &mut self.layers)).chain(
            self.keyframes
                .iter_mut()
                .enumerate()
                .map(|(k, key)| (format!("{FIELD}.keyframes[{k}].layers"), &mut key.layers)),
        );
        for (field, layers) in stacks {
            for (k, layer) in layers.iter_mut().enumerate() {
                if let TfLayer::Diffusion { constraints, .. } = layer {
                    for (j, constraint) in constraints.iter_mut().enumerate() {
                        if let Some(point) = constraint.world_point {
                            let at = format!("{field}[{k}].constraints[{j}].world_point");
                            constraint.position = constraint_position(&at, locate(point), &range)?;
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// The keys around `time` and the weight of the second: clamped outside the keys. `times`
/// is non-empty and increasing.
fn bracket(times: &[f32], time: f32) -> (usize, usize, f32) {
    let last = times.len() - 1;
    if time.is_nan() || time <= times[0] {
        return (0, 0, 0.0);
    }
    if time >= times[last] {
        return (last, last, 0.0);
    }
    // times[a] < time < times[last]: find the key at or before `time`.
    let b = times.partition_point(|&t| t <= time);
    let a = b - 1;
    let w = (time - times[a]) / (times[b] - times[a]);
    (a, b, w)
}

impl TfTexture {
    /// Wraps texels already checked: `size ≥ 1`, `size²` finite texels.
    fn with_texels(size: u32, texels: Vec<Rgba>) -> TfTexture {
        let n = size as usize;
        let p = n + 2;
        let mut padded = vec![[0.0; 4]; p * p];
        for (j, row) in padded.chunks_exact_mut(p).enumerate() {
            let source = j.clamp(1, n) - 1;
            for (i, texel) in row.iter_mut().enumerate() {
                *texel = texels[source * n + i.clamp(1, n) - 1];
            }
        }
        TfTexture {
            size,
            texels,
            padded,
        }
    }

    /// A texture from premultiplied texels, `size × size`, row `j` at `u = (j + 0.5)/size`.
    /// Alpha is clamped to [0, 1] and colour to ≥ 0; non-finite values are refused.
    pub fn from_texels(size: u32, texels: Vec<Rgba>) -> Result<Self> {
        check_resolution("size", size)?;
        let expected = size as usize * size as usize;
        if texels.len() != expected {
            return Err(Error::invalid(
                "texels",
                format!("has {} texels, expected {expected}", texels.len()),
            ));
        }
        if let Some(k) = texels.iter().position(|t| t.iter().any(|v| !v.is_finite())) {
            return Err(Error::invalid(
                format!("texels[{k}]"),
                format!("must be finite, got {:?}", texels[k]),
            ));
        }
        let texels = texels
            .into_iter()
            .map(|t| [t[0].max(0.0), t[1].max(0.0), t[2].max(0.0), unit(t[3])])
            .collect();
        Ok(TfTexture::with_texels(size, texels))
    }

    /// Opaque white: the identity of [`TfMode::Monochrome`] (and of [`TfMode::Color`] under a
    /// white light).
    pub fn white(size: u32) -> Result<Self> {
        Self::from_texels(size, vec![[1.0; 4]; size as usize * size as usize])
    }

    pub fn size(&self) -> u32 {
        self.size
    }

    /// Premultiplied texels, row-major.
    pub fn texels(&self) -> &[Rgba] {
        &self.texels
    }

    /// Bilinear lookup at TF position (V̄, u), texel centres at `(i + 0.5)/size`, clamped to
    /// the edge texels. Coordinates are clamped to [0, 1] (NaN reads as 0).
    pub fn sample(&self, visibility: f32, u: f32) -> Rgba {
        bilinear(&self.padded, self.size as usize, visibility, u)
    }

    /// `(1 − w)·self + w·other`, texel by texel; `w = 0` gives `self` and `w = 1` gives
    /// `other` exactly.
    pub fn lerp(&self, other: &TfTexture, w: f32) -> Result<TfTexture> {
        if other.size != self.size {
            return Err(Error::invalid(
                "keyframes",
                format!(
                    "textures of different sizes ({} and {}) cannot be interpolated",
                    self.size, other.size
                ),
            ));
        }
        if !w.is_finite() {
            return Err(Error::invalid("weight", format!("must be finite, got {w}")));
        }
        let texels = self
            .texels
            .iter()
            .zip(&other.texels)
            .map(|(a, b)| lanes(|k| (1.0 - w) * a[k] + w * b[k]))
            .collect();
        Ok(TfTexture::with_texels(self.size, texels))
    }
}

/// Bilinear lookup in a padded `(n + 2)²` texture (see [`TfTexture`]'s `padded`): texel
/// `i`'s centre is at padded coordinate `i + 1.5`, so `t = 0` lands on 0.5 and `t = 1` on
/// `n + 0.5`, both inside the border, and no index needs clamping.
#[inline(always)]
fn bilinear(padded: &[Rgba], n: usize, visibility: f32, u: f32) -> Rgba {
    // A range of one with near 0 makes the depth argument u itself.
    let lookup = Lookup::new(
        n,
        &DepthRange {
            near: 0.0,
            far: 1.0,
        },
    );
    lookup.sample(padded, visibility, u)
}

impl BakedKeyframes {
    /// Keys `(time, texture)` in strictly increasing time order, all of one size.
    pub fn new(keys: Vec<(f32, TfTexture)>) -> Result<Self> {
        if keys.is_empty() {
            return Err(Error::invalid("keyframes", "needs at least one key frame"));
        }
        for (k, (time, texture)) in keys.iter().enumerate() {
            if !time.is_finite() {
                return Err(Error::invalid(
                    format!("keyframes[{k}].time"),
                    format!("must be finite, got {time}"),
                ));
            }
            if k > 0 && *time <= keys[k - 1].0 {
                return Err(Error::invalid(
                    format!("keyframes[{k}].time"),
                    format!(
                        "key frames must be in increasing time order, got {time} after {}",
                        keys[k - 1].0
                    ),
                ));
            }
            if texture.size != keys[0].1.size {
                return Err(Error::invalid(
                    format!("keyframes[{k}]"),
                    format!(
                        "is {0}x{0} texels but the first key is {1}x{1}",
                        texture.size, keys[0].1.size
                    ),
                ));
            }
        }
        Ok(BakedKeyframes { keys })
    }

    pub fn keys(&self) -> &[(f32, TfTexture)] {
        &self.keys
    }

    /// The TF at `time`: a key's own texture at its time, the linear mix between the two
    /// keys around `time`, and the first or last key before or after them (NaN: the first).
    pub fn at(&self, time: f32) -> TfTexture {
        let times: Vec<f32> = self.keys.iter().map(|k| k.0).collect();
        let (a, b, w) = bracket(&times, time);
        if a == b || w == 0.0 {
            return self.keys[a].1.clone();
        }
        let (first, second) = (&self.keys[a].1, &self.keys[b].1);
        let texels = first
            .texels
            .iter()
            .zip(&second.texels)
            .map(|(p, q)| lanes(|k| (1.0 - w) * p[k] + w * q[k]))
            .collect();
        TfTexture::with_texels(first.size, texels)
    }
}

impl ApplySettings {
    pub fn validate(&self) -> Result<()> {
        self.depth_range.validate_at("depth_range")?;
        if let Some(c) = self
            .light_color
            .iter()
            .position(|v| !(v.is_finite() && *v >= 0.0))
        {
            return Err(Error::invalid(
                format!("light_color[{c}]"),
                format!(
                    "must be a finite non-negative number, got {}",
                    self.light_color[c]
                ),
            ));
        }
        Ok(())
    }
}

/// Channels below this fraction of the light's largest channel count as absent.
const ABSENT_CHANNEL: f32 = 1e-4;

/// `K = M·L`: radiance per unit light colour, see the module docs.
#[derive(Clone, Copy)]
enum PerLight {
    /// Every channel present: `K_c = L_c / Ĉ_c`.
    Diagonal([f32; 3]),
    Matrix([[f32; 3]; 3]),
}

impl PerLight {
    fn new(light: [f32; 3]) -> PerLight {
        let peak = light[0].max(light[1]).max(light[2]);
        if peak.is_nan() || peak <= 0.0 {
            return PerLight::Diagonal([1.0; 3]);
        }
        let hat = light.map(|c| c / peak);
        let present = hat.map(|c| c >= ABSENT_CHANNEL);
        if present.iter().all(|&p| p) {
            return PerLight::Diagonal(hat.map(|c| 1.0 / c));
        }
        let sum: f32 = (0..3).filter(|&c| present[c]).map(|c| hat[c]).sum();
        let mut m = [[0.0; 3]; 3];
        for c in 0..3 {
            if present[c] {
                m[c][c] = 1.0 / hat[c];
            } else {
                for j in (0..3).filter(|&j| present[j]) {
                    m[c][j] = 1.0 / sum;
                }
            }
        }
        PerLight::Matrix(m)
    }

    #[inline(always)]
    fn apply(&self, l: [f32; 3]) -> [f32; 3] {
        match self {
            PerLight::Diagonal(d) => [l[0] * d[0], l[1] * d[1], l[2] * d[2]],
            PerLight::Matrix(m) => {
                [0, 1, 2].map(|c| m[c][0] * l[0] + m[c][1] * l[1] + m[c][2] * l[2])
            }
        }
    }
}

/// `M` of `K = M·L` as a full matrix (rows), for backends that apply the colour rule
/// themselves.
pub fn per_light_matrix(light_color: [f32; 3]) -> [[f32; 3]; 3] {
    match PerLight::new(light_color) {
        PerLight::Diagonal(d) => [[d[0], 0.0, 0.0], [0.0, d[1], 0.0], [0.0, 0.0, d[2]]],
        PerLight::Matrix(m) => m,
    }
}

/// Applies `texture` to premultiplied `volume` RGBA in place, reading the `visibility` and
/// `depth` layers of the same `width`-pixel rows; see the module docs for the rule. Rows run
/// in parallel and each pixel is computed alone, so the result does not depend on the
/// thread count. Non-finite radiance reads as 0.
pub fn apply(
    texture: &TfTexture,
    settings: &ApplySettings,
    width: usize,
    visibility: &[f32],
    depth: &[f32],
    volume: &mut [f32],
) -> Result<()> {
    settings.validate()?;
    let pixels = visibility.len();
    if depth.len() != pixels || volume.len() != pixels * 4 {
        return Err(Error::invalid(
            "volume",
            format!(
                "layer sizes differ: {} visibility, {} depth and {} volume values (expected {} \
                 RGBA values)",
                pixels,
                depth.len(),
                volume.len(),
                pixels * 4
            ),
        ));
    }
    if pixels == 0 {
        return Ok(());
    }
    if width == 0 || !pixels.is_multiple_of(width) {
        return Err(Error::invalid(
            "width",
            format!("{width} does not divide the {pixels} pixels into rows"),
        ));
    }
    let range = settings.depth_range;
    let n = texture.size as usize;
    // The rule is linear in L with coefficients that depend on the TF sample alone, and
    // affine in the sample, so it is folded into a per-texel gain texture first: the same
    // bilinear lookup of the gains gives the rule applied to the interpolated sample.
    let gains: Vec<Rgba> = match (settings.mode, PerLight::new(settings.light_color)) {
        (TfMode::Monochrome, _) => texture
            .padded
            .iter()
            .map(|t| {
                let g = (1.0 - t[3]) + luminance([t[0], t[1], t[2]]);
                [g, g, g, 1.0]
            })
            .collect(),
        (TfMode::Color, PerLight::Diagonal(d)) => texture
            .padded
            .iter()
            .map(|t| {
                let keep = 1.0 - t[3];
                [
                    keep + t[0] * d[0],
                    keep + t[1] * d[1],
                    keep + t[2] * d[2],
                    1.0,
                ]
            })
            .collect(),
        // A light without some channel mixes channels: sample the TF and apply the rule.
        (TfMode::Color, per_light @ PerLight::Matrix(_)) => {
            let rows = volume
                .par_chunks_mut(width * 4)
                .zip(visibility.par_chunks(width))
                .zip(depth.par_chunks(width));
            rows.for_each(|((volume, visibility), depth)| {
                for ((v, s), px) in visibility.iter().zip(depth).zip(volume.chunks_exact_mut(4)) {
                    let t = bilinear(&texture.padded, n, *v, range.normalize(*s));
                    let l = [px[0], px[1], px[2]].map(finite_or_zero);
                    let k = per_light.apply(l);
                    let keep = 1.0 - t[3];
                    for c in 0..3 {
                        px[c] = keep * l[c] + t[c] * k[c];
                    }
                    px[3] = unit(px[3]);
                }
            });
            return Ok(());
        }
    };
    let lookup = Lookup::new(n, &range);
    let rows = volume
        .par_chunks_mut(width * 4)
        .zip(visibility.par_chunks(width))
        .zip(depth.par_chunks(width));
    rows.for_each(|((volume, visibility), depth)| {
        let mut at = [Texel::default(); CHUNK];
        let pixels = volume
            .chunks_mut(CHUNK * 4)
            .zip(visibility.chunks(CHUNK))
            .zip(depth.chunks(CHUNK));
        for ((volume, visibility), depth) in pixels {
            // Coordinates first, in a loop the compiler vectorizes across pixels; then the
            // texel fetches, which it cannot.
            for ((texel, v), s) in at.iter_mut().zip(visibility).zip(depth) {
                *texel = lookup.locate(*v, *s);
            }
            for (texel, px) in at.iter().zip(volume.chunks_exact_mut(4)) {
                // The gain of alpha is 1: all four lanes take the same SIMD path.
                let g = lookup.fetch(&gains, texel);
                let mut out = [0.0; 4];
                for c in 0..4 {
                    // Alpha is clamped to [0, 1]; the bounds leave finite radiance alone.
                    out[c] = finite_or_zero(g[c] * px[c]).max(LOWER[c]).min(UPPER[c]);
                }
                px.copy_from_slice(&out);
            }
        }
    });
    Ok(())
}

/// Per-lane bounds of the output: radiance unbounded, alpha in [0, 1].
const LOWER: Rgba = [f32::MIN, f32::MIN, f32::MIN, 0.0];
const UPPER: Rgba = [f32::MAX, f32::MAX, f32::MAX, 1.0];

/// Pixels whose texture coordinates are computed together.
const CHUNK: usize = 64;

/// Where a pixel's bilinear lookup reads: the padded index of its upper-left texel and the
/// weights of the texels to the right and above.
#[derive(Clone, Copy, Default)]
struct Texel {
    index: u32,
    fx: f32,
    fy: f32,
}

/// The per-pixel lookup with everything that does not change per pixel in registers.
#[derive(Clone, Copy)]
struct Lookup {
    /// Texels per side, as f32, and the padded row length.
    scale: f32,
    stride: usize,
    near: f32,
    inv_range: f32,
}

impl Lookup {
    fn new(n: usize, range: &DepthRange) -> Lookup {
        Lookup {
            scale: n as f32,
            stride: n + 2,
            near: range.near,
            inv_range: 1.0 / (range.far - range.near),
        }
    }

    /// Where [`bilinear`] reads at (V̄, normalized `depth`); see [`DepthRange::normalize`].
    #[inline(always)]
    fn locate(&self, visibility: f32, depth: f32) -> Texel {
        let x = unit(visibility) * self.scale + 0.5;
        let y = unit((depth - self.near) * self.inv_range) * self.scale + 0.5;
        let (i, j) = (lower_texel(x), lower_texel(y));
        Texel {
            index: (j * self.stride as i32 + i) as u32,
            fx: x - i as f32,
            fy: y - j as f32,
        }
    }

    #[inline(always)]
    fn fetch(&self, padded: &[Rgba], texel: &Texel) -> Rgba {
        let at = texel.index as usize;
        let top = &padded[at..at + 2];
        let bottom = &padded[at + self.stride..at + self.stride + 2];
        let (fx, fy) = (texel.fx, texel.fy);
        lanes(|k| {
            let upper = top[0][k] + fx * (top[1][k] - top[0][k]);
            let lower = bottom[0][k] + fx * (bottom[1][k] - bottom[0][k]);
            upper + fy * (lower - upper)
        })
    }

    #[inline(always)]
    fn sample(&self, padded: &[Rgba], visibility: f32, depth: f32) -> Rgba {
        self.fetch(padded, &self.locate(visibility, depth))
    }
}

/// The texel below padded coordinate `x ∈ [0.5, n + 0.5]`: `round(x − 0.5)`, found by adding
/// 2²³, where f32 has no fraction bits left, and reading the integer off the mantissa. It is
/// `floor(x)` except that an integer `x` may give `x − 1` with weight 1 on the next texel,
/// the same sample. Unlike `as i32` (which must saturate and map NaN), this vectorizes.
#[inline(always)]
fn lower_texel(x: f32) -> i32 {
    const SHIFT: f32 = 8_388_608.0; // 2²³
    ((x - 0.5 + SHIFT).to_bits() as i32) - SHIFT.to_bits() as i32
}

#[inline(always)]
fn finite_or_zero(v: f32) -> f32 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// [`apply`] to a whole layer set, in place.
pub fn apply_to_layers(
    layers: &mut Layers,
    texture: &TfTexture,
    settings: &ApplySettings,
) -> Result<()> {
    let width = layers.width as usize;
    apply(
        texture,
        settings,
        width,
        &layers.visibility,
        &layers.depth,
        &mut layers.volume,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const RANGE: DepthRange = DepthRange {
        near: 1.0,
        far: 11.0,
    };

    fn settings(mode: TfMode, light_color: [f32; 3]) -> ApplySettings {
        ApplySettings {
            mode,
            depth_range: RANGE,
            light_color,
        }
    }

    fn field_of(result: Result<impl std::fmt::Debug>) -> String {
        match result {
            Err(Error::InvalidInput { field, .. }) => field,
            other => panic!("expected InvalidInput, got {other:?}"),
        }
    }

    /// Pseudo-random layers of `width × height` pixels with radiance up to 4.
    fn sample_layers(width: u32, height: u32) -> Layers {
        let mut layers = Layers::new(width, height);
        let mut state = 0x2545_f491_u32;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state as f32 / u32::MAX as f32
        };
        for i in 0..layers.pixel_count() {
            layers.visibility[i] = next();
            layers.depth[i] = 15.0 * next();
            let v = &mut layers.volume[i * 4..i * 4 + 4];
            v.copy_from_slice(&[4.0 * next(), 2.0 * next(), next(), next()]);
        }
        layers
    }

    fn solid(color: Rgba, opacity: f32, blend: BlendMode) -> TfLayer {
        TfLayer::Solid {
            opacity,
            blend,
            color,
        }
    }

    #[test]
    fn luminance_of_white_is_exactly_one() {
        assert_eq!(luminance([1.0; 3]), 1.0);
    }

    #[test]
    fn identity_tfs_reproduce_the_physically_based_layers_exactly() {
        let physical = sample_layers(37, 23);
        let white = TfTexture::white(16).unwrap();
        let clear = bake_layers(&[], 16, "layers").unwrap();
        let cases = [
            (&white, settings(TfMode::Monochrome, [1.0, 0.5, 0.2])),
            (&white, settings(TfMode::Color, [1.0, 1.0, 1.0])),
            (&white, settings(TfMode::Color, [0.3, 0.3, 0.3])),
            (&clear, settings(TfMode::Color, [1.0, 0.5, 0.2])),
            (&clear, settings(TfMode::Monochrome, [1.0, 0.5, 0.2])),
        ];
        for (texture, settings) in cases {
            let mut layers = physical.clone();
            apply_to_layers(&mut layers, texture, &settings).unwrap();
            assert_eq!(layers, physical, "{settings:?}");
        }
    }

    #[test]
    fn colour_mode_identity_under_a_coloured_light_is_the_light_colour() {
        let light = [1.0, 0.5, 0.25];
        let physical = sample_layers(16, 8);
        // Physically based radiance under this light is proportional to it.
        let mut proportional = physical.clone();
        for px in proportional.volume.chunks_exact_mut(4) {
            let k = px[0];
            px[..3].copy_from_slice(&light.map(|c| c * k));
        }
        let own = TfTexture::from_texels(4, vec![[1.0, 0.5, 0.25, 1.0]; 16]).unwrap();
        let mut layers = proportional.clone();
        apply_to_layers(&mut layers, &own, &settings(TfMode::Color, light)).unwrap();
        for (a, b) in layers.volume.iter().zip(&proportional.volume) {
            assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{a} != {b}");
        }
        // White then recolours the shafts to white at the same intensity per unit light.
        let mut layers = proportional.clone();
        let white = TfTexture::white(4).unwrap();
        apply_to_layers(&mut layers, &white, &settings(TfMode::Color, light)).unwrap();
        for (px, original) in layers
            .volume
            .chunks_exact(4)
            .zip(proportional.volume.chunks_exact(4))
        {
            for value in &px[..3] {
                assert!((value - original[0]).abs() <= 1e-6 * original[0].max(1.0));
            }
        }
    }

    #[test]
    fn modes_follow_the_documented_rule_on_known_values() {
        // Half-covered orange: P = 0.5·(1, 0.5, 0), a = 0.5.
        let texture = TfTexture::from_texels(1, vec![[0.5, 0.25, 0.0, 0.5]]).unwrap();
        let run = |settings: ApplySettings, volume: [f32; 4]| {
            let mut volume = volume.to_vec();
            apply(&texture, &settings, 1, &[0.5], &[3.0], &mut volume).unwrap();
            volume
        };
        // Monochrome: (1 − 0.5)·L + Y(P)·L, Y(P) = 0.5·0.2126 + 0.25·0.7152.
        let y = 0.5 * 0.2126 + 0.25 * 0.7152;
        let out = run(settings(TfMode::Monochrome, [1.0; 3]), [2.0, 1.0, 0.5, 0.3]);
        for (o, l) in out.iter().zip([2.0f32, 1.0, 0.5]) {
            assert!((o - (0.5 + y) * l).abs() < 1e-6);
        }
        assert_eq!(out[3], 0.3);
        // Colour, light (1, 0.5, 0.5) → Ĉ = (1, 0.5, 0.5): K = (2, 2, 1).
        let out = run(
            settings(TfMode::Color, [2.0, 1.0, 1.0]),
            [2.0, 1.0, 0.5, 0.3],
        );
        let expected = [0.5 * 2.0 + 0.5 * 2.0, 0.5 * 1.0 + 0.25 * 2.0, 0.5 * 0.5];
        for (o, e) in out.iter().zip(expected) {
            assert!((o - e).abs() < 1e-6, "{out:?} vs {expected:?}");
        }
        // A red light has no green or blue: those channels take the red intensity.
        let out = run(
            settings(TfMode::Color, [3.0, 0.0, 0.0]),
            [2.0, 0.0, 0.0, 1.0],
        );
        let expected = [0.5 * 2.0 + 0.5 * 2.0, 0.25 * 2.0, 0.0];
        for (o, e) in out.iter().zip(expected) {
            assert!((o - e).abs() < 1e-6, "{out:?} vs {expected:?}");
        }
    }

    #[test]
    fn alpha_stays_in_unit_range_and_bad_values_do_not_spread() {
        let texture = TfTexture::white(2).unwrap();
        let mut volume = vec![
            1.0,
            1.0,
            1.0,
            f32::NAN,
            f32::NAN,
            f32::INFINITY,
            1.0,
            1.7,
            1.0,
            1.0,
            1.0,
            -0.2,
        ];
        let visibility = [f32::NAN, 0.5, 2.0];
        let depth = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
        for mode in [TfMode::Color, TfMode::Monochrome] {
            let mut v = volume.clone();
            apply(
                &texture,
                &settings(mode, [1.0; 3]),
                3,
                &visibility,
                &depth,
                &mut v,
            )
            .unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
            for a in v.chunks_exact(4).map(|p| p[3]) {
                assert!((0.0..=1.0).contains(&a));
            }
        }
        apply(
            &texture,
            &settings(TfMode::Color, [1.0; 3]),
            3,
            &visibility,
            &depth,
            &mut volume,
        )
        .unwrap();
        assert_eq!(volume[3], 0.0);
        assert_eq!(volume[7], 1.0);
        assert_eq!(volume[11], 0.0);
        assert_eq!(&volume[4..7], &[0.0, 0.0, 1.0]);
    }

    #[test]
    fn application_is_identical_for_any_thread_count() {
        let texture = bake_layers(
            &[TfLayer::Gradient {
                opacity: 0.8,
                blend: BlendMode::Alpha,
                shape: GradientShape::Radial {
                    center: [0.3, 0.6],
                    radius: 0.7,
                },
                stops: vec![
                    ColorStop {
                        position: 0.0,
                        color: [1.0, 0.2, 0.1, 1.0],
                    },
                    ColorStop {
                        position: 1.0,
                        color: [0.1, 0.3, 2.0, 0.5],
                    },
                ],
            }],
            64,
            "layers",
        )
        .unwrap();
        let layers = sample_layers(301, 67);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut copy = layers.clone();
            pool.install(|| {
                apply_to_layers(
                    &mut copy,
                    &texture,
                    &settings(TfMode::Color, [1.0, 0.8, 0.6]),
                )
            })
            .unwrap();
            std::mem::take(&mut copy.volume)
        };
        let one = run(1);
        assert_ne!(one, layers.volume);
        for threads in [2, 3, 8] {
            let other = run(threads);
            assert!(one
                .iter()
                .zip(&other)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }

    #[test]
    fn bilinear_lookup_on_a_known_texture() {
        // Texel centres at 0.25 and 0.75; row 0 is u = 0.25.
        let texture = TfTexture::from_texels(
            2,
            vec![
                [0.0, 0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 2.0, 0.0, 1.0],
                [1.0, 2.0, 4.0, 1.0],
            ],
        )
        .unwrap();
        assert_eq!(texture.sample(0.25, 0.25), [0.0, 0.0, 0.0, 0.0]);
        assert_eq!(texture.sample(0.75, 0.75), [1.0, 2.0, 4.0, 1.0]);
        assert_eq!(texture.sample(0.5, 0.5), [0.5, 1.0, 1.0, 0.5]);
        assert_eq!(texture.sample(0.375, 0.25), [0.25, 0.0, 0.0, 0.0]);
        assert_eq!(texture.sample(0.25, 0.625), [0.0, 1.5, 0.0, 0.75]);
        // Clamp to edge outside the centres, and for coordinates outside [0, 1].
        assert_eq!(texture.sample(0.0, 0.0), [0.0, 0.0, 0.0, 0.0]);
        assert_eq!(texture.sample(1.0, 0.1), [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(texture.sample(7.0, 1.0), [1.0, 2.0, 4.0, 1.0]);
        assert_eq!(texture.sample(f32::NAN, -3.0), [0.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn blend_modes_on_known_values() {
        let below = [0.2, 0.4, 0.1, 0.5]; // premultiplied: colour (0.4, 0.8, 0.2) at 50 %
        let src = [1.0, 0.5, 0.0, 0.8];
        let opacity = 0.5; // coverage α = 0.4
        let close = |a: Rgba, b: Rgba| {
            assert!(
                a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6),
                "{a:?} != {b:?}"
            )
        };
        let a = 0.4 + 0.6 * 0.5;
        close(
            blend(below, src, opacity, BlendMode::Alpha),
            [0.4 + 0.6 * 0.2, 0.2 + 0.6 * 0.4, 0.6 * 0.1, a],
        );
        close(
            blend(below, src, opacity, BlendMode::Add),
            [0.4 + 0.2, 0.2 + 0.4, 0.1, a],
        );
        // α(1 − αb)Cs + α Cs Pb + (1 − α) Pb
        close(
            blend(below, src, opacity, BlendMode::Multiply),
            [
                0.4 * 0.5 * 1.0 + 0.4 * 1.0 * 0.2 + 0.6 * 0.2,
                0.4 * 0.5 * 0.5 + 0.4 * 0.5 * 0.4 + 0.6 * 0.4,
                0.6 * 0.1,
                a,
            ],
        );
        // Onto nothing every mode shows the layer; multiply by opaque white changes nothing.
        for mode in [BlendMode::Alpha, BlendMode::Add, BlendMode::Multiply] {
            close(blend([0.0; 4], src, 1.0, mode), [0.8, 0.4, 0.0, 0.8]);
        }
        close(
            blend(below, [1.0; 4], 1.0, BlendMode::Multiply),
            [0.2 + 0.5, 0.4 + 0.5, 0.1 + 0.5, 1.0],
        );
        close(
            blend([0.3, 0.3, 0.3, 1.0], [1.0; 4], 1.0, BlendMode::Multiply),
            [0.3, 0.3, 0.3, 1.0],
        );
        // A stack: opaque grey, then multiply by half-red.
        let texture = bake_layers(
            &[
                solid([0.5, 0.5, 0.5, 1.0], 1.0, BlendMode::Alpha),
                solid([1.0, 0.0, 0.0, 1.0], 0.5, BlendMode::Multiply),
            ],
            4,
            "layers",
        )
        .unwrap();
        close(texture.sample(0.3, 0.9), [0.5, 0.25, 0.25, 1.0]);
    }

    #[test]
    fn gradient_stops_interpolate_linearly_and_clamp() {
        let n = 8;
        let stops = vec![
            ColorStop {
                position: 0.75,
                color: [0.0, 0.0, 1.0, 1.0],
            },
            ColorStop {
                position: 0.25,
                color: [1.0, 0.0, 0.0, 1.0],
            },
            ColorStop {
                position: 0.5,
                color: [0.0, 1.0, 0.0, 0.5],
            },
        ];
        let linear = TfLayer::Gradient {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            shape: GradientShape::Linear {
                from: [0.0, 0.0],
                to: [1.0, 0.0],
            },
            stops: stops.clone(),
        };
        let colors = linear.evaluate(n, "layer").unwrap();
        // Column i sits at (i + 0.5)/8 along V̄; every row is the same.
        let expect = |i: usize| -> Rgba {
            match i {
                0 | 1 => [1.0, 0.0, 0.0, 1.0], // 0.0625, 0.1875: before the first stop
                2 => [0.75, 0.25, 0.0, 0.875], // 0.3125
                3 => [0.25, 0.75, 0.0, 0.625], // 0.4375
                4 => [0.0, 0.75, 0.25, 0.625], // 0.5625
                5 => [0.0, 0.25, 0.75, 0.875], // 0.6875
                _ => [0.0, 0.0, 1.0, 1.0],     // after the last stop
            }
        };
        for j in 0..n {
            for i in 0..n {
                let got = colors[j * n + i];
                assert!(
                    got.iter().zip(expect(i)).all(|(a, b)| (a - b).abs() < 1e-6),
                    "texel ({i}, {j}): {got:?} vs {:?}",
                    expect(i)
                );
            }
        }
        // Radial: distance from the centre over the radius.
        let radial = TfLayer::Gradient {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            shape: GradientShape::Radial {
                center: [0.0625, 0.0625],
                radius: 0.5,
            },
            stops: vec![
                ColorStop {
                    position: 0.0,
                    color: [0.0; 4],
                },
                ColorStop {
                    position: 1.0,
                    color: [1.0; 4],
                },
            ],
        };
        let colors = radial.evaluate(n, "layer").unwrap();
        assert_eq!(colors[0], [0.0; 4]);
        assert!((colors[2][0] - 0.25 / 0.5).abs() < 1e-6); // two texels along V̄: 0.25 away
        assert!((colors[2 * n][1] - 0.5).abs() < 1e-6); // two texels along u
        assert_eq!(colors[n * n - 1], [1.0; 4]);
        // Two stops at one position make a step.
        let step = TfLayer::Gradient {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            shape: GradientShape::Linear {
                from: [0.0, 0.0],
                to: [1.0, 0.0],
            },
            stops: vec![
                ColorStop {
                    position: 0.5,
                    color: [0.0; 4],
                },
                ColorStop {
                    position: 0.5,
                    color: [1.0; 4],
                },
            ],
        };
        let colors = step.evaluate(n, "layer").unwrap();
        assert_eq!(colors[3], [0.0; 4]);
        assert_eq!(colors[4], [1.0; 4]);
    }

    fn diffusion(constraints: &[([f32; 2], Rgba)]) -> TfLayer {
        TfLayer::Diffusion {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            constraints: constraints
                .iter()
                .map(|&(position, color)| DiffusionConstraint {
                    position,
                    color,
                    world_point: None,
                })
                .collect(),
        }
    }

    #[test]
    fn one_diffusion_constraint_gives_a_uniform_layer() {
        let color = [0.9, 0.3, 0.125, 0.7];
        let colors = diffusion(&[([0.31, 0.77], color)])
            .evaluate(64, "layer")
            .unwrap();
        assert!(colors.iter().all(|c| *c == color));
        // Equal constraints too.
        let colors = diffusion(&[([0.1, 0.1], color), ([0.9, 0.5], color)])
            .evaluate(64, "layer")
            .unwrap();
        assert!(colors.iter().all(|c| *c == color));
    }

    #[test]
    fn two_diffusion_constraints_give_a_smooth_monotone_gradient() {
        let n = 256;
        let black = [0.0, 0.0, 0.0, 1.0];
        let white = [1.0, 1.0, 1.0, 1.0];
        // Texels 51 and 204 of row 128: mirror images about the centre.
        let layer = diffusion(&[([0.2, 0.5], black), ([0.8, 0.5], white)]);
        let colors = layer.evaluate(n, "layer").unwrap();
        let at = |i: usize, j: usize| colors[j * n + i];
        assert_eq!(at(51, 128), black);
        assert_eq!(at(204, 128), white);
        for i in 51..204 {
            assert!(at(i + 1, 128)[0] > at(i, 128)[0], "not increasing at {i}");
        }
        // Mirror symmetry: c(i) + c(255 − i) = 1, and the middle is mid-grey.
        for j in [0, 64, 128, 200, 255] {
            for i in 0..n {
                let sum = at(i, j)[0] + at(n - 1 - i, j)[0];
                assert!((sum - 1.0).abs() < 1e-4, "({i}, {j}): {sum}");
            }
        }
        // The maximum principle holds and alpha, constrained to 1 at both, stays 1.
        for c in &colors {
            assert!((0.0..=1.0).contains(&c[0]), "{c:?}");
            assert!((c[3] - 1.0).abs() < 1e-5);
        }
        // Smooth: harmonic away from the constraints.
        let pinned: Vec<bool> = (0..n * n)
            .map(|k| k == 128 * n + 51 || k == 128 * n + 204)
            .collect();
        let residual = diffusion::laplacian_residual(n, n, &colors, &pinned);
        assert!(residual.iter().all(|&r| r < 1e-5), "{residual:?}");
    }

    #[test]
    fn diffusion_meets_its_constraints_and_is_harmonic_elsewhere() {
        let n = 97;
        let constraints = [
            ([0.05, 0.1], [1.0, 0.0, 0.0, 1.0]),
            ([0.9, 0.2], [0.0, 1.0, 0.0, 0.5]),
            ([0.5, 0.95], [0.0, 0.0, 4.0, 1.0]),
            ([0.4, 0.4], [0.2, 0.2, 0.2, 0.0]),
            ([0.395, 0.395], [1.0, 1.0, 1.0, 0.0]), // same texel as the one before: averaged
        ];
        let colors = diffusion(&constraints).evaluate(n, "layer").unwrap();
        let texel = |p: [f32; 2]| (p[1] * n as f32) as usize * n + (p[0] * n as f32) as usize;
        let mut pinned = vec![false; n * n];
        for (position, color) in &constraints[..3] {
            assert_eq!(colors[texel(*position)], *color);
            pinned[texel(*position)] = true;
        }
        assert_eq!(colors[texel([0.4, 0.4])], [0.6, 0.6, 0.6, 0.0]);
        pinned[texel([0.4, 0.4])] = true;
        let residual = diffusion::laplacian_residual(n, n, &colors, &pinned);
        // The solver's tolerance is 1e-6 of each channel's scale (4 for blue), plus f32
        // rounding of the stored values.
        for (c, r) in residual.iter().enumerate() {
            let scale = if c == 2 { 4.0 } else { 1.0 };
            assert!(*r <= 2e-6 * scale, "channel {c}: {r}");
        }
        // Something actually varies.
        assert!(colors.iter().any(|c| c[0] > 0.3) && colors.iter().any(|c| c[0] < 0.1));
    }

    #[test]
    fn keyframes_hit_their_keys_and_mix_linearly_between() {
        let red = bake_layers(
            &[solid([1.0, 0.0, 0.0, 1.0], 1.0, BlendMode::Alpha)],
            8,
            "a",
        )
        .unwrap();
        let blue = bake_layers(
            &[solid([0.0, 0.0, 1.0, 0.5], 1.0, BlendMode::Alpha)],
            8,
            "b",
        )
        .unwrap();
        let green = bake_layers(
            &[solid([0.0, 1.0, 0.0, 1.0], 1.0, BlendMode::Alpha)],
            8,
            "c",
        )
        .unwrap();
        let keys = BakedKeyframes::new(vec![
            (10.0, red.clone()),
            (20.0, blue.clone()),
            (40.0, green.clone()),
        ])
        .unwrap();
        assert_eq!(keys.at(10.0), red);
        assert_eq!(keys.at(20.0), blue);
        assert_eq!(keys.at(40.0), green);
        assert_eq!(keys.at(-5.0), red);
        assert_eq!(keys.at(99.0), green);
        assert_eq!(keys.at(f32::NAN), red);
        let half = keys.at(15.0);
        assert!(half.texels().iter().all(|t| *t == [0.5, 0.0, 0.25, 0.75]));
        let quarter = keys.at(25.0);
        assert!(quarter
            .texels()
            .iter()
            .all(|t| *t == [0.0, 0.25, 0.375, 0.625]));

        // The same through a key-framed transfer function.
        let tf = TransferFunction {
            mode: TfMode::Color,
            depth_range: RANGE,
            resolution: 8,
            layers: vec![],
            keyframes: vec![
                TfKeyframe {
                    time: 10.0,
                    layers: vec![solid([1.0, 0.0, 0.0, 1.0], 1.0, BlendMode::Alpha)],
                },
                TfKeyframe {
                    time: 20.0,
                    layers: vec![solid([0.0, 0.0, 1.0, 0.5], 1.0, BlendMode::Alpha)],
                },
            ],
        };
        assert_eq!(tf.bake(10.0).unwrap(), red);
        assert_eq!(tf.bake(20.0).unwrap(), blue);
        assert_eq!(tf.bake(15.0).unwrap(), half);
        assert_eq!(tf.bake_keyframes().unwrap().at(15.0), half);
    }

    #[test]
    fn keyframes_refuse_unordered_times_and_mixed_sizes() {
        let a = TfTexture::white(4).unwrap();
        let b = TfTexture::white(8).unwrap();
        assert_eq!(
            field_of(BakedKeyframes::new(vec![
                (1.0, a.clone()),
                (1.0, a.clone())
            ])),
            "keyframes[1].time"
        );
        assert_eq!(
            field_of(BakedKeyframes::new(vec![(1.0, a), (2.0, b)])),
            "keyframes[1]"
        );
        assert_eq!(field_of(BakedKeyframes::new(vec![])), "keyframes");
    }

    #[test]
    fn image_layers_read_top_row_as_far_and_resample_bilinearly() {
        // 2×2 image: top row (far) red and green, bottom row (near) blue and transparent.
        let image = TfLayer::Image {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            image: ImageSource::Pixels {
                width: 2,
                height: 2,
                rgba: vec![
                    [1.0, 0.0, 0.0, 1.0],
                    [0.0, 1.0, 0.0, 1.0],
                    [0.0, 0.0, 1.0, 1.0],
                    [0.5, 0.5, 0.5, 0.0],
                ],
            },
        };
        let colors = image.evaluate(4, "layer").unwrap();
        let at = |i: usize, j: usize| colors[j * 4 + i];
        assert_eq!(at(0, 3), [1.0, 0.0, 0.0, 1.0]); // far, low V̄
        assert_eq!(at(3, 3), [0.0, 1.0, 0.0, 1.0]); // far, high V̄
        assert_eq!(at(0, 0), [0.0, 0.0, 1.0, 1.0]); // near, low V̄
        assert_eq!(at(3, 0), [0.0; 4]); // transparent
                                        // Texel 1 of 4 sits a quarter of the way between the two image pixels' centres:
                                        // the transparent pixel's grey does not bleed into the blue.
        let c = at(1, 0);
        assert!(
            (c[3] - 0.75).abs() < 1e-6 && c[2] == 1.0 && c[0] == 0.0,
            "{c:?}"
        );
    }

    fn temp_path(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("crepuscular-tf-{}-{name}", std::process::id()))
    }

    #[test]
    fn image_files_load_from_png_and_exr() {
        // PNG: 8-bit sRGB RGBA, 2×1.
        let png_path = temp_path("layer.png");
        {
            let mut bytes = Vec::new();
            let mut encoder = png::Encoder::new(&mut bytes, 2, 1);
            encoder.set_color(png::ColorType::Rgba);
            encoder.set_depth(png::BitDepth::Eight);
            let mut writer = encoder.write_header().unwrap();
            writer
                .write_image_data(&[255, 0, 0, 255, 188, 188, 188, 128])
                .unwrap();
            writer.finish().unwrap();
            std::fs::write(&png_path, bytes).unwrap();
        }
        let source = ImageSource::File {
            path: png_path.clone(),
        };
        let layer = TfLayer::Image {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            image: source,
        };
        let colors = layer.evaluate(2, "layer").unwrap();
        std::fs::remove_file(&png_path).ok();
        assert_eq!(colors[0], [1.0, 0.0, 0.0, 1.0]);
        // sRGB 188 is linear 0.5029; alpha 128/255.
        let c = colors[1];
        assert!(
            (c[0] - 0.502_886).abs() < 1e-4 && (c[3] - 128.0 / 255.0).abs() < 1e-6,
            "{c:?}"
        );

        // EXR: premultiplied on disk, straight in the layer.
        let exr_path = temp_path("layer.exr");
        let channels: [(&str, &[f32]); 4] = [
            ("R", &[0.25, 2.0]),
            ("G", &[0.0, -0.1]), // ringing below zero is clamped
            ("B", &[0.1, 0.0]),
            ("A", &[0.5, 1.0]),
        ];
        crate::exr_file::write_channels(
            &exr_path,
            2,
            1,
            &channels,
            crate::exr_file::Precision::F32,
            crate::exr_file::ExrCompression::Zip,
            1.0,
        )
        .unwrap();
        let layer = TfLayer::Image {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            image: ImageSource::File {
                path: exr_path.clone(),
            },
        };
        let colors = layer.evaluate(2, "layer").unwrap();
        std::fs::remove_file(&exr_path).ok();
        assert_eq!(colors[0], [0.5, 0.0, 0.2, 0.5]);
        assert_eq!(colors[1], [2.0, 0.0, 0.0, 1.0]);

        // Non-finite values are refused, naming the file.
        let nan: [(&str, &[f32]); 3] = [("R", &[f32::NAN]), ("G", &[0.0]), ("B", &[0.0])];
        crate::exr_file::write_channels(
            &exr_path,
            1,
            1,
            &nan,
            crate::exr_file::Precision::F32,
            crate::exr_file::ExrCompression::Zip,
            1.0,
        )
        .unwrap();
        let result = bake_layers(&[layer], 2, "layers");
        std::fs::remove_file(&exr_path).ok();
        match result {
            Err(Error::Exr { path, reason }) => {
                assert_eq!(path, exr_path);
                assert!(reason.contains("(0, 0)"), "{reason}");
            }
            other => panic!("expected Exr, got {other:?}"),
        }
    }

    #[test]
    fn preset_and_scene_files_find_their_images_beside_them() {
        let folder = temp_path("looks");
        std::fs::create_dir_all(&folder).unwrap();
        let tf = TransferFunction {
            keyframes: vec![TfKeyframe {
                time: 0.0,
                layers: vec![TfLayer::Image {
                    opacity: 1.0,
                    blend: BlendMode::Alpha,
                    image: ImageSource::File {
                        path: PathBuf::from("ramp.png"),
                    },
                }],
            }],
            ..TransferFunction::new(
                TfMode::Color,
                DepthRange {
                    near: 0.0,
                    far: 50.0,
                },
                Vec::new(),
            )
        };
        let style = crate::Style {
            tf: Some(tf),
            ..crate::Style::default()
        };
        let mut scene = crate::builtin_scene("torus").unwrap();
        scene.style = style.clone();
        let (style_file, scene_file) = (folder.join("look.json"), folder.join("shot.json"));
        std::fs::write(&style_file, style.to_json()).unwrap();
        std::fs::write(&scene_file, scene.to_json()).unwrap();
        let loaded_style = crate::Style::load(&style_file);
        let loaded_scene = crate::Scene::load(&scene_file);
        std::fs::remove_dir_all(&folder).ok();
        let image_path =
            |style: &crate::Style| match &style.tf.as_ref().unwrap().keyframes[0].layers[0] {
                TfLayer::Image {
                    image: ImageSource::File { path },
                    ..
                } => path.clone(),
                other => panic!("expected an image layer, got {other:?}"),
            };
        assert_eq!(image_path(&loaded_style.unwrap()), folder.join("ramp.png"));
        assert_eq!(
            image_path(&loaded_scene.unwrap().style),
            folder.join("ramp.png")
        );
        // Absolute paths stay as they are.
        let mut absolute = style.clone();
        let root = PathBuf::from("/srv/looks/ramp.png");
        if let Some(TfLayer::Image {
            image: ImageSource::File { path },
            ..
        }) = absolute.tf.as_mut().unwrap().keyframes[0]
            .layers
            .first_mut()
        {
            path.clone_from(&root);
        }
        absolute.rebase_paths(&folder);
        assert_eq!(image_path(&absolute), root);
    }

    #[test]
    fn missing_or_corrupt_image_files_name_the_path() {
        let image = |path: PathBuf| {
            vec![TfLayer::Image {
                opacity: 1.0,
                blend: BlendMode::Alpha,
                image: ImageSource::File { path },
            }]
        };
        let missing = PathBuf::from("/nonexistent/tf-layer.png");
        match bake_layers(&image(missing.clone()), 4, "style.tf.layers") {
            Err(Error::Io { path, .. }) => assert_eq!(path, missing),
            other => panic!("expected Io, got {other:?}"),
        }
        let missing = PathBuf::from("/nonexistent/tf-layer.exr");
        match bake_layers(&image(missing.clone()), 4, "style.tf.layers") {
            Err(Error::Io { path, .. }) => assert_eq!(path, missing),
            other => panic!("expected Io, got {other:?}"),
        }
        let corrupt = temp_path("corrupt.png");
        std::fs::write(&corrupt, b"not a png").unwrap();
        let result = bake_layers(&image(corrupt.clone()), 4, "style.tf.layers");
        std::fs::remove_file(&corrupt).ok();
        match result {
            Err(Error::Png { path, .. }) => assert_eq!(path, corrupt),
            other => panic!("expected Png, got {other:?}"),
        }
        let corrupt = temp_path("corrupt.exr");
        std::fs::write(&corrupt, b"not an exr").unwrap();
        let result = bake_layers(&image(corrupt.clone()), 4, "style.tf.layers");
        std::fs::remove_file(&corrupt).ok();
        match result {
            Err(Error::Exr { path, .. }) => assert_eq!(path, corrupt),
            other => panic!("expected Exr, got {other:?}"),
        }
        assert_eq!(
            field_of(bake_layers(
                &image(PathBuf::from("layer.tiff")),
                4,
                "style.tf.layers"
            )),
            "style.tf.layers[0].image.path"
        );
    }

    fn preset() -> TransferFunction {
        TransferFunction {
            mode: TfMode::Monochrome,
            depth_range: DepthRange {
                near: 0.5,
                far: 80.0,
            },
            resolution: 128,
            layers: vec![
                solid([0.2, 0.3, 0.4, 1.0], 1.0, BlendMode::Alpha),
                TfLayer::Gradient {
                    opacity: 0.5,
                    blend: BlendMode::Multiply,
                    shape: GradientShape::Linear {
                        from: [0.0, 0.0],
                        to: [1.0, 1.0],
                    },
                    stops: vec![
                        ColorStop {
                            position: 0.0,
                            color: [1.0, 0.5, 0.0, 1.0],
                        },
                        ColorStop {
                            position: 1.0,
                            color: [0.0, 0.5, 1.0, 1.0],
                        },
                    ],
                },
                TfLayer::Image {
                    opacity: 1.0,
                    blend: BlendMode::Add,
                    image: ImageSource::Pixels {
                        width: 1,
                        height: 1,
                        rgba: vec![[0.1, 0.1, 0.1, 1.0]],
                    },
                },
                TfLayer::Diffusion {
                    opacity: 0.25,
                    blend: BlendMode::Alpha,
                    constraints: vec![
                        DiffusionConstraint {
                            position: [0.1, 0.2],
                            color: [1.0, 0.0, 0.0, 1.0],
                            world_point: None,
                        },
                        DiffusionConstraint {
                            position: [0.7, 0.9],
                            color: [0.0, 0.0, 1.0, 0.5],
                            world_point: Some([1.0, 2.0, 3.0]),
                        },
                    ],
                },
            ],
            keyframes: vec![],
        }
    }

    #[test]
    fn json_round_trips_and_names_unknown_keys() {
        let tf = preset();
        let text = tf.to_json();
        assert!(text.contains("\"kind\": \"gradient\""), "{text}");
        assert_eq!(TransferFunction::from_json(&text).unwrap(), tf);
        let mut keyed = tf.clone();
        keyed.keyframes = vec![TfKeyframe {
            time: 3.0,
            layers: std::mem::take(&mut keyed.layers),
        }];
        assert_eq!(
            TransferFunction::from_json(&keyed.to_json()).unwrap(),
            keyed
        );

        // Defaults: mode colour, 256 texels, opacity 1, blend alpha.
        let minimal = r#"{"depth_range": {"near": 0, "far": 10},
            "layers": [{"kind": "solid", "color": [1, 1, 1, 1]}]}"#;
        let parsed = TransferFunction::from_json(minimal).unwrap();
        assert_eq!(parsed.mode, TfMode::Color);
        assert_eq!(parsed.resolution, DEFAULT_RESOLUTION);
        assert_eq!(parsed.layers[0].opacity(), 1.0);
        assert_eq!(parsed.layers[0].blend(), BlendMode::Alpha);

        let unknown = r#"{"depth_range": {"near": 0, "far": 10},
            "layers": [{"kind": "solid", "color": [1, 1, 1, 1], "colour": 3}]}"#;
        match TransferFunction::from_json(unknown) {
            Err(Error::SceneFormat(message)) => {
                assert!(message.contains("style.tf.layers[0]"), "{message}");
                assert!(message.contains("colour"), "{message}");
            }
            other => panic!("expected SceneFormat, got {other:?}"),
        }
        let bad_kind = r#"{"depth_range": {"near": 0, "far": 10},
            "layers": [{"kind": "sparkle"}]}"#;
        assert!(matches!(
            TransferFunction::from_json(bad_kind),
            Err(Error::SceneFormat(_))
        ));
    }

    #[test]
    fn validation_names_the_offending_field() {
        let check = |edit: &dyn Fn(&mut TransferFunction)| {
            let mut tf = preset();
            edit(&mut tf);
            field_of(tf.validate())
        };
        assert!(preset().validate().is_ok());
        assert_eq!(check(&|tf| tf.resolution = 0), "style.tf.resolution");
        assert_eq!(check(&|tf| tf.resolution = 4097), "style.tf.resolution");
        assert_eq!(
            check(&|tf| tf.depth_range.far = 0.5),
            "style.tf.depth_range.far"
        );
        assert_eq!(
            check(&|tf| tf.depth_range.near = f32::NAN),
            "style.tf.depth_range.near"
        );
        assert_eq!(
            check(&|tf| tf.layers[0] = solid([f32::NAN, 0.0, 0.0, 1.0], 1.0, BlendMode::Add)),
            "style.tf.layers[0].color"
        );
        assert_eq!(
            check(&|tf| tf.layers[0] = solid([1.0; 4], 1.5, BlendMode::Add)),
            "style.tf.layers[0].opacity"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Gradient { stops, .. } = &mut tf.layers[1] {
                    stops[1].position = 1.5;
                }
            ),
            "style.tf.layers[1].stops[1].position"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Gradient { stops, .. } = &mut tf.layers[1] {
                    stops.clear();
                }
            ),
            "style.tf.layers[1].stops"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Gradient { shape, .. } = &mut tf.layers[1] {
                    *shape = GradientShape::Linear {
                        from: [0.5, 0.5],
                        to: [0.5, 0.5],
                    };
                }
            ),
            "style.tf.layers[1].shape.to"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Gradient { shape, .. } = &mut tf.layers[1] {
                    *shape = GradientShape::Radial {
                        center: [0.5, 0.5],
                        radius: 0.0,
                    };
                }
            ),
            "style.tf.layers[1].shape.radius"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Image { image, .. } = &mut tf.layers[2] {
                    *image = ImageSource::Pixels {
                        width: 2,
                        height: 1,
                        rgba: vec![[0.0; 4]],
                    };
                }
            ),
            "style.tf.layers[2].image.rgba"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Image { image, .. } = &mut tf.layers[2] {
                    *image = ImageSource::Pixels {
                        width: 0,
                        height: 1,
                        rgba: vec![],
                    };
                }
            ),
            "style.tf.layers[2].image.width"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Image { image, .. } = &mut tf.layers[2] {
                    *image = ImageSource::Pixels {
                        width: 1,
                        height: 1,
                        rgba: vec![[0.0, 0.0, 0.0, f32::INFINITY]],
                    };
                }
            ),
            "style.tf.layers[2].image.rgba[0]"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Diffusion { constraints, .. } = &mut tf.layers[3] {
                    constraints[1].position = [0.5, 1.2];
                }
            ),
            "style.tf.layers[3].constraints[1].position"
        );
        assert_eq!(
            check(
                &|tf| if let TfLayer::Diffusion { constraints, .. } = &mut tf.layers[3] {
                    constraints[0].color[3] = 2.0;
                }
            ),
            "style.tf.layers[3].constraints[0].color"
        );
        assert_eq!(
            check(&|tf| tf.keyframes = vec![TfKeyframe {
                time: 0.0,
                layers: vec![],
            }]),
            "style.tf.layers"
        );
        assert_eq!(
            check(&|tf| {
                tf.keyframes = vec![
                    TfKeyframe {
                        time: 2.0,
                        layers: std::mem::take(&mut tf.layers),
                    },
                    TfKeyframe {
                        time: 1.0,
                        layers: vec![],
                    },
                ];
            }),
            "style.tf.keyframes[1].time"
        );
        assert_eq!(
            check(&|tf| {
                tf.keyframes = vec![TfKeyframe {
                    time: 2.0,
                    layers: vec![solid([1.0, -1.0, 0.0, 1.0], 1.0, BlendMode::Alpha)],
                }];
                tf.layers.clear();
            }),
            "style.tf.keyframes[0].layers[0].color"
        );
        // Baking validates too.
        let mut tf = preset();
        tf.resolution = 0;
        assert_eq!(field_of(tf.bake(0.0)), "style.tf.resolution");
    }

    #[test]
    fn apply_refuses_mismatched_layers_and_bad_settings() {
        let texture = TfTexture::white(2).unwrap();
        let ok = settings(TfMode::Color, [1.0; 3]);
        let mut volume = vec![0.0; 8];
        assert_eq!(
            field_of(apply(&texture, &ok, 2, &[0.0; 2], &[0.0; 3], &mut volume)),
            "volume"
        );
        assert_eq!(
            field_of(apply(&texture, &ok, 3, &[0.0; 2], &[0.0; 2], &mut volume)),
            "width"
        );
        let bad_light = settings(TfMode::Color, [1.0, f32::NAN, 0.0]);
        assert_eq!(
            field_of(apply(
                &texture,
                &bad_light,
                2,
                &[0.0; 2],
                &[0.0; 2],
                &mut volume
            )),
            "light_color[1]"
        );
        let mut bad_range = ok;
        bad_range.depth_range.far = bad_range.depth_range.near;
        assert_eq!(
            field_of(apply(
                &texture,
                &bad_range,
                2,
                &[0.0; 2],
                &[0.0; 2],
                &mut volume
            )),
            "depth_range.far"
        );
        assert_eq!(field_of(TfTexture::from_texels(0, vec![])), "size");
        assert_eq!(
            field_of(TfTexture::from_texels(2, vec![[0.0; 4]; 3])),
            "texels"
        );
    }

    #[test]
    fn depth_normalization_and_tf_positions() {
        assert_eq!(RANGE.normalize(1.0), 0.0);
        assert_eq!(RANGE.normalize(6.0), 0.5);
        assert_eq!(RANGE.normalize(11.0), 1.0);
        assert_eq!(RANGE.normalize(0.0), 0.0);
        assert_eq!(RANGE.normalize(1e9), 1.0);
        assert_eq!(RANGE.normalize(f32::INFINITY), 1.0);
        assert_eq!(RANGE.normalize(f32::NAN), 0.0);
        assert_eq!(tf_position(0.25, 8.5, &RANGE), [0.25, 0.75]);
        assert_eq!(tf_position(1.5, -2.0, &RANGE), [1.0, 0.0]);
    }

    #[test]
    fn world_constraints_move_with_their_pixel_or_name_themselves() {
        let field = "style.tf.layers[3].constraints[1].world_point";
        let visible = ProjectedPoint::Visible {
            visibility: 0.4,
            depth: 3.5,
        };
        assert_eq!(
            constraint_position(field, visible, &RANGE).unwrap(),
            [0.4, 0.25]
        );
        for point in [ProjectedPoint::OffScreen, ProjectedPoint::Occluded] {
            match constraint_position(field, point, &RANGE) {
                Err(Error::InvalidInput { field: f, reason }) => {
                    assert_eq!(f, field);
                    let word = if point == ProjectedPoint::OffScreen {
                        "off screen"
                    } else {
                        "occluded"
                    };
                    assert!(reason.contains(word), "{reason}");
                }
                other => panic!("expected InvalidInput, got {other:?}"),
            }
        }

        let mut tf = preset();
        let mut asked = Vec::new();
        tf.resolve_world_constraints(|p| {
            asked.push(p);
            ProjectedPoint::Visible {
                visibility: 0.6,
                depth: 0.5 + 79.5 * 0.3,
            }
        })
        .unwrap();
        assert_eq!(asked, vec![[1.0, 2.0, 3.0]]);
        let TfLayer::Diffusion { constraints, .. } = &tf.layers[3] else {
            panic!("layer 3 is the diffusion layer");
        };
        assert_eq!(constraints[0].position, [0.1, 0.2]); // a plain constraint stays put
        assert!((constraints[1].position[0] - 0.6).abs() < 1e-6);
        assert!((constraints[1].position[1] - 0.3).abs() < 1e-6);
        assert_eq!(
            field_of(tf.resolve_world_constraints(|_| ProjectedPoint::Occluded)),
            field
        );
    }
}
