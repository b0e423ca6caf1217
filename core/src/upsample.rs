//! Depth-aware joint-bilateral upsampling of layers evaluated at reduced resolution
//! (paper 003; paper 001 §5.2).
//!
//! Low-resolution sample (i, j) is the full-resolution pixel (f·i + f/2, f·j + f/2), so
//! every sample is exact for one real pixel. A full-resolution pixel blends its four
//! surrounding samples by bilinear distance times depth similarity; where none of them
//! lies at a similar depth (a thin object between samples), it takes the sample of the
//! closest depth rather than blending across the edge.

use rayon::prelude::*;

use crate::layers::Layers;

/// Relative depth difference at which a sample's weight falls to e⁻¹.
pub const DEPTH_TOLERANCE: f32 = 0.05;

/// The full-resolution pixel that low-resolution sample `index` stands for.
pub fn sample_pixel(index: u32, factor: u32, full: u32) -> u32 {
    (index * factor + factor / 2).min(full - 1)
}

/// Low-resolution size for a full-resolution side.
pub fn reduced_size(full: u32, factor: u32) -> u32 {
    full.div_ceil(factor)
}

/// Upsamples `low` (whose `depth` holds each sample's depth) to `width` × `height`,
/// guided by the full-resolution `depth`, which the result keeps as its depth layer.
pub fn joint_bilateral(
    low: &Layers,
    depth: &[f32],
    width: u32,
    height: u32,
    factor: u32,
) -> Layers {
    let mut out = Layers::new(width, height);
    let (lw, lh) = (low.width as usize, low.height as usize);
    let half = (factor / 2) as f32;
    let neighbours = |position: f32, count: usize| {
        let u = ((position - half) / factor as f32).max(0.0);
        let first = (u.floor() as usize).min(count - 1);
        let second = (first + 1).min(count - 1);
        (first, second, u - first as f32)
    };
    let width = width as usize;
    out.volume
        .par_chunks_mut(width * 4)
        .zip(out.visibility.par_chunks_mut(width))
        .enumerate()
        .for_each(|(y, (volume, visibility))| {
            let (y0, y1, fy) = neighbours(y as f32, lh);
            for x in 0..width {
                let (x0, x1, fx) = neighbours(x as f32, lw);
                let target = depth[y * width + x];
                let candidates = [
                    (y0 * lw + x0, (1.0 - fx) * (1.0 - fy)),
                    (y0 * lw + x1, fx * (1.0 - fy)),
                    (y1 * lw + x0, (1.0 - fx) * fy),
                    (y1 * lw + x1, fx * fy),
                ];
                let mut total = 0.0f32;
                let mut rgba = [0.0f32; 4];
                let mut seen = 0.0f32;
                let mut closest = (f32::INFINITY, candidates[0].0);
                for (index, spatial) in candidates {
                    let difference = (low.depth[index] - target).abs();
                    if difference < closest.0 {
                        closest = (difference, index);
                    }
                    let relative = difference / (DEPTH_TOLERANCE * target.abs().max(1e-6));
                    // A floor on the spatial weight keeps all four eligible at a sample.
                    let weight = (spatial + 1e-3) * (-relative * relative).exp();
                    total += weight;
                    for (c, value) in rgba.iter_mut().enumerate() {
                        *value += weight * low.volume[index * 4 + c];
                    }
                    seen += weight * low.visibility[index];
                }
                let (rgba, seen) = if total > 1e-6 {
                    (rgba.map(|v| v / total), seen / total)
                } else {
                    let index = closest.1;
                    let mut own = [0.0f32; 4];
                    own.copy_from_slice(&low.volume[index * 4..index * 4 + 4]);
                    (own, low.visibility[index])
                };
                volume[x * 4..x * 4 + 4].copy_from_slice(&rgba);
                visibility[x] = seen;
            }
        });
    out.depth.copy_from_slice(depth);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two depth regions split at column 13, each with its own constant layer values.
    fn two_regions(width: u32, height: u32) -> (Vec<f32>, impl Fn(u32) -> ([f32; 4], f32)) {
        let depth = (0..width * height)
            .map(|i| if i % width < 13 { 2.0 } else { 40.0 })
            .collect();
        let value = |x: u32| {
            if x < 13 {
                ([0.5, 0.25, 0.125, 0.75], 0.2)
            } else {
                ([0.01, 0.02, 0.03, 0.9], 0.95)
            }
        };
        (depth, value)
    }

    #[test]
    fn samples_do_not_bleed_across_depth_edges() {
        let (width, height, factor) = (30, 20, 4);
        let (depth, value) = two_regions(width, height);
        let (lw, lh) = (reduced_size(width, factor), reduced_size(height, factor));
        let mut low = Layers::new(lw, lh);
        for j in 0..lh {
            for i in 0..lw {
                let (x, y) = (
                    sample_pixel(i, factor, width),
                    sample_pixel(j, factor, height),
                );
                let k = (j * lw + i) as usize;
                let (rgba, seen) = value(x);
                low.volume[k * 4..k * 4 + 4].copy_from_slice(&rgba);
                low.visibility[k] = seen;
                low.depth[k] = depth[(y * width + x) as usize];
            }
        }
        let up = joint_bilateral(&low, &depth, width, height, factor);
        for y in 0..height {
            for x in 0..width {
                let (rgba, seen) = value(x);
                let got = up.volume_rgba(x, y);
                for c in 0..4 {
                    assert!(
                        (got[c] - rgba[c]).abs() < 1e-4,
                        "({x}, {y}) {got:?} vs {rgba:?}"
                    );
                }
                assert!((up.visibility[(y * width + x) as usize] - seen).abs() < 1e-4);
            }
        }
        assert_eq!(up.depth, depth);
    }

    #[test]
    fn smooth_layers_interpolate_bilinearly_between_samples() {
        let (width, height, factor) = (16, 8, 2);
        let depth = vec![10.0f32; (width * height) as usize];
        let (lw, lh) = (reduced_size(width, factor), reduced_size(height, factor));
        let mut low = Layers::new(lw, lh);
        for j in 0..lh {
            for i in 0..lw {
                let k = (j * lw + i) as usize;
                low.visibility[k] = sample_pixel(i, factor, width) as f32;
                low.depth[k] = 10.0;
            }
        }
        let up = joint_bilateral(&low, &depth, width, height, factor);
        // Between the samples at pixels 1 and 3 a linear ramp is reproduced, up to the
        // small spatial-weight floor.
        let at = |x: u32| up.visibility[(3 * width + x) as usize];
        assert!((at(2) - 2.0).abs() < 0.01, "{}", at(2));
        assert!((at(1) - 1.0).abs() < 0.01);
    }
}
