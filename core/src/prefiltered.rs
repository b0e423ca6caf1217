//! Prefiltered single scattering on the rectified shadow map (dissertation §4.3): the
//! visibility step is expanded in a Fourier basis (Eq. 4.7), so that the average
//! visibility over any stretch of a view ray is one dot product between the ray's
//! coefficients and the difference of two prefix sums of the basis along its slice.
//!
//! Per slice, keys (view-ray angles) are warped monotonically by the quantiles of the
//! slice's ray keys into [¼, ¾], so that the basis resolves keys where rays are and
//! differences stay clear of the series' periodic jump.
//!
//! Transmittance weighting departs from the paper's single reference ray per slice
//! (§4.3.2): near the epipole, rays of one slice cross it at speeds that differ by orders
//! of magnitude, and one reference mis-weights them badly. Instead each ray is cut into
//! segments of small optical depth; each segment's average visibility comes from the
//! prefix sums and is weighted by the ray's own exact transmittance integral (through a
//! box medium too). Thin media need one segment; no weighted table is stored.

use std::f64::consts::PI;

use rayon::prelude::*;

use crate::camera::{CameraModel, Ray};
use crate::epipolar::{EpipolarMap, RaySlice};
use crate::reference::{integral_exp, medium_segment, BoxMedium, RaySample};
use crate::scene::{Medium, Sun};

/// Basis coefficients M: sine and cosine of M/2 frequencies.
pub const MIN_BASES: u32 = 4;
pub const MAX_BASES: u32 = 64;

/// Optical depth of one weighting segment of a ray.
const SEGMENT_OPTICAL_DEPTH: f64 = 0.125;
/// Most weighting segments per ray.
const MAX_SEGMENTS: usize = 32;

/// Quantiles of the ray keys kept per slice.
const KNOTS: usize = 9;

/// Per slice, a monotone warp of keys: the quantiles of the slice's ray keys map to
/// evenly spaced positions in [¼, ¾], which spends the basis' resolution where rays are.
#[derive(Clone, Copy, Debug)]
struct SliceFrame {
    knots: [f64; KNOTS],
}

impl SliceFrame {
    /// Position in [0, 1] for a key; rays land in [¼, ¾].
    fn warp(&self, key: f64) -> f64 {
        let k = &self.knots;
        let segment = (KNOTS - 1) as f64;
        let index = k[1..KNOTS - 1].partition_point(|&knot| knot <= key);
        let (a, b) = (k[index], k[index + 1]);
        let local = (index as f64 + (key - a) / (b - a)) / segment;
        (0.25 + 0.5 * local).clamp(0.0, 1.0)
    }
}

/// The filtered-basis storage: per slice and sample boundary, the prefix sums of the
/// cosine and sine bases.
pub struct Prefiltered<'a> {
    map: &'a EpipolarMap,
    frequencies: usize,
    frames: Vec<SliceFrame>,
    /// Per slice, (samples + 1) rows of [U_cos(F), U_sin(F)].
    prefix: Vec<f32>,
    medium: &'a Medium,
    box_medium: Option<BoxMedium>,
}

fn frequency(m: usize) -> f64 {
    PI * (2 * m + 1) as f64
}

impl<'a> Prefiltered<'a> {
    /// `bases` is M, even, in [`MIN_BASES`]..=[`MAX_BASES`] (validated by the settings).
    pub fn build(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        bases: u32,
        sun: &Sun,
        medium: &'a Medium,
    ) -> Self {
        let frequencies = (bases / 2) as usize;
        let frames = slice_frames(map, camera);
        let samples = map.samples as usize;
        let row_len = 2 * frequencies;
        let mut prefix = vec![0.0f32; map.slices as usize * (samples + 1) * row_len];
        prefix
            .par_chunks_mut((samples + 1) * row_len)
            .enumerate()
            .for_each(|(slice, prefix)| {
                let frame = frames[slice];
                let mut sums = vec![0.0f64; row_len];
                for (i, &value) in map.row(slice as u32).iter().enumerate() {
                    let z = frame.warp(map.order_key(value as f64));
                    for m in 0..frequencies {
                        let (sin, cos) = (frequency(m) * z).sin_cos();
                        sums[m] += cos;
                        sums[frequencies + m] += sin;
                    }
                    for (out, sum) in prefix[(i + 1) * row_len..(i + 2) * row_len]
                        .iter_mut()
                        .zip(&sums)
                    {
                        *out = *sum as f32;
                    }
                }
            });
        let light_travel = sun.direction.as_dvec3().normalize();
        Self {
            map,
            frequencies,
            frames,
            prefix,
            medium,
            box_medium: BoxMedium::new(&medium.extent, light_travel),
        }
    }

    pub fn memory_bytes(&self) -> usize {
        self.prefix.len() * std::mem::size_of::<f32>()
    }

    /// The ray's basis coefficients in `slice`:
    /// V ≈ ½ + Σ (2/c)(sin(c·z_r)·cos(c·z_i) − cos(c·z_r)·sin(c·z_i)).
    fn coefficients(&self, located: &RaySlice, slice: u32, out: &mut [f64]) {
        let frame = self.frames[slice as usize];
        let z = frame.warp(self.map.order_key(located.threshold));
        let f = self.frequencies;
        for m in 0..f {
            let c = frequency(m);
            let (sin, cos) = (c * z).sin_cos();
            out[m] = 2.0 / c * sin;
            out[f + m] = -2.0 / c * cos;
        }
    }

    /// Σ coefficient · prefix sum at a continuous position `s` along `slice`, with the
    /// prefix interpolated linearly within a sample, and the position in samples.
    fn filtered(&self, coefficients: &[f64], slice: u32, s: f64) -> (f64, f64) {
        let samples = self.map.samples as usize;
        let b = ((s - self.map.s_first) / self.map.s_step).clamp(0.0, samples as f64);
        let lower = (b.floor() as usize).min(samples);
        let upper = (lower + 1).min(samples);
        let fraction = b - lower as f64;
        let row_len = coefficients.len();
        let base = slice as usize * (samples + 1) * row_len;
        let a = &self.prefix[base + lower * row_len..][..row_len];
        let c = &self.prefix[base + upper * row_len..][..row_len];
        let mut sum = 0.0;
        for k in 0..row_len {
            sum += coefficients[k] * (a[k] as f64 + fraction * (c[k] as f64 - a[k] as f64));
        }
        (sum, b)
    }

    /// Average visibility between two filtered positions of one slice.
    fn average((sum0, b0): (f64, f64), (sum1, b1): (f64, f64)) -> Option<f64> {
        (b1 - b0 > 1e-9).then(|| (0.5 + (sum1 - sum0) / (b1 - b0)).clamp(0.0, 1.0))
    }

    /// Integrates one ray over [t_start, t_end]; `None` when the ray runs along the light.
    pub fn march(&self, ray: &Ray, t_start: f64, t_end: f64) -> Option<RaySample> {
        let located = self.map.locate(ray)?;
        if t_end <= t_start {
            return Some(RaySample::EMPTY);
        }
        let sigma = self.medium.extinction as f64;
        let medium_segment = medium_segment(self.box_medium.as_ref(), ray, t_start, t_end);
        let s = |t: f64| located.s_origin + located.s_per_t * t;
        let mut coefficients = [0.0f64; MAX_BASES as usize];
        let coefficients = &mut coefficients[..2 * self.frequencies];
        let mut sample = RaySample::default();
        for (slice, weight) in self.map.neighbours(located.slice) {
            if weight == 0.0 {
                continue;
            }
            self.coefficients(&located, slice, coefficients);
            let whole = (
                self.filtered(coefficients, slice, s(t_start)),
                self.filtered(coefficients, slice, s(t_end)),
            );
            // Off the map (shorter than a sample) counts as lit, like the other methods.
            sample.visibility += weight * Self::average(whole.0, whole.1).unwrap_or(1.0);
            let Some((a, b)) = medium_segment else {
                continue;
            };
            let segments =
                ((sigma * (b - a) / SEGMENT_OPTICAL_DEPTH).ceil() as usize).clamp(1, MAX_SEGMENTS);
            let step = (b - a) / segments as f64;
            let mut before = self.filtered(coefficients, slice, s(a));
            let mut scattering = 0.0;
            for k in 0..segments {
                let (t0, t1) = (a + k as f64 * step, a + (k + 1) as f64 * step);
                let after = self.filtered(coefficients, slice, s(t1));
                let visibility = Self::average(before, after).unwrap_or(1.0);
                let unshadowed = match &self.box_medium {
                    None => (-sigma * (t0 - a)).exp() * integral_exp(sigma, t1 - t0),
                    Some(box_medium) => box_medium.integrate(ray, t0, t1, a, sigma),
                };
                scattering += visibility * unshadowed;
                before = after;
            }
            sample.scattering += weight * scattering;
        }
        sample.alpha = medium_segment.map_or(0.0, |(a, b)| -(-sigma * (b - a)).exp_m1());
        Some(sample)
    }
}

/// Key quantiles per slice, from the rays of every other pixel and the image's border;
/// slices that no sampled ray touches take the whole image's quantiles.
fn slice_frames(map: &EpipolarMap, camera: &CameraModel) -> Vec<SliceFrame> {
    let mut keys: Vec<Vec<f64>> = vec![Vec::new(); map.slices as usize];
    let mut all = Vec::new();
    let (w, h) = (camera.width, camera.height);
    let xs: Vec<u32> = (0..w).step_by(2).chain(std::iter::once(w - 1)).collect();
    let ys: Vec<u32> = (0..h).step_by(2).chain(std::iter::once(h - 1)).collect();
    for &y in &ys {
        for &x in &xs {
            // The pixel's centre and both corners, so that the border rays are included.
            let (x, y) = (x as f64, y as f64);
            for (px, py) in [(x + 0.5, y + 0.5), (x, y), (x + 1.0, y + 1.0)] {
                let Some(located) = map.locate(&camera.ray(px, py)) else {
                    continue;
                };
                let key = map.order_key(located.threshold);
                for (slice, _) in map.neighbours(located.slice) {
                    keys[slice as usize].push(key);
                }
                all.push(key);
            }
        }
    }
    let quantiles = |keys: &mut Vec<f64>| -> Option<[f64; KNOTS]> {
        if keys.is_empty() {
            return None;
        }
        keys.sort_by(f64::total_cmp);
        let mut knots = [0.0; KNOTS];
        for (i, knot) in knots.iter_mut().enumerate() {
            let position = i * (keys.len() - 1) / (KNOTS - 1);
            *knot = keys[position];
        }
        // Strictly increasing, so that every segment has a slope.
        let spread = (knots[KNOTS - 1] - knots[0]).max(1e-9);
        for i in 1..KNOTS {
            knots[i] = knots[i].max(knots[i - 1] + spread * 1e-6);
        }
        Some(knots)
    };
    let global = quantiles(&mut all).unwrap_or_else(|| {
        let mut knots = [0.0; KNOTS];
        for (i, knot) in knots.iter_mut().enumerate() {
            *knot = i as f64;
        }
        knots
    });
    keys.par_iter_mut()
        .map(|keys| SliceFrame {
            knots: quantiles(keys).unwrap_or(global),
        })
        .collect()
}
