//! Alpha cutouts: triangles that a texture's alpha makes partly empty (leaf cards, fences,
//! grilles), alpha-tested as a renderer's clip mode does. A sample of such a triangle is
//! drawn into the shadow map and the camera's depth only where the mask's alpha, filtered
//! bilinearly at its texture coordinates, reaches the mask's threshold; elsewhere light and
//! sight pass through. Without this a canopy of leaf cards casts the solid shadow of its
//! rectangles and lets no shaft through.
//!
//! Coordinates are interpolated perspective-correctly over the triangle as authored, from
//! its vertices' homogeneous pixel coordinates, so clipping (which cuts a triangle into
//! others) never has to carry them.

use std::borrow::Cow;

use glam::{DMat3, DVec3, DVec4};

use crate::error::{Error, Result};

/// A triangle's mask index meaning it has none: opaque everywhere.
pub const OPAQUE: u32 = u32::MAX;

/// An alpha texture: `alpha` holds `width` × `height` values, rows from v = 0 up (the
/// order of Blender's image pixels and of OpenGL textures), and repeats in u and v. Hosts
/// lend their arrays; a scene description's images are owned.
#[derive(Clone, Debug)]
pub struct AlphaMask<'a> {
    pub width: u32,
    pub height: u32,
    pub alpha: Cow<'a, [f32]>,
    /// Samples whose filtered alpha is below this are empty.
    pub threshold: f32,
}

impl AlphaMask<'_> {
    /// The alpha at (u, v), filtered bilinearly between texel centres, repeating.
    #[inline]
    pub fn alpha_at(&self, [u, v]: [f64; 2]) -> f32 {
        let (width, height) = (self.width as i64, self.height as i64);
        let x = u * width as f64 - 0.5;
        let y = v * height as f64 - 0.5;
        // Large coordinates wrap before the conversion so that i64 never saturates.
        let (x, y) = (x.rem_euclid(width as f64), y.rem_euclid(height as f64));
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let column = |i: i64| i.rem_euclid(width) as usize;
        let row = |j: i64| j.rem_euclid(height) as usize * width as usize;
        let (i0, j0) = (x0 as i64, y0 as i64);
        let at = |i: i64, j: i64| self.alpha[row(j) + column(i)];
        let bottom = at(i0, j0) + (at(i0 + 1, j0) - at(i0, j0)) * fx;
        let top = at(i0, j0 + 1) + (at(i0 + 1, j0 + 1) - at(i0, j0 + 1)) * fx;
        bottom + (top - bottom) * fy
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
        AlphaMask {
            width,
            height,
            alpha: Cow::Borrowed(alpha),
            threshold: 0.5,
        }
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
