//! Depth-aware joint-bilateral upsampling of layers evaluated at reduced resolution
//! (paper 003; paper 001 §5.2).
//!
//! Low-resolution sample (i, j) is the full-resolution pixel (f·i + f/2, f·j + f/2), so
//! every sample is exact for one real pixel. A full-resolution pixel blends its four
//! surrounding samples by bilinear distance times depth similarity; where none of them
//! lies at a similar depth (a thin object between samples), it takes the sample of the
//! closest depth rather than blending across the edge.
//!
//! In a box of fog the layers also jump where no depth does: at the box's silhouette a
//! sample just inside is lit fog and one just outside is nothing, in front of the same
//! background. There an [`opacity_guide`] gives pixels their exact opacity, and they blend
//! their samples' radiance per unit opacity, which is smooth across the silhouette.

use rayon::prelude::*;

use crate::basis_kernels::Kernels;
use crate::error::{Result, Sizing};
use crate::layers::Layers;
use crate::spare::Spare;

/// Relative depth difference at which a sample's weight falls to e⁻¹.
pub const DEPTH_TOLERANCE: f32 = 0.05;

/// Spread of the four samples' opacity around a pixel, relative to the largest, above
/// which [`opacity_guide`] gives the pixel its exact opacity.
pub const OPACITY_SPREAD: f32 = 0.25;

/// An [`opacity_guide`]'s value for a pixel whose samples' opacities agree: it blends them
/// as everywhere else.
pub const BLENDED: f32 = -1.0;

/// The last frame's [`opacity_guide`], for the next box frame's ([`keep_opacity_guide`]).
static SPARE_OPACITY_GUIDE: Spare<f32> = Spare::new(Sizing::Image);

/// Keeps an [`opacity_guide`] done with for a later frame's.
pub fn keep_opacity_guide(guide: Vec<f32>) {
    SPARE_OPACITY_GUIDE.keep(guide);
}

/// Lets go of the kept opacity guide ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_OPACITY_GUIDE.clear();
}

/// The full-resolution pixel that low-resolution sample `index` stands for.
pub fn sample_pixel(index: u32, factor: u32, full: u32) -> u32 {
    (index * factor + factor / 2).min(full - 1)
}

/// Low-resolution size for a full-resolution side.
pub fn reduced_size(full: u32, factor: u32) -> u32 {
    full.div_ceil(factor)
}

/// The low-resolution samples a frame reduced by `factor` shades, taken from `full`'s
/// pixels: to measure upsampling apart from shading.
pub fn samples_of(full: &Layers, factor: u32) -> Layers {
    let (lw, lh) = (
        reduced_size(full.width, factor),
        reduced_size(full.height, factor),
    );
    let mut low = Layers::new(lw, lh);
    for j in 0..lh {
        for i in 0..lw {
            let x = sample_pixel(i, factor, full.width);
            let y = sample_pixel(j, factor, full.height);
            let (k, f) = ((j * lw + i) as usize, (y * full.width + x) as usize);
            low.volume[k * 4..k * 4 + 4].copy_from_slice(&full.volume[f * 4..f * 4 + 4]);
            low.visibility[k] = full.visibility[f];
            low.depth[k] = full.depth[f];
        }
    }
    low
}

/// Where a full-resolution position falls between low-resolution samples: the lower and
/// upper sample (clamped to the `count` there are) and the fraction towards the upper.
#[derive(Clone, Copy)]
struct Between {
    lower: usize,
    upper: usize,
    fraction: f32,
}

impl Between {
    fn of(position: u32, factor: u32, count: usize) -> Self {
        let u = ((position as f32 - (factor / 2) as f32) / factor as f32).max(0.0);
        let lower = (u as usize).min(count - 1);
        Self {
            lower,
            upper: (lower + 1).min(count - 1),
            fraction: u - lower as f32,
        }
    }
}

/// e^(−|x|), for the range weight: within 10⁻⁷·(2 + |x|) relative (float rounding of the
/// exponent), at most 2^−126 beyond |x| ≈ 87 and for NaN. The weight is taken four times
/// per output pixel, and libm's `expf` was a third of upsampling's time; this is plain
/// multiplies and adds without branches, so the four vectorize, and the results do not
/// depend on the CPU.
#[inline(always)]
fn exp_negative(x: f32) -> f32 {
    // `max` also maps NaN to the floor; a negative x (never passed) counts as its size.
    let t = (-x.abs() * std::f32::consts::LOG2_E).max(-126.0);
    // t = k + f with f in [−½, ½]: adding 1.5·2²³ rounds to an integer.
    const ROUND: f32 = 12_582_912.0;
    let rounded = t + ROUND;
    let k = rounded - ROUND;
    let f = t - k;
    // 2^f, Cephes' exp2f minimax polynomial on [−½, ½].
    let p = ((((1.535_336_2e-4 * f + 1.339_887_4e-3) * f + 9.618_437e-3) * f + 5.550_332_5e-2) * f
        + 0.240_226_48)
        * f
        + std::f32::consts::LN_2;
    // 2^k from the integer in `rounded`'s low mantissa bits (its bits are those of
    // 1.5·2²³ plus k), without a float-to-integer conversion, which kept the four
    // weights from vectorizing.
    let exponent = rounded.to_bits().wrapping_sub(ROUND.to_bits() - 127) << 23;
    (1.0 + f * p) * f32::from_bits(exponent)
}

/// Where each output column falls between the low-resolution columns, in arrays of their
/// own so that the weights of a whole row vectorize.
struct Columns {
    lower: Vec<usize>,
    upper: Vec<usize>,
    fraction: Vec<f32>,
}

impl Columns {
    fn of(width: u32, factor: u32, count: usize) -> Self {
        let between: Vec<Between> = (0..width).map(|x| Between::of(x, factor, count)).collect();
        Self {
            lower: between.iter().map(|column| column.lower).collect(),
            upper: between.iter().map(|column| column.upper).collect(),
            fraction: between.iter().map(|column| column.fraction).collect(),
        }
    }
}

/// A row's per-tap depth differences and weights, kept by each thread from row to row.
#[derive(Default)]
struct RowTaps {
    differences: [Vec<f32>; 4],
    weights: [Vec<f32>; 4],
}

/// One output row of [`joint_bilateral`], lying at `row` between the rows of samples:
/// `depth`, `volume` and `visibility` are its pixels'. The row is taken in three sweeps:
/// the taps' depths gathered, their weights computed for the whole row (which vectorizes),
/// then the blend. Weights computed eight pixels at a time straight after their gathers
/// read back values still in the store buffer, a fifth of upsampling's time.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn upsample_row(
    low: &Layers,
    columns: &Columns,
    row: Between,
    depth: &[f32],
    opacity: Option<&[f32]>,
    volume: &mut [f32],
    visibility: &mut [f32],
    taps: &mut RowTaps,
) {
    let width = depth.len();
    let lw = low.width as usize;
    let (above, below, fy) = (row.lower * lw, row.upper * lw, row.fraction);
    let (lower, upper) = (&columns.lower[..width], &columns.upper[..width]);
    // The two sample rows, each sample's four values one array: a tap is one
    // bounds-checked read of its row. Slicing the whole layers at computed indices took a
    // ninth more of the row's instructions.
    let [depth_above, depth_below] = [above, below].map(|first| &low.depth[first..first + lw]);
    let [volume_above, volume_below] =
        [above, below].map(|first| low.volume[4 * first..4 * (first + lw)].as_chunks::<4>().0);
    let [visibility_above, visibility_below] =
        [above, below].map(|first| &low.visibility[first..first + lw]);
    let fraction = &columns.fraction[..width];
    for buffer in taps.differences.iter_mut().chain(&mut taps.weights) {
        buffer.resize(width, 0.0);
    }
    let [d0, d1, d2, d3] = &mut taps.differences;
    let (d0, d1, d2, d3) = (
        &mut d0[..width],
        &mut d1[..width],
        &mut d2[..width],
        &mut d3[..width],
    );
    for x in 0..width {
        let target = depth[x];
        d0[x] = (depth_above[lower[x]] - target).abs();
        d1[x] = (depth_above[upper[x]] - target).abs();
        d2[x] = (depth_below[lower[x]] - target).abs();
        d3[x] = (depth_below[upper[x]] - target).abs();
    }
    let [w0, w1, w2, w3] = &mut taps.weights;
    let (w0, w1, w2, w3) = (
        &mut w0[..width],
        &mut w1[..width],
        &mut w2[..width],
        &mut w3[..width],
    );
    for x in 0..width {
        let (fx, target) = (fraction[x], depth[x]);
        let per_tolerance = 1.0 / (DEPTH_TOLERANCE * target.abs().max(1e-6));
        let weight = |difference: f32, spatial: f32| {
            let relative = difference * per_tolerance;
            spatial * exp_negative(relative * relative)
        };
        // A floor on the spatial weight keeps all four eligible at a sample.
        w0[x] = weight(d0[x], (1.0 - fx) * (1.0 - fy) + 1e-3);
        w1[x] = weight(d1[x], fx * (1.0 - fy) + 1e-3);
        w2[x] = weight(d2[x], (1.0 - fx) * fy + 1e-3);
        w3[x] = weight(d3[x], fx * fy + 1e-3);
    }
    for (x, (rgba_out, seen_out)) in volume
        .chunks_exact_mut(4)
        .zip(visibility.iter_mut())
        .enumerate()
    {
        let (left, right) = (lower[x], upper[x]);
        let samples = [
            volume_above[left],
            volume_above[right],
            volume_below[left],
            volume_below[right],
        ];
        let seen_samples = [
            visibility_above[left],
            visibility_above[right],
            visibility_below[left],
            visibility_below[right],
        ];
        let weights = [w0[x], w1[x], w2[x], w3[x]];
        let total = weights[0] + weights[1] + weights[2] + weights[3];
        let mut rgba = [0.0f32; 4];
        let mut seen = 0.0f32;
        for ((values, &sample_seen), &weight) in samples.iter().zip(&seen_samples).zip(&weights) {
            for (value, sample) in rgba.iter_mut().zip(values) {
                *value += weight * sample;
            }
            seen += weight * sample_seen;
        }
        if total > 1e-6 {
            let scale = 1.0 / total;
            for (out, value) in rgba_out.iter_mut().zip(rgba) {
                *out = value * scale;
            }
            *seen_out = seen * scale;
        } else {
            // No sample at a similar depth: the closest in depth, not a blend.
            let closest = closest_depth(&[d0[x], d1[x], d2[x], d3[x]]);
            rgba_out.copy_from_slice(&samples[closest]);
            *seen_out = seen_samples[closest];
        }
    }
    // The few pixels the opacity guide gives, over the blend: a sweep of their own keeps
    // the branch out of every other pixel's.
    let Some(opacity) = opacity else {
        return;
    };
    for (x, &exact) in opacity.iter().enumerate() {
        if exact < 0.0 {
            continue;
        }
        let indices = [
            above + lower[x],
            above + upper[x],
            below + lower[x],
            below + upper[x],
        ];
        let mut weights = [w0[x], w1[x], w2[x], w3[x]];
        let total = weights[0] + weights[1] + weights[2] + weights[3];
        // As in the blend, a pixel with no sample at a similar depth takes the closest.
        if total <= 1e-6 {
            weights = [0.0; 4];
            weights[closest_depth(&[d0[x], d1[x], d2[x], d3[x]])] = 1.0;
        }
        let (rgba, seen) = blend_through_opacity(low, &indices, &weights, exact);
        volume[x * 4..x * 4 + 4].copy_from_slice(&rgba);
        visibility[x] = seen;
    }
}

/// Which of four taps' depth `differences` is least (the first of equals).
fn closest_depth(differences: &[f32; 4]) -> usize {
    (1..4).fold(0, |best, k| {
        if differences[k] < differences[best] {
            k
        } else {
            best
        }
    })
}

/// A pixel of exact `opacity` among samples whose opacities spread ([`opacity_guide`]):
/// their radiance per unit opacity, blended by `weights` times each sample's opacity,
/// times the pixel's own opacity. Its visibility blends the samples on its side of the
/// medium's edge: weighted by opacity inside, and those that see no medium outside (whose
/// visibility is the lit share of the ray rather than a weighted one).
fn blend_through_opacity(
    low: &Layers,
    indices: &[usize; 4],
    weights: &[f32; 4],
    opacity: f32,
) -> ([f32; 4], f32) {
    let mut radiance = [0.0f32; 3];
    let mut through = 0.0f32;
    let (mut seen, mut seen_weight) = (0.0f32, 0.0f32);
    let (mut plain_seen, mut plain_weight) = (0.0f32, 0.0f32);
    for (&index, &weight) in indices.iter().zip(weights) {
        let sample = &low.volume[index * 4..index * 4 + 4];
        let alpha = sample[3];
        for (sum, value) in radiance.iter_mut().zip(sample) {
            *sum += weight * value;
        }
        through += weight * alpha;
        let side = match (opacity > 0.0, alpha > 0.0) {
            (true, _) => alpha,
            (false, false) => 1.0,
            (false, true) => 0.0,
        };
        let visibility = low.visibility[index];
        seen += weight * side * visibility;
        seen_weight += weight * side;
        plain_seen += weight * visibility;
        plain_weight += weight;
    }
    // No sample sees the medium: a sliver thinner than the samples' spacing stays dark.
    let scale = if through > 0.0 {
        opacity / through
    } else {
        0.0
    };
    let visibility = if seen_weight > 0.0 {
        seen / seen_weight
    } else {
        plain_seen / plain_weight
    };
    (
        [
            radiance[0] * scale,
            radiance[1] * scale,
            radiance[2] * scale,
            opacity,
        ],
        visibility,
    )
}

/// Per full-size pixel, its exact opacity (`exact(x, y)`, 1 − transmittance through the
/// medium along its ray) where the opacities of the four samples around it spread by more
/// than [`OPACITY_SPREAD`] of the largest, and [`BLENDED`] elsewhere: the guide
/// [`joint_bilateral_into`] takes in bounded media, where opacity jumps at the medium's
/// silhouette. Only those pixels pay for a ray; `None` where no samples spread. The
/// guide is full-size (a 16384² frame's is 1 GiB): an error names the image's settings
/// where it cannot be allocated, and [`keep_opacity_guide`] keeps it for the next frame.
pub fn opacity_guide(
    low: &Layers,
    width: u32,
    height: u32,
    factor: u32,
    exact: impl Fn(u32, u32) -> f32 + Sync,
) -> Result<Option<Vec<f32>>> {
    let (lw, lh) = (low.width as usize, low.height as usize);
    if lw == 0 || lh == 0 {
        return Ok(None);
    }
    let alpha = |index: usize| low.volume[index * 4 + 3];
    // Per cell between sample rows j, j + 1 and columns i, i + 1 (the last with itself):
    // whether its four samples spread. Every pixel in the cell shares the answer.
    let spread: Vec<bool> = (0..lh * lw)
        .into_par_iter()
        .map(|k| {
            let (j, i) = (k / lw, k % lw);
            let (above, below) = (j * lw, (j + 1).min(lh - 1) * lw);
            let next = (i + 1).min(lw - 1);
            let alphas = [above + i, above + next, below + i, below + next].map(alpha);
            let most = alphas.iter().fold(0.0f32, |a, &b| a.max(b));
            let least = alphas.iter().fold(f32::INFINITY, |a, &b| a.min(b));
            most > 0.0 && most - least > OPACITY_SPREAD * most
        })
        .collect();
    if !spread.contains(&true) {
        return Ok(None);
    }
    let columns = Columns::of(width, factor, lw);
    let w = (width as usize).max(1);
    let mut guide = SPARE_OPACITY_GUIDE.try_take(width as usize * height as usize, || {
        format!("upsampling's opacity guide ({width}×{height})")
    })?;
    guide.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let cells = &spread[Between::of(y as u32, factor, lh).lower * lw..][..lw];
        if !cells.contains(&true) {
            row.fill(BLENDED);
            return;
        }
        for (x, out) in row.iter_mut().enumerate() {
            *out = match cells[columns.lower[x]] {
                true => exact(x as u32, y as u32),
                false => BLENDED,
            };
        }
    });
    Ok(Some(guide))
}

/// Upsamples `low` (whose `depth` holds each sample's depth) to `width` × `height`,
/// guided by the full-resolution `depth`, which the result keeps as its depth layer, and
/// in bounded media by an [`opacity_guide`].
pub fn joint_bilateral(
    low: &Layers,
    depth: &[f32],
    opacity: Option<&[f32]>,
    width: u32,
    height: u32,
    factor: u32,
) -> Result<Layers> {
    let mut out = Layers::for_overwrite(width, height)?;
    out.depth.copy_from_slice(depth);
    Ok(joint_bilateral_into(low, out, opacity, factor))
}

/// [`upsample_row`] compiled for AVX2, whose weights take eight pixels a step rather than
/// SSE2's four; the same operations in the same order, so the same bits.
///
/// # Safety
/// The CPU must have AVX2 ([`Kernels::detect`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn upsample_row_avx2(
    low: &Layers,
    columns: &Columns,
    row: Between,
    depth: &[f32],
    opacity: Option<&[f32]>,
    volume: &mut [f32],
    visibility: &mut [f32],
    taps: &mut RowTaps,
) {
    upsample_row(low, columns, row, depth, opacity, volume, visibility, taps)
}

/// [`joint_bilateral`] into `out`, whose depth layer is the full-resolution guide and is
/// kept; its other layers are overwritten. Frames fill the guide straight into the
/// layers they return, rather than into a fresh buffer that is then copied (2M pixels at
/// 1080p, their pages faulted in every frame). `opacity`, if any, is full size.
pub fn joint_bilateral_into(
    low: &Layers,
    mut out: Layers,
    opacity: Option<&[f32]>,
    factor: u32,
) -> Layers {
    let (lw, lh) = (low.width as usize, low.height as usize);
    let columns = Columns::of(out.width, factor, lw);
    if let Some(guide) = opacity {
        assert_eq!(
            guide.len(),
            out.depth.len(),
            "an opacity guide is full size"
        );
    }
    let width = (out.width as usize).max(1);
    let kernels = Kernels::detect();
    let Layers {
        volume,
        visibility,
        depth,
        ..
    } = &mut out;
    volume
        .par_chunks_mut(width * 4)
        .zip(visibility.par_chunks_mut(width))
        .zip(depth.par_chunks(width))
        .enumerate()
        .for_each_init(
            RowTaps::default,
            |taps, (y, ((volume, visibility), depth))| {
                let row = Between::of(y as u32, factor, lh);
                let opacity = opacity.map(|guide| &guide[y * width..(y + 1) * width]);
                match kernels {
                    // SAFETY: `Kernels::detect` chose this variant where the CPU has AVX2.
                    #[cfg(target_arch = "x86_64")]
                    Kernels::Avx2Fma => unsafe {
                        upsample_row_avx2(
                            low, &columns, row, depth, opacity, volume, visibility, taps,
                        )
                    },
                    Kernels::Portable => {
                        upsample_row(low, &columns, row, depth, opacity, volume, visibility, taps)
                    }
                }
            },
        );
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
        let up = joint_bilateral(&low, &depth, None, width, height, factor).unwrap();
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

    /// The AVX2 build of a row gives the portable build's bits, on layers with depth edges,
    /// ramps, a pixel far from every sample (the closest-sample fallback) and, at ¼, pixels
    /// an opacity guide gives their opacity.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_rows_are_the_portable_rows_bit_for_bit() {
        if Kernels::detect() != Kernels::Avx2Fma {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        let (width, height) = (67u32, 23u32);
        let depth: Vec<f32> = (0..width * height)
            .map(|i| {
                let (x, y) = (i % width, i / width);
                match (x * 7 + y * 3) % 11 {
                    0 => 500.0,
                    k if k < 4 => 2.0 + 0.01 * x as f32,
                    _ => 40.0 - 0.3 * y as f32,
                }
            })
            .collect();
        for factor in [2u32, 4] {
            let (lw, lh) = (reduced_size(width, factor), reduced_size(height, factor));
            let mut low = Layers::new(lw, lh);
            for k in 0..(lw * lh) as usize {
                let (i, j) = (k as u32 % lw, k as u32 / lw);
                let (x, y) = (
                    sample_pixel(i, factor, width),
                    sample_pixel(j, factor, height),
                );
                let level = ((i * 13 + j * 5) % 17) as f32 / 16.0;
                low.volume[k * 4..k * 4 + 4].copy_from_slice(&[level, 0.5 * level, 0.1, level]);
                low.visibility[k] = 1.0 - level;
                low.depth[k] = depth[(y * width + x) as usize];
            }
            // Opacity guided at ¼, where the samples' opacities spread.
            let opacity = (factor == 4).then(|| {
                opacity_guide(&low, width, height, factor, |x, y| {
                    ((x + y) % 3) as f32 / 3.0
                })
                .unwrap()
                .expect("samples that spread")
            });
            let columns = Columns::of(width, factor, lw as usize);
            let w = width as usize;
            for y in 0..height {
                let row = Between::of(y, factor, lh as usize);
                let guide = &depth[y as usize * w..(y as usize + 1) * w];
                let opacity = opacity
                    .as_deref()
                    .map(|guide| &guide[y as usize * w..(y as usize + 1) * w]);
                let (mut portable, mut avx2) = (
                    (vec![0.0; 4 * w], vec![0.0; w]),
                    (vec![0.0; 4 * w], vec![0.0; w]),
                );
                let mut taps = RowTaps::default();
                upsample_row(
                    &low,
                    &columns,
                    row,
                    guide,
                    opacity,
                    &mut portable.0,
                    &mut portable.1,
                    &mut taps,
                );
                // SAFETY: the CPU has AVX2, checked above.
                unsafe {
                    upsample_row_avx2(
                        &low,
                        &columns,
                        row,
                        guide,
                        opacity,
                        &mut avx2.0,
                        &mut avx2.1,
                        &mut taps,
                    )
                };
                let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&portable.0), bits(&avx2.0), "factor {factor}, row {y}");
                assert_eq!(bits(&portable.1), bits(&avx2.1), "factor {factor}, row {y}");
            }
        }
    }

    /// A fog box's silhouette between columns 12 and 13, every pixel at one depth: fog of
    /// opacity 0.6 and radiance 0.6·(1, 0.5, 0.25) inside it, nothing outside.
    fn box_silhouette(x: u32) -> ([f32; 4], f32) {
        if x < 13 {
            ([0.0; 4], 0.3)
        } else {
            ([0.6, 0.3, 0.15, 0.6], 0.8)
        }
    }

    #[test]
    fn an_opacity_guide_keeps_the_fog_off_pixels_outside_a_box() {
        let (width, height, factor) = (30u32, 12u32, 4u32);
        let depth = vec![50.0f32; (width * height) as usize];
        let (lw, lh) = (reduced_size(width, factor), reduced_size(height, factor));
        let mut low = Layers::new(lw, lh);
        for k in 0..(lw * lh) as usize {
            let (rgba, seen) = box_silhouette(sample_pixel(k as u32 % lw, factor, width));
            low.volume[k * 4..k * 4 + 4].copy_from_slice(&rgba);
            low.visibility[k] = seen;
            low.depth[k] = 50.0;
        }
        // In a kept buffer of NaN: every pixel is written, guided or not.
        keep_opacity_guide(vec![f32::NAN; (width * height) as usize]);
        let guide = opacity_guide(&low, width, height, factor, |x, _| box_silhouette(x).0[3])
            .unwrap()
            .expect("samples that spread");
        // Only the columns that blend the samples either side of the edge (10 and 14) take
        // their exact opacity.
        for y in 0..height {
            for x in 0..width {
                let expected = if (10..=13).contains(&x) {
                    box_silhouette(x).0[3]
                } else {
                    BLENDED
                };
                assert_eq!(guide[(y * width + x) as usize], expected, "({x}, {y})");
            }
        }
        let guided = joint_bilateral(&low, &depth, Some(&guide), width, height, factor).unwrap();
        let depth_only = joint_bilateral(&low, &depth, None, width, height, factor).unwrap();
        for x in 10..=13 {
            let (rgba, seen) = box_silhouette(x);
            let got = guided.volume_rgba(x, 5);
            for c in 0..4 {
                assert!((got[c] - rgba[c]).abs() < 1e-6, "({x}) {got:?} vs {rgba:?}");
            }
            assert!((guided.visibility[(5 * width + x) as usize] - seen).abs() < 1e-6);
        }
        // Depth alone spreads the fog over the background beside the box.
        assert!(depth_only.volume_rgba(12, 5)[0] > 0.2);
        assert!(depth_only.volume_rgba(13, 5)[0] < 0.5);
    }

    #[test]
    fn upsampling_into_kept_layers_overwrites_all_but_the_guide() {
        let (width, height, factor) = (37, 21, 2);
        let (depth, value) = two_regions(width, height);
        let (lw, lh) = (reduced_size(width, factor), reduced_size(height, factor));
        let mut low = Layers::new(lw, lh);
        for k in 0..(lw * lh) as usize {
            let x = sample_pixel(k as u32 % lw, factor, width);
            let (rgba, seen) = value(x);
            low.volume[k * 4..k * 4 + 4].copy_from_slice(&rgba);
            low.visibility[k] = seen + 1e-3 * k as f32;
            low.depth[k] = if x < 13 { 2.0 } else { 40.0 };
        }
        // An earlier frame's values, which must not show through.
        let mut kept = Layers::new(width, height);
        kept.volume.fill(f32::NAN);
        kept.visibility.fill(f32::NAN);
        kept.depth.copy_from_slice(&depth);
        let into = joint_bilateral_into(&low, kept, None, factor);
        let fresh = joint_bilateral(&low, &depth, None, width, height, factor).unwrap();
        assert!(into
            .volume
            .iter()
            .chain(&into.visibility)
            .all(|v| v.is_finite()));
        assert_eq!(into, fresh);
    }

    #[test]
    fn the_range_weight_matches_exp_to_float_precision() {
        for i in 0..=200_000 {
            let x = i as f32 * 4e-4;
            let exact = (-(x as f64)).exp();
            let got = exp_negative(x) as f64;
            assert!(
                (got - exact).abs() <= 1e-7 * (2.0 + x as f64) * exact,
                "e^-{x}: {got} vs {exact}"
            );
        }
        assert_eq!(exp_negative(0.0), 1.0);
        for x in [90.0, 200.0, f32::INFINITY, f32::NAN] {
            assert!(exp_negative(x) <= f32::MIN_POSITIVE, "e^-{x}");
        }
        assert_eq!(exp_negative(-5.0), exp_negative(5.0));
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
        let up = joint_bilateral(&low, &depth, None, width, height, factor).unwrap();
        // Between the samples at pixels 1 and 3 a linear ramp is reproduced, up to the
        // small spatial-weight floor.
        let at = |x: u32| up.visibility[(3 * width + x) as usize];
        assert!((at(2) - 2.0).abs() < 0.01, "{}", at(2));
        assert!((at(1) - 1.0).abs() < 0.01);
    }
}
