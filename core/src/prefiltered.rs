//! Prefiltered single scattering on the rectified shadow map (dissertation §4.3): the
//! visibility step is expanded in a Fourier basis (Eq. 4.7), so that the
//! transmittance-weighted visibility along any stretch of a view ray is one dot product
//! between the ray's coefficients and a difference of weighted prefix sums of the basis
//! along its slice.
//!
//! - Keys (rectified values, oriented so that larger means more shadowed) are warped per
//!   slice by the quantiles of the slice's ray keys into [¼, ¾], which spends the basis'
//!   resolution where rays are and keeps differences clear of the series' periodic jump.
//! - Weights follow one reference ray per slice (Eq. 4.8–4.12): the geometric mean of the
//!   slice's smallest and largest projected speeds, so no ray is more than √(k_max/k_min)
//!   off. Weights are stored normalized (the filtered basis stays in [−1, 1]), with the
//!   cumulative weight beside them.
//! - A ray whose own transmittance departs from its reference by more than
//!   [`SEGMENT_MISMATCH`] in optical depth over its length (rays near the epipole, box
//!   media) is cut into segments, each read from the same tables and weighted by the
//!   ray's exact transmittance integral. Most rays take one lookup.

use std::f64::consts::PI;

use rayon::prelude::*;

use crate::camera::{CameraModel, Ray};
use crate::epipolar::{EpipolarMap, RaySlice};
use crate::reference::{integral_exp, medium_segment, weighted_visibility, BoxMedium, RaySample};
use crate::scene::{Medium, Sun};

/// Basis coefficients M: sine and cosine of M/2 frequencies.
pub const MIN_BASES: u32 = 4;
pub const MAX_BASES: u32 = 64;

/// Quantiles of the ray keys kept per slice.
const KNOTS: usize = 9;
/// Resolution of the tabulated basis over warped keys in [0, 1]: finer than the
/// highest frequency resolves by two orders of magnitude.
const TABLE_STEPS: usize = 8192;
/// Reference optical depth beyond which sample weights stop falling: differences of
/// prefix sums far along a slice then keep f32 precision.
const MAX_REFERENCE_DEPTH: f64 = 10.0;
/// Optical depth by which a ray's transmittance may depart from its slice reference's
/// within one segment.
pub const SEGMENT_MISMATCH: f64 = 0.5;
/// Most segments per ray.
const MAX_SEGMENTS: usize = 24;
/// Largest ratio between a slice's fastest and slowest ray considered for its reference.
const MAX_SPEED_RATIO: f64 = 4096.0;

/// Per slice: a monotone warp of keys, and the slice's reference ray.
#[derive(Clone, Copy, Debug)]
struct SliceFrame {
    /// Keys at evenly spaced warped positions in [¼, ¾], strictly increasing.
    knots: [f64; KNOTS],
    /// Texels per unit of t of the reference ray, and its position at t = 0.
    reference_rate: f64,
    reference_origin: f64,
}

impl SliceFrame {
    /// Position in [0, 1] for a key; rays land in [¼, ¾].
    #[inline]
    fn warp(&self, key: f64) -> f64 {
        let k = &self.knots;
        let segment = (KNOTS - 1) as f64;
        let index = k[1..KNOTS - 1].partition_point(|&knot| knot <= key);
        let (a, b) = (k[index], k[index + 1]);
        let local = (index as f64 + (key - a) / (b - a)) / segment;
        (0.25 + 0.5 * local).clamp(0.0, 1.0)
    }
}

/// The filtered-basis storage.
pub struct Prefiltered<'a> {
    map: &'a EpipolarMap,
    frequencies: usize,
    frames: Vec<SliceFrame>,
    /// Per slice, (samples + 1) rows of 2·frequencies: the weighted mean of
    /// [cos(c·z), sin(c·z)] over the slice's samples before each boundary.
    basis: Vec<f32>,
    /// Per slice, the cumulative weight at each of its samples + 1 boundaries.
    weight: Vec<f32>,
    /// 2/c_m, the Fourier coefficients' scale per frequency.
    scales: Vec<f32>,
    extinction: f64,
    box_medium: Option<BoxMedium>,
}

fn frequency(m: usize) -> f64 {
    PI * (2 * m + 1) as f64
}

/// (cos(c_m·z), sin(c_m·z)) for m < `frequencies`, written as [cos…, sin…].
#[inline]
fn harmonics(z: f64, frequencies: usize, out: &mut [f64]) {
    let (sin, cos) = (PI * z).sin_cos();
    let (step_sin, step_cos) = (2.0 * PI * z).sin_cos();
    let (mut s, mut c) = (sin, cos);
    for m in 0..frequencies {
        out[m] = c;
        out[frequencies + m] = s;
        (s, c) = (s * step_cos + c * step_sin, c * step_cos - s * step_sin);
    }
}

/// The basis tabulated over warped keys: row i holds the harmonics of i / TABLE_STEPS.
fn basis_table(frequencies: usize) -> Vec<f32> {
    let row = 2 * frequencies;
    let mut table = vec![0.0f32; (TABLE_STEPS + 1) * row];
    let mut values = vec![0.0f64; row];
    for (i, out) in table.chunks_exact_mut(row).enumerate() {
        harmonics(i as f64 / TABLE_STEPS as f64, frequencies, &mut values);
        for (o, v) in out.iter_mut().zip(&values) {
            *o = *v as f32;
        }
    }
    table
}

#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut sums = [0.0f32; LANES];
    for (a, b) in a.chunks_exact(LANES).zip(b.chunks_exact(LANES)) {
        for lane in 0..LANES {
            sums[lane] += a[lane] * b[lane];
        }
    }
    let tail = a.len() / LANES * LANES;
    let mut total: f32 = sums.iter().sum();
    for k in tail..a.len() {
        total += a[k] * b[k];
    }
    total
}

/// A ray's place on one slice: its coefficients, weighted.
struct SliceRay {
    slice: u32,
    weight: f64,
    coefficients: [f32; MAX_BASES as usize],
}

impl<'a> Prefiltered<'a> {
    /// `bases` is M, even, in [`MIN_BASES`]..=[`MAX_BASES`] (validated by the settings).
    /// `epipoles` are where the sun and anti-sun points appear in the image, if they do:
    /// slices crowd there, so frames sample every pixel around them.
    pub fn build(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        bases: u32,
        sun: &Sun,
        medium: &Medium,
    ) -> Self {
        let frequencies = (bases / 2) as usize;
        let row = 2 * frequencies;
        let extinction = medium.extinction as f64;
        let frames = slice_frames(map, camera, epipoles);
        let table = basis_table(frequencies);
        let samples = map.samples as usize;
        let mut basis = vec![0.0f32; map.slices as usize * (samples + 1) * row];
        let mut weight = vec![0.0f32; map.slices as usize * (samples + 1)];
        basis
            .par_chunks_mut((samples + 1) * row)
            .zip(weight.par_chunks_mut(samples + 1))
            .enumerate()
            .for_each(|(slice, (basis, weight))| {
                let frame = &frames[slice];
                let mut sums = [0.0f32; MAX_BASES as usize];
                let sums = &mut sums[..row];
                let mut total = 0.0f64;
                let t_of = |s: f64| (s - frame.reference_origin) / frame.reference_rate;
                let depth_of = |s: f64| (extinction * t_of(s).max(0.0)).min(MAX_REFERENCE_DEPTH);
                for (i, &value) in map.row(slice as u32).iter().enumerate() {
                    let (s0, s1) = map.sample_interval(i);
                    let (d0, d1) = (depth_of(s0), depth_of(s1));
                    // ∫ σ e^(−σt) dt over the sample, and its flat continuation beyond
                    // the depth cap; as σ → 0 this tends to uniform weights.
                    let w = if d1 > d0 {
                        (-d0).exp() * -(d0 - d1).exp_m1()
                    } else {
                        (-d0).exp() * (extinction * map.s_step / frame.reference_rate)
                    };
                    let w = if extinction > 0.0 { w } else { 1.0 };
                    let z = frame.warp(map.order_key(value as f64));
                    let entry = &table[(z * TABLE_STEPS as f64).round() as usize * row..][..row];
                    let w32 = w as f32;
                    for (sum, b) in sums.iter_mut().zip(entry) {
                        *sum += w32 * b;
                    }
                    total += w;
                    let normalize = (1.0 / total) as f32;
                    for (out, sum) in basis[(i + 1) * row..(i + 2) * row]
                        .iter_mut()
                        .zip(sums.iter())
                    {
                        *out = sum * normalize;
                    }
                    weight[i + 1] = total as f32;
                }
            });
        Self {
            map,
            frequencies,
            frames,
            basis,
            weight,
            scales: (0..frequencies)
                .map(|m| (2.0 / frequency(m)) as f32)
                .collect(),
            extinction,
            box_medium: BoxMedium::new(&medium.extent, sun.direction.as_dvec3().normalize()),
        }
    }

    pub fn memory_bytes(&self) -> usize {
        (self.basis.len() + self.weight.len()) * std::mem::size_of::<f32>()
    }

    /// The ray's coefficients in `slice`: V ≈ ½ + Σ (2/c)·sin(c·(z_r − z_i)), expanded
    /// against the stored [cos(c·z_i), sin(c·z_i)].
    fn slice_ray(&self, key: f64, slice: u32, weight: f64) -> SliceRay {
        let z = self.frames[slice as usize].warp(key);
        let f = self.frequencies;
        let (sin, cos) = (PI * z).sin_cos();
        let (step_sin, step_cos) = (2.0 * sin * cos, cos * cos - sin * sin);
        let (step_sin, step_cos) = (step_sin as f32, step_cos as f32);
        let (mut s, mut c) = (sin as f32, cos as f32);
        let mut coefficients = [0.0f32; MAX_BASES as usize];
        for m in 0..f {
            let scale = self.scales[m];
            // sin(c(z_r − z_i)) = sin(c·z_r)·cos(c·z_i) − cos(c·z_r)·sin(c·z_i)
            coefficients[m] = scale * s;
            coefficients[f + m] = -scale * c;
            (s, c) = (s * step_cos + c * step_sin, c * step_cos - s * step_sin);
        }
        SliceRay {
            slice,
            weight,
            coefficients,
        }
    }

    /// (coefficients · weighted prefix sum, cumulative weight) at a continuous sample
    /// position `x`, interpolated linearly between boundaries.
    #[inline]
    fn prefix(&self, ray: &SliceRay, x: f64) -> (f64, f64) {
        let samples = self.map.samples as usize;
        let row = 2 * self.frequencies;
        let x = x.clamp(0.0, samples as f64);
        let lower = (x as usize).min(samples);
        let upper = (lower + 1).min(samples);
        let fraction = x - lower as f64;
        let base = ray.slice as usize * (samples + 1);
        let coefficients = &ray.coefficients[..row];
        let at = |b: usize| {
            let w = self.weight[base + b] as f64;
            let rows = &self.basis[(base + b) * row..][..row];
            (w * dot(coefficients, rows) as f64, w)
        };
        let (s0, w0) = at(lower);
        if fraction == 0.0 {
            return (s0, w0);
        }
        let (s1, w1) = at(upper);
        (s0 + fraction * (s1 - s0), w0 + fraction * (w1 - w0))
    }

    /// Weighted average visibility between continuous positions `x0 < x1`.
    #[inline]
    fn average(&self, rays: &[SliceRay; 2], x0: f64, x1: f64) -> Option<f64> {
        let mut visibility = 0.0;
        for ray in rays {
            if ray.weight == 0.0 {
                continue;
            }
            let (s1, w1) = self.prefix(ray, x1);
            let (s0, w0) = if x0 <= 0.0 {
                (0.0, 0.0)
            } else {
                self.prefix(ray, x0)
            };
            let dw = w1 - w0;
            if dw <= 0.0 || x1 - x0 < 1e-9 {
                return None;
            }
            visibility += ray.weight * (0.5 + (s1 - s0) / dw).clamp(0.0, 1.0);
        }
        Some(visibility)
    }

    /// Integrates one ray over [t_start, t_end]; `None` when the ray runs along the light.
    pub fn march(&self, ray: &Ray, t_start: f64, t_end: f64) -> Option<RaySample> {
        let located = self.map.locate(ray)?;
        if t_end <= t_start {
            return Some(RaySample::EMPTY);
        }
        let [(first, w_first), (second, w_second)] = self.map.neighbours(located.slice);
        let key = self.map.order_key(located.threshold);
        let rays = [
            self.slice_ray(key, first, w_first),
            self.slice_ray(key, second, w_second),
        ];
        let x =
            |t: f64| (located.s_origin + located.s_per_t * t - self.map.s_first) / self.map.s_step;
        let sigma = self.extinction;
        let Some((a, b)) = medium_segment(self.box_medium.as_ref(), ray, t_start, t_end) else {
            // Off the map (shorter than a sample) counts as lit, like the other methods.
            let visibility = self.average(&rays, x(t_start), x(t_end)).unwrap_or(1.0);
            return Some(RaySample {
                visibility,
                ..RaySample::EMPTY
            });
        };
        let unshadowed = |t0: f64, t1: f64| match &self.box_medium {
            None => (-sigma * (t0 - a)).exp() * integral_exp(sigma, t1 - t0),
            Some(box_medium) => box_medium.integrate(ray, t0, t1, a, sigma),
        };
        let segments = self.segments(&located, &rays, a, b);
        let step = (b - a) / segments as f64;
        let (mut scattering, mut total) = (0.0, 0.0);
        let mut x0 = x(a);
        for k in 0..segments {
            let (t0, t1) = (a + k as f64 * step, a + (k + 1) as f64 * step);
            let x1 = x(t1);
            let visibility = self.average(&rays, x0, x1).unwrap_or(1.0);
            let weight = unshadowed(t0, t1);
            scattering += visibility * weight;
            total += weight;
            x0 = x1;
        }
        let visibility = weighted_visibility(scattering, total)
            .unwrap_or_else(|| self.average(&rays, x(t_start), x(t_end)).unwrap_or(1.0));
        Some(RaySample {
            scattering,
            alpha: -(-sigma * (b - a)).exp_m1(),
            visibility,
        })
    }

    /// How many segments keep the ray's transmittance within [`SEGMENT_MISMATCH`] of
    /// the references of the slices it reads.
    fn segments(&self, located: &RaySlice, rays: &[SliceRay; 2], a: f64, b: f64) -> usize {
        let depth = self.extinction * (b - a);
        let mut mismatch = rays
            .iter()
            .filter(|ray| ray.weight > 0.0)
            .map(|ray| {
                let rate = self.frames[ray.slice as usize].reference_rate;
                depth * (1.0 - located.s_per_t / rate).abs()
            })
            .fold(0.0, f64::max);
        if self.box_medium.is_some() {
            // Sunlight's attenuation inside the box varies along each ray differently.
            mismatch += depth;
        }
        ((mismatch / SEGMENT_MISMATCH).ceil() as usize).clamp(1, MAX_SEGMENTS)
    }
}

/// One ray sampled for a slice's frame.
#[derive(Clone, Copy)]
struct SampledRay {
    key: f64,
    rate: f64,
    origin: f64,
}

/// Per slice, key quantiles and the reference ray, from the rays of the image's border
/// (where each slice's extreme rays are), every other pixel inside, and every pixel
/// near an epipole, where slices are closer than two pixels. Slices that no sampled ray
/// touches take their nearest sampled neighbour's frame.
fn slice_frames(map: &EpipolarMap, camera: &CameraModel, epipoles: &[[f64; 2]]) -> Vec<SliceFrame> {
    const INTERIOR_STRIDE: u32 = 2;
    let (w, h) = (camera.width, camera.height);
    // Slices 2 px apart: at distance r from the epipole they are 2π·r/slices apart.
    let dense_radius = 2.0 * map.slices as f64 / std::f64::consts::TAU;
    let near_epipole = |x: f64, y: f64| {
        epipoles
            .iter()
            .any(|e| (x - e[0]).abs() <= dense_radius && (y - e[1]).abs() <= dense_radius)
    };
    let mut positions: Vec<(f64, f64)> = Vec::new();
    for x in 0..=w {
        positions.push((x as f64, 0.0));
        positions.push((x as f64, h as f64));
    }
    for y in 0..=h {
        positions.push((0.0, y as f64));
        positions.push((w as f64, y as f64));
    }
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            let on_grid = x % INTERIOR_STRIDE == 0 && y % INTERIOR_STRIDE == 0;
            if on_grid || near_epipole(px, py) {
                positions.push((px, py));
            }
        }
    }
    let located: Vec<RaySlice> = positions
        .par_iter()
        .filter_map(|&(x, y)| map.locate(&camera.ray(x, y)))
        .collect();
    let mut rays: Vec<Vec<SampledRay>> = vec![Vec::new(); map.slices as usize];
    for located in &located {
        let sampled = SampledRay {
            key: map.order_key(located.threshold),
            rate: located.s_per_t,
            origin: located.s_origin,
        };
        for (slice, _) in map.neighbours(located.slice) {
            rays[slice as usize].push(sampled);
        }
    }
    let frames: Vec<Option<SliceFrame>> = rays.par_iter_mut().map(|r| frame_of(r)).collect();
    // Fill unsampled slices from the nearest sampled one, scanning both ways.
    let sampled: Vec<usize> = (0..frames.len()).filter(|&i| frames[i].is_some()).collect();
    let fallback = SliceFrame {
        knots: std::array::from_fn(|i| i as f64),
        reference_rate: 1.0,
        reference_origin: 0.0,
    };
    (0..frames.len())
        .map(|i| {
            frames[i].unwrap_or_else(|| {
                let nearest = sampled
                    .iter()
                    .min_by_key(|&&j| (j as isize - i as isize).unsigned_abs());
                nearest.and_then(|&j| frames[j]).unwrap_or(fallback)
            })
        })
        .collect()
}

fn frame_of(rays: &mut [SampledRay]) -> Option<SliceFrame> {
    if rays.is_empty() {
        return None;
    }
    rays.sort_by(|a, b| a.key.total_cmp(&b.key));
    let mut knots = [0.0; KNOTS];
    for (i, knot) in knots.iter_mut().enumerate() {
        *knot = rays[i * (rays.len() - 1) / (KNOTS - 1)].key;
    }
    // Strictly increasing, so that every segment has a slope.
    let spread = (knots[KNOTS - 1] - knots[0]).max(1e-9);
    for i in 1..KNOTS {
        knots[i] = knots[i].max(knots[i - 1] + spread * 1e-6);
    }
    let fastest = rays.iter().map(|r| r.rate).fold(0.0, f64::max);
    let slowest = rays
        .iter()
        .map(|r| r.rate)
        .fold(f64::INFINITY, f64::min)
        .max(fastest / MAX_SPEED_RATIO);
    let origin = rays.iter().map(|r| r.origin).fold(f64::INFINITY, f64::min);
    Some(SliceFrame {
        knots,
        reference_rate: (fastest * slowest).sqrt(),
        reference_origin: origin,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn harmonics_match_direct_evaluation() {
        let frequencies = 32;
        let mut values = vec![0.0; 2 * frequencies];
        for &z in &[0.0, 0.13, 0.5, 0.77, 1.0] {
            harmonics(z, frequencies, &mut values);
            for m in 0..frequencies {
                let (sin, cos) = (frequency(m) * z).sin_cos();
                assert!((values[m] - cos).abs() < 1e-12, "cos m={m} z={z}");
                assert!(
                    (values[frequencies + m] - sin).abs() < 1e-12,
                    "sin m={m} z={z}"
                );
            }
        }
    }

    #[test]
    fn dot_handles_every_length() {
        for n in [4usize, 8, 12, 32, 64] {
            let a: Vec<f32> = (0..n).map(|i| i as f32 * 0.5).collect();
            let b: Vec<f32> = (0..n).map(|i| 1.0 - i as f32 * 0.01).collect();
            let expected: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            assert!((dot(&a, &b) - expected).abs() < 1e-3 * expected.abs().max(1.0));
        }
    }

    /// ½ + Σ (2/c)·sin(c·(z_r − z_i)) is a step: 1 where the ray's key exceeds the
    /// texel's, 0 below, ½ at the jump, within the ringing of a truncated series.
    #[test]
    fn the_series_reconstructs_the_visibility_step() {
        let frequencies = 32;
        let table = basis_table(frequencies);
        let row = 2 * frequencies;
        let visibility = |z_ray: f64, z_texel: f64| {
            let entry = &table[(z_texel * TABLE_STEPS as f64).round() as usize * row..][..row];
            let mut sum = 0.5;
            for m in 0..frequencies {
                let (sin, cos) = (frequency(m) * z_ray).sin_cos();
                let scale = 2.0 / frequency(m);
                sum += scale * (sin * entry[m] as f64 - cos * entry[frequencies + m] as f64);
            }
            sum
        };
        for &(z_ray, z_texel, expected) in &[
            (0.6, 0.3, 1.0),
            (0.3, 0.6, 0.0),
            (0.75, 0.25, 1.0),
            (0.25, 0.75, 0.0),
            (0.5, 0.1, 1.0),
        ] {
            let v = visibility(z_ray, z_texel);
            assert!((v - expected).abs() < 0.03, "V({z_ray}, {z_texel}) = {v}");
        }
        assert!((visibility(0.5, 0.5) - 0.5).abs() < 1e-3);
        // Steeper with more frequencies: the transition is narrower than 1/frequencies.
        assert!(visibility(0.5, 0.5 - 1.5 / frequencies as f64) > 0.9);
        assert!(visibility(0.5, 0.5 + 1.5 / frequencies as f64) < 0.1);
    }

    #[test]
    fn warp_is_monotone_and_puts_ray_keys_in_the_middle_half() {
        let mut rays: Vec<SampledRay> = (0..100)
            .map(|i| SampledRay {
                key: (i as f64 * 0.37).sin() * 3.0 + i as f64 * 0.01,
                rate: 1.0 + i as f64,
                origin: 0.0,
            })
            .collect();
        let frame = frame_of(&mut rays).expect("a frame");
        let (lo, hi) = (rays[0].key, rays[99].key);
        assert!((frame.warp(lo) - 0.25).abs() < 1e-9);
        assert!((frame.warp(hi) - 0.75).abs() < 1e-9);
        let mut last = -1.0;
        for i in 0..=1000 {
            let key = lo - 5.0 + (hi - lo + 10.0) * i as f64 / 1000.0;
            let z = frame.warp(key);
            assert!((0.0..=1.0).contains(&z) && z >= last);
            last = z;
        }
        // Eq. 4.12: the reference speed is the geometric mean of the extremes.
        assert!((frame.reference_rate - (1.0f64 * 100.0).sqrt()).abs() < 1e-9);
    }
}
