//! Alpha cutouts: triangles that a texture's alpha makes partly empty (leaf cards, fences,
//! grilles), alpha-tested as a renderer's clip mode does. A sample of such a triangle is
//! drawn into the shadow map and the camera's depth only where the mask's alpha, filtered
//! and wrapped past its edges as the host's texture node says, reaches the mask's
//! threshold; elsewhere light and sight pass through. Without this a canopy of leaf cards
//! casts the solid shadow of its rectangles and lets no shaft through.
//!
//! Coordinates are interpolated perspective-correctly over the triangle as authored, from
//! its vertices' homogeneous pixel coordinates, so clipping (which cuts a triangle into
//! others) never has to carry them.

use std::borrow::Cow;

use glam::{DMat3, DVec3, DVec4};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// A triangle's mask index meaning it has none: opaque everywhere.
pub const OPAQUE: u32 = u32::MAX;

/// How a mask is read past its edges along one axis: Blender's Image Texture extension,
/// or USD's `wrapS`/`wrapT`, as Cycles and USD's renderers read them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Wrap {
    /// The texture tiles.
    #[default]
    Repeat,
    /// The edge texels continue outward (Blender's Extend, USD's `clamp`).
    Extend,
    /// The texture tiles, every other copy flipped.
    Mirror,
    /// The mask's `border` alpha outside (Blender's Clip and USD's `black`, whose
    /// transparent black reads as alpha 0 but for an inverted or biased alpha), the edge
    /// texels fading to it over the half texel past them.
    Clip,
}

impl Wrap {
    /// The texel read for index `i` of a side of `size` texels; `None` for none (a clipped
    /// border).
    #[inline]
    fn texel(self, i: i64, size: i64) -> Option<usize> {
        let index = match self {
            Self::Repeat => i.rem_euclid(size),
            Self::Extend => i.clamp(0, size - 1),
            // Period 2·size: size..2·size reads the side backwards, so that texel −1 is
            // texel 0 and texel `size` is texel `size` − 1.
            Self::Mirror => {
                let folded = i.rem_euclid(2 * size);
                if folded < size {
                    folded
                } else {
                    2 * size - 1 - folded
                }
            }
            Self::Clip => {
                if !(0..size).contains(&i) {
                    return None;
                }
                i
            }
        };
        Some(index as usize)
    }

    /// `x` (in texels) moved by whole periods, or clamped, into a range where every index
    /// it reads is what it reads at `x`: so that large coordinates never saturate an i64.
    #[inline]
    fn near(self, x: f64, size: f64) -> f64 {
        match self {
            Self::Repeat => x.rem_euclid(size),
            Self::Mirror => x.rem_euclid(2.0 * size),
            Self::Extend | Self::Clip => x.clamp(-2.0, size + 1.0),
        }
    }
}

/// How a mask is filtered between texels: Blender's Image Texture interpolation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskFilter {
    /// Bilinear between texel centres (Blender's Linear; Cubic and Smart are read so too).
    #[default]
    Linear,
    /// The texel a point lies in (Blender's Closest): cut edges follow the texels.
    Closest,
}

/// An alpha texture: `alpha` holds `width` × `height` values, rows from v = 0 up (the
/// order of Blender's image pixels and of OpenGL textures), read past its edges as `wrap`
/// says along u and v. Hosts lend their arrays; a scene description's images are owned.
#[derive(Clone, Debug)]
pub struct AlphaMask<'a> {
    pub width: u32,
    pub height: u32,
    pub alpha: Cow<'a, [f32]>,
    /// Samples whose filtered alpha is below this are empty.
    pub threshold: f32,
    /// Along u, then v.
    pub wrap: [Wrap; 2],
    pub filter: MaskFilter,
    /// The alpha read past a clipped edge ([`Wrap::Clip`]).
    pub border: f32,
}

impl<'a> AlphaMask<'a> {
    /// A mask that repeats and is filtered bilinearly, the defaults of Blender's Image
    /// Texture.
    pub fn repeating(width: u32, height: u32, alpha: Cow<'a, [f32]>, threshold: f32) -> Self {
        Self {
            width,
            height,
            alpha,
            threshold,
            wrap: [Wrap::Repeat; 2],
            filter: MaskFilter::Linear,
            border: 0.0,
        }
    }
}

impl AlphaMask<'_> {
    /// The alpha at (u, v), filtered and wrapped as the mask says.
    #[inline]
    pub fn alpha_at(&self, [u, v]: [f64; 2]) -> f32 {
        let (width, height) = (self.width as i64, self.height as i64);
        let [wrap_u, wrap_v] = self.wrap;
        let at = |i: Option<usize>, j: Option<usize>| match (i, j) {
            (Some(i), Some(j)) => self.alpha[j * width as usize + i],
            _ => self.border,
        };
        match self.filter {
            MaskFilter::Closest => {
                let x = wrap_u.near(u * width as f64, width as f64).floor() as i64;
                let y = wrap_v.near(v * height as f64, height as f64).floor() as i64;
                at(wrap_u.texel(x, width), wrap_v.texel(y, height))
            }
            MaskFilter::Linear => {
                let x = wrap_u.near(u * width as f64 - 0.5, width as f64);
                let y = wrap_v.near(v * height as f64 - 0.5, height as f64);
                let (x0, y0) = (x.floor(), y.floor());
                let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
                let (i0, j0) = (x0 as i64, y0 as i64);
                let [i0, i1] = [i0, i0 + 1].map(|i| wrap_u.texel(i, width));
                let [j0, j1] = [j0, j0 + 1].map(|j| wrap_v.texel(j, height));
                let bottom = at(i0, j0) + (at(i1, j0) - at(i0, j0)) * fx;
                let top = at(i0, j1) + (at(i1, j1) - at(i0, j1)) * fx;
                bottom + (top - bottom) * fy
            }
        }
    }

    /// The wrap and filter as `raster_cut.glsl`'s `Mask::sampling` packs them: bits 0–1
    /// the wrap along u, 2–3 along v, bit 4 set for closest filtering.
    pub fn shader_sampling(&self) -> u32 {
        let wrap = |wrap: Wrap| match wrap {
            Wrap::Repeat => 0,
            Wrap::Extend => 1,
            Wrap::Mirror => 2,
            Wrap::Clip => 3,
        };
        let closest = match self.filter {
            MaskFilter::Linear => 0,
            MaskFilter::Closest => 16,
        };
        wrap(self.wrap[0]) | wrap(self.wrap[1]) << 2 | closest
    }

    /// Whether the mask is solid at (u, v).
    #[inline]
    pub fn covers(&self, uv: [f64; 2]) -> bool {
        self.alpha_at(uv) >= self.threshold
    }

    fn validate(&self, index: usize) -> Result<()> {
        let field = || format!("masks[{index}]");
        let expected = self.width as usize * self.height as usize;
        if self.width == 0 || self.height == 0 {
            return Err(Error::invalid(field(), "is empty (0 texels wide or high)"));
        }
        if self.alpha.len() != expected {
            return Err(Error::invalid(
                field(),
                format!(
                    "has {} values but is {}×{} (expected {expected})",
                    self.alpha.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        if let Some(k) = self.alpha.iter().position(|a| !a.is_finite()) {
            return Err(Error::invalid(
                field(),
                format!("alpha {} at texel {k} is not finite", self.alpha[k]),
            ));
        }
        if !self.threshold.is_finite() {
            return Err(Error::invalid(
                format!("{}.threshold", field()),
                format!("{} is not finite", self.threshold),
            ));
        }
        if !self.border.is_finite() {
            return Err(Error::invalid(
                format!("{}.border", field()),
                format!("{} is not finite", self.border),
            ));
        }
        Ok(())
    }
}

/// The cutouts of a frame's geometry: texture coordinates per position, and per triangle
/// the mask it is cut by.
#[derive(Clone, Copy, Debug)]
pub struct Cutouts<'a> {
    pub uvs: &'a [[f32; 2]],
    /// Per triangle, an index into `masks`, or [`OPAQUE`].
    pub triangle_masks: &'a [u32],
    pub masks: &'a [AlphaMask<'a>],
}

impl Cutouts<'_> {
    /// Checks the arrays against the geometry's `positions` and `triangles` counts.
    pub fn validate(&self, positions: usize, triangles: usize) -> Result<()> {
        if self.uvs.len() != positions {
            return Err(Error::invalid(
                "uvs",
                format!(
                    "has {} entries but there are {positions} positions (give one per position)",
                    self.uvs.len()
                ),
            ));
        }
        if let Some(k) = self
            .uvs
            .iter()
            .position(|uv| !uv.iter().all(|c| c.is_finite()))
        {
            return Err(Error::invalid(
                format!("uvs[{k}]"),
                format!("{:?} is not finite", self.uvs[k]),
            ));
        }
        if self.triangle_masks.len() != triangles {
            return Err(Error::invalid(
                "triangle_masks",
                format!(
                    "has {} entries but there are {triangles} triangles (give one per \
                     triangle, {OPAQUE} or -1 for none)",
                    self.triangle_masks.len()
                ),
            ));
        }
        let count = self.masks.len();
        if let Some(k) = self
            .triangle_masks
            .iter()
            .position(|&m| m != OPAQUE && m as usize >= count)
        {
            return Err(Error::invalid(
                format!("triangle_masks[{k}]"),
                format!("{} indexes past the {count} masks", self.triangle_masks[k]),
            ));
        }
        for (index, mask) in self.masks.iter().enumerate() {
            mask.validate(index)?;
        }
        Ok(())
    }

    /// Whether any triangle is cut.
    pub fn cuts_any(&self) -> bool {
        self.triangle_masks.iter().any(|&m| m != OPAQUE)
    }
}

/// Perspective-correct texture coordinates over one triangle: the inverse of the matrix
/// whose columns are its vertices' (x·w, y·w, w) takes a pixel (x, y, 1) to barycentric
/// weights over w, which normalised interpolate the coordinates as the projection does.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TexturedTriangle {
    inverse: DMat3,
    uvs: [[f64; 2]; 3],
    pub mask: u32,
}

impl TexturedTriangle {
    /// A placeholder for a triangle seen edge on, which no sample reads.
    pub const EDGE_ON: Self = Self {
        inverse: DMat3::ZERO,
        uvs: [[0.0; 2]; 3],
        mask: OPAQUE,
    };

    /// From the triangle's vertices in clip space ((x·w, y·w, depth, w)), their texture
    /// coordinates and its mask; `None` where the triangle is seen edge on.
    pub fn new(clip: [DVec4; 3], uvs: [[f32; 2]; 3], mask: u32) -> Option<Self> {
        let columns = clip.map(|c| DVec3::new(c.x, c.y, c.w));
        let matrix = DMat3::from_cols(columns[0], columns[1], columns[2]);
        let determinant = matrix.determinant();
        if !determinant.is_finite() || determinant == 0.0 {
            return None;
        }
        Some(Self {
            inverse: matrix.inverse(),
            uvs: uvs.map(|[u, v]| [u as f64, v as f64]),
            mask,
        })
    }

    /// The texture coordinates at pixel point (x, y).
    #[inline]
    pub fn uv_at(&self, x: f64, y: f64) -> [f64; 2] {
        let weights = self.inverse * DVec3::new(x, y, 1.0);
        let sum = weights.x + weights.y + weights.z;
        let [a, b, c] = [weights.x / sum, weights.y / sum, weights.z / sum];
        [0, 1].map(|k| a * self.uvs[0][k] + b * self.uvs[1][k] + c * self.uvs[2][k])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(width: u32, height: u32, alpha: &[f32]) -> AlphaMask<'_> {
        AlphaMask::repeating(width, height, Cow::Borrowed(alpha), 0.5)
    }

    #[test]
    fn alpha_is_bilinear_between_texel_centres_and_repeats() {
        // Rows from v = 0 up: the bottom row is [0, 1], the top [1, 1].
        let alpha = [0.0, 1.0, 1.0, 1.0];
        let m = mask(2, 2, &alpha);
        assert_eq!(m.alpha_at([0.25, 0.25]), 0.0);
        assert_eq!(m.alpha_at([0.75, 0.25]), 1.0);
        assert_eq!(m.alpha_at([0.25, 0.75]), 1.0);
        assert!((m.alpha_at([0.5, 0.25]) - 0.5).abs() < 1e-6);
        assert!((m.alpha_at([0.5, 0.5]) - 0.75).abs() < 1e-6);
        // Repeating: a whole period off reads the same, and the seam blends both ends.
        assert_eq!(m.alpha_at([3.25, -1.75]), m.alpha_at([0.25, 0.25]));
        assert!((m.alpha_at([0.0, 0.25]) - 0.5).abs() < 1e-6);
        assert!(m.covers([0.6, 0.25]) && !m.covers([0.4, 0.25]));
    }

    /// One row of three texels, 0, 1 and 0.25, wrapped along u as `wrap` says.
    fn row_of_three(wrap: Wrap, filter: MaskFilter) -> AlphaMask<'static> {
        AlphaMask {
            wrap: [wrap, Wrap::Repeat],
            filter,
            ..AlphaMask::repeating(3, 1, Cow::Owned(vec![0.0, 1.0, 0.25]), 0.5)
        }
    }

    #[test]
    fn each_wrap_reads_past_the_edges_as_blender_and_usd_do() {
        // Texel i's centre, and the texture's right edge, between texel 2 and the next.
        let centre = |i: f64| [(i + 0.5) / 3.0, 0.5];
        let read = |wrap, at: [f64; 2]| row_of_three(wrap, MaskFilter::Linear).alpha_at(at);
        let cases: [(Wrap, [(f64, f32); 7]); 4] = [
            (
                Wrap::Repeat,
                [
                    (-2.0, 1.0),
                    (-1.0, 0.25),
                    (3.0, 0.0),
                    (4.0, 1.0),
                    (5.0, 0.25),
                    (6.0, 0.0),
                    (302.0, 0.25),
                ],
            ),
            (
                Wrap::Extend,
                [
                    (-2.0, 0.0),
                    (-1.0, 0.0),
                    (3.0, 0.25),
                    (4.0, 0.25),
                    (5.0, 0.25),
                    (6.0, 0.25),
                    (302.0, 0.25),
                ],
            ),
            (
                // Period 6: 3, 4, 5 read 2, 1, 0; −1, −2 read 0, 1.
                Wrap::Mirror,
                [
                    (-2.0, 1.0),
                    (-1.0, 0.0),
                    (3.0, 0.25),
                    (4.0, 1.0),
                    (5.0, 0.0),
                    (6.0, 0.0),
                    (303.0, 0.25),
                ],
            ),
            (
                Wrap::Clip,
                [
                    (-2.0, 0.0),
                    (-1.0, 0.0),
                    (3.0, 0.0),
                    (4.0, 0.0),
                    (5.0, 0.0),
                    (6.0, 0.0),
                    (302.0, 0.0),
                ],
            ),
        ];
        for (wrap, reads) in cases {
            for (i, expected) in reads {
                assert_eq!(read(wrap, centre(i)), expected, "{wrap:?} at texel {i}");
            }
            // Inside, every wrap reads the texture itself.
            assert_eq!(read(wrap, centre(1.0)), 1.0);
            assert!((read(wrap, centre(1.5)) - 0.625).abs() < 1e-6);
            // Huge coordinates read some texel or the border, never past the array.
            for u in [1e30, -1e30, 1e15 + 0.3] {
                let alpha = read(wrap, [u, 0.5]);
                assert!((0.0..=1.0).contains(&alpha), "{wrap:?} at {u}: {alpha}");
            }
        }
        // At the right edge, half a texel past texel 2's centre: the blend of texel 2 and
        // what lies beyond it.
        let edge = [1.0, 0.5];
        assert!((read(Wrap::Repeat, edge) - 0.125).abs() < 1e-6);
        assert_eq!(read(Wrap::Extend, edge), 0.25);
        assert_eq!(read(Wrap::Mirror, edge), 0.25);
        assert!((read(Wrap::Clip, edge) - 0.125).abs() < 1e-6);
        // Clipped edges read the border alpha, an inverted mask's 1.
        let mut inverted = row_of_three(Wrap::Clip, MaskFilter::Linear);
        inverted.border = 1.0;
        assert_eq!(inverted.alpha_at(centre(4.0)), 1.0);
        assert!((inverted.alpha_at(edge) - 0.625).abs() < 1e-6);
        // Per axis: v clipped, u repeating.
        let mut mask = row_of_three(Wrap::Repeat, MaskFilter::Linear);
        mask.wrap[1] = Wrap::Clip;
        assert_eq!(mask.alpha_at([centre(4.0)[0], 0.5]), 1.0);
        assert_eq!(mask.alpha_at([centre(4.0)[0], 1.5]), 0.0);
    }

    #[test]
    fn closest_filtering_reads_the_texel_a_point_lies_in() {
        let closest = |wrap, u: f64| row_of_three(wrap, MaskFilter::Closest).alpha_at([u, 0.5]);
        assert_eq!(closest(Wrap::Repeat, 0.34), 1.0);
        assert_eq!(closest(Wrap::Repeat, 0.33), 0.0);
        assert_eq!(closest(Wrap::Repeat, 0.99), 0.25);
        assert_eq!(closest(Wrap::Repeat, 1.01), 0.0);
        assert_eq!(closest(Wrap::Extend, 1.01), 0.25);
        assert_eq!(closest(Wrap::Mirror, 1.01), 0.25);
        assert_eq!(closest(Wrap::Mirror, 1.35), 1.0);
        assert_eq!(closest(Wrap::Clip, 1.01), 0.0);
        assert_eq!(closest(Wrap::Clip, -0.01), 0.0);
        // Linear filtering would blend texels 0 and 1 there.
        let linear = row_of_three(Wrap::Repeat, MaskFilter::Linear).alpha_at([0.34, 0.5]);
        assert!(linear > 0.5 && linear < 1.0);
    }

    #[test]
    fn shaders_read_the_wrap_and_filter_from_their_bits() {
        let mut mask = row_of_three(Wrap::Mirror, MaskFilter::Closest);
        mask.wrap[1] = Wrap::Clip;
        assert_eq!(mask.shader_sampling(), 2 | 3 << 2 | 16);
        assert_eq!(
            row_of_three(Wrap::Repeat, MaskFilter::Linear).shader_sampling(),
            0
        );
        let glsl = include_str!("../../shaders/raster_cut.glsl");
        for (name, value) in [
            ("WRAP_REPEAT", 0),
            ("WRAP_EXTEND", 1),
            ("WRAP_MIRROR", 2),
            ("WRAP_CLIP", 3),
            ("CLOSEST", 16),
        ] {
            assert!(
                glsl.contains(&format!("const uint {name} = {value}u;")),
                "{name}"
            );
        }
    }

    #[test]
    fn coordinates_interpolate_perspective_correctly() {
        // A triangle receding in depth: w 1, 1 and 3. At the screen midpoint of the edge
        // from vertex 0 to vertex 2, the perspective-correct weight of vertex 2 is
        // (1/3) / (1 + 1/3) = 1/4, not 1/2.
        let vertex = |x: f64, y: f64, w: f64| DVec4::new(x * w, y * w, 0.0, w);
        let clip = [
            vertex(0.0, 0.0, 1.0),
            vertex(4.0, 0.0, 1.0),
            vertex(0.0, 4.0, 3.0),
        ];
        let triangle =
            TexturedTriangle::new(clip, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], 0).unwrap();
        let [u, v] = triangle.uv_at(0.0, 2.0);
        assert!(u.abs() < 1e-12 && (v - 0.25).abs() < 1e-12, "{u} {v}");
        // At the vertices themselves, their own coordinates.
        let [u, v] = triangle.uv_at(4.0, 0.0);
        assert!((u - 1.0).abs() < 1e-12 && v.abs() < 1e-12);
        // Orthographic (w = 1 everywhere): affine.
        let flat = clip.map(|c| DVec4::new(c.x / c.w, c.y / c.w, 0.0, 1.0));
        let triangle =
            TexturedTriangle::new(flat, [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], 0).unwrap();
        let [_, v] = triangle.uv_at(0.0, 2.0);
        assert!((v - 0.5).abs() < 1e-12);
    }

    #[test]
    fn bad_cutouts_are_named() {
        let alpha = [1.0; 4];
        let masks = [mask(2, 2, &alpha)];
        let uvs = [[0.0, 0.0]; 3];
        let cutouts = |triangle_masks| Cutouts {
            uvs: &uvs,
            triangle_masks,
            masks: &masks,
        };
        assert!(cutouts(&[0]).validate(3, 1).is_ok());
        assert!(cutouts(&[OPAQUE]).validate(3, 1).is_ok());
        let message = |result: Result<()>| result.unwrap_err().to_string();
        assert!(message(cutouts(&[1]).validate(3, 1)).contains("triangle_masks[0]"));
        assert!(message(cutouts(&[0, 0]).validate(3, 1)).contains("triangle_masks"));
        assert!(message(cutouts(&[0]).validate(4, 1)).contains("uvs"));
        let short = [1.0; 3];
        let bad = [mask(2, 2, &short)];
        let cutouts = Cutouts {
            uvs: &uvs,
            triangle_masks: &[0],
            masks: &bad,
        };
        assert!(message(cutouts.validate(3, 1)).contains("masks[0]"));
    }
}
