//! The rasterizer's inner loop: a row's run of covered samples, their depths interpolated
//! and depth-tested. Written once per sample and once four samples at a time with AVX2,
//! the same operations in the same order, so both give the same bits; [`RunKernels`]
//! picks one per raster.

use super::{twice_area, ScreenTriangle};

/// One row's run of pixel centres inside a triangle: `len` pixels from (`x`, `y`), with
/// the triangle's edge functions at the first and their change per pixel.
pub(super) struct Run {
    pub x: u32,
    pub y: u32,
    pub len: usize,
    pub values: [i64; 3],
    pub step: [i64; 3],
}

impl Run {
    /// The edge functions at the run's `k`-th pixel.
    #[inline(always)]
    pub fn values_at(&self, k: usize) -> [i64; 3] {
        std::array::from_fn(|i| self.values[i] + k as i64 * self.step[i])
    }
}

/// How a triangle's depth follows from its edge functions: the vertices' attributes
/// weighted by them, over twice its area (their constant sum), or that area over the
/// weighted reciprocals where depth is w.
pub(super) struct RunDepth {
    attributes: [f64; 3],
    area: f64,
    perspective: bool,
}

impl RunDepth {
    pub fn of(triangle: &ScreenTriangle, perspective: bool) -> Self {
        Self {
            attributes: triangle.attributes,
            area: twice_area(&triangle.vertices) as f64,
            perspective,
        }
    }

    /// The depth where the edge functions are `values`.
    #[inline(always)]
    pub fn at(&self, values: [i64; 3]) -> f64 {
        let [a0, a1, a2] = self.attributes;
        let weighted = values[0] as f64 * a0 + values[1] as f64 * a1 + values[2] as f64 * a2;
        // With perspective, w is 1 over the interpolated 1/w: one division, and one
        // rounding, rather than the interpolation's then the reciprocal's.
        if self.perspective {
            self.area / weighted
        } else {
            weighted / self.area
        }
    }
}

/// What a run's samples are tested against: depths outside `range` are dropped, the rest
/// replace a stored depth they lie strictly nearer than, with `object_id` where ids are
/// kept.
pub(super) struct DepthTest<'a> {
    pub depth: &'a RunDepth,
    pub range: (f64, f64),
    pub object_id: u32,
}

#[derive(Clone, Copy, Debug)]
pub(super) enum RunKernels {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
}

/// Largest target side whose edge functions stay below 2⁵²: snapped coordinates lie
/// within the guard band, (3·side + 64)·256 in magnitude, and an edge function is at most
/// 8 times that squared.
const EXACT_SIDE: u32 = 32768;

impl RunKernels {
    /// The fastest kernels the CPU has for a `width` × `height` target.
    pub fn for_target(width: u32, height: u32) -> Self {
        #[cfg(target_arch = "x86_64")]
        if width.max(height) <= EXACT_SIDE && std::arch::is_x86_feature_detected!("avx2") {
            return RunKernels::Avx2;
        }
        let _ = (width, height);
        RunKernels::Portable
    }

    /// Tests `run`'s samples against `depth` (and `ids`), the run's own `len` samples.
    #[inline]
    pub fn test(self, test: &DepthTest, run: &Run, depth: &mut [f32], ids: Option<&mut [u32]>) {
        match self {
            RunKernels::Portable => test_run(test, run, depth, ids),
            // SAFETY: `for_target` only chose this variant where the CPU has AVX2.
            #[cfg(target_arch = "x86_64")]
            RunKernels::Avx2 => unsafe { test_run_avx2(test, run, depth, ids) },
        }
    }
}

/// The run's samples one at a time.
#[inline(always)]
fn test_run(test: &DepthTest, run: &Run, depth: &mut [f32], ids: Option<&mut [u32]>) {
    let (near, far) = test.range;
    let depth = &mut depth[..run.len];
    let mut ids = ids.map(|ids| &mut ids[..run.len]);
    for k in 0..run.len {
        let z = test.depth.at(run.values_at(k));
        if z < near || z > far {
            continue;
        }
        let z = z as f32;
        if z < depth[k] {
            depth[k] = z;
            if let Some(ids) = ids.as_deref_mut() {
                ids[k] = test.object_id;
            }
        }
    }
}

/// [`test_run`], four samples at a time, the last few under a mask. The edge functions
/// stay integers below 2⁵² ([`EXACT_SIDE`]), so they are exact in f64 and step there as
/// in i64; the weighted sum multiplies and adds apart (no fused multiply-add), as the
/// scalar code does.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn test_run_avx2(test: &DepthTest, run: &Run, depth: &mut [f32], ids: Option<&mut [u32]>) {
    use std::arch::x86_64::*;
    const LANES: usize = 4;
    let depth = &mut depth[..run.len];
    let mut ids = ids.map(|ids| &mut ids[..run.len]);
    let RunDepth {
        attributes,
        area,
        perspective,
    } = *test.depth;
    let attributes = attributes.map(|a| _mm256_set1_pd(a));
    let area = _mm256_set1_pd(area);
    let (near, far) = (_mm256_set1_pd(test.range.0), _mm256_set1_pd(test.range.1));
    let infinity = _mm256_set1_pd(f64::INFINITY);
    let object_id = _mm_set1_epi32(test.object_id as i32);
    let mut values: [__m256d; 3] = std::array::from_fn(|i| {
        let [a, b, c, d] = [0, 1, 2, 3].map(|k| (run.values[i] + k * run.step[i]) as f64);
        _mm256_setr_pd(a, b, c, d)
    });
    let steps: [__m256d; 3] =
        std::array::from_fn(|i| _mm256_set1_pd((LANES as i64 * run.step[i]) as f64));
    let lane_numbers = _mm_setr_epi32(0, 1, 2, 3);
    for k in (0..run.len).step_by(LANES) {
        let weighted = _mm256_add_pd(
            _mm256_add_pd(
                _mm256_mul_pd(values[0], attributes[0]),
                _mm256_mul_pd(values[1], attributes[1]),
            ),
            _mm256_mul_pd(values[2], attributes[2]),
        );
        let z = if perspective {
            _mm256_div_pd(area, weighted)
        } else {
            _mm256_div_pd(weighted, area)
        };
        // Outside the range becomes +∞, which no stored depth lies beyond; NaN stays and
        // fails the strict test, as it does one at a time.
        let outside = _mm256_or_pd(
            _mm256_cmp_pd::<_CMP_LT_OQ>(z, near),
            _mm256_cmp_pd::<_CMP_GT_OQ>(z, far),
        );
        let z = _mm256_cvtpd_ps(_mm256_blendv_pd(z, infinity, outside));
        // Lanes past the run's end are neither read nor written.
        let remaining = (run.len - k).min(LANES) as i32;
        let active = _mm_cmplt_epi32(lane_numbers, _mm_set1_epi32(remaining));
        let at = depth.as_mut_ptr().add(k);
        let stored = _mm_maskload_ps(at, active);
        let nearer = _mm_and_si128(
            _mm_castps_si128(_mm_cmp_ps::<_CMP_LT_OQ>(z, stored)),
            active,
        );
        _mm_maskstore_ps(at, nearer, z);
        if let Some(ids) = ids.as_deref_mut() {
            _mm_maskstore_epi32(ids.as_mut_ptr().add(k) as *mut i32, nearer, object_id);
        }
        for (value, step) in values.iter_mut().zip(&steps) {
            *value = _mm256_add_pd(*value, *step);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A triangle with these snapped vertices and attributes; only what runs read is set.
    fn triangle(vertices: [[i64; 2]; 3], attributes: [f64; 3]) -> ScreenTriangle {
        ScreenTriangle {
            vertices,
            attributes,
            object_id: 0,
            bounds: [0; 4],
            nearest: 0.0,
        }
    }

    #[test]
    fn the_area_is_the_edge_functions_sum_anywhere() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let limit = 1i64 << 24;
        for _ in 0..1000 {
            let vertices: [[i64; 2]; 3] =
                std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-limit..limit)));
            let depth = RunDepth::of(&triangle(vertices, [1.0; 3]), false);
            let p = [
                rng.random_range(-limit..limit),
                rng.random_range(-limit..limit),
            ];
            let sum: i64 = (0..3)
                .map(|i| {
                    let (a, b) = (vertices[(i + 1) % 3], vertices[(i + 2) % 3]);
                    -(b[1] - a[1]) * (p[0] - a[0]) + (b[0] - a[0]) * (p[1] - a[1])
                })
                .sum();
            assert_eq!(depth.area, sum as f64, "{vertices:?} at {p:?}");
        }
    }

    /// Every kernel's depths and ids, bit for bit, against one sample at a time, on runs
    /// of every length up to 13 with edge functions up to 2⁵⁰, attributes of either sign
    /// (depths of ±∞ and NaN where the weights cancel), depth ranges that drop some
    /// samples, and stored depths that are ±∞ or NaN.
    #[test]
    fn every_kernel_tests_runs_as_one_sample_at_a_time() {
        let kernels = RunKernels::for_target(1920, 1080);
        if matches!(kernels, RunKernels::Portable) {
            eprintln!("skipped: this CPU has only the portable kernel");
            return;
        }
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let stored_values = [f32::INFINITY, f32::NEG_INFINITY, f32::NAN, 0.0, 1.0];
        for case in 0..4000 {
            let len = case % 14;
            let magnitude = 1i64 << rng.random_range(4..50);
            let run = Run {
                x: 0,
                y: 0,
                len,
                values: std::array::from_fn(|_| rng.random_range(-magnitude..magnitude)),
                step: std::array::from_fn(|_| {
                    rng.random_range(-(magnitude >> 2) - 1..(magnitude >> 2) + 1)
                }),
            };
            let attributes = std::array::from_fn(|_| match rng.random_range(0..4) {
                0 => 0.0,
                _ => rng.random_range(-2.0..2.0),
            });
            let vertices = [[0, 0], [rng.random_range(1..magnitude), 0], [0, 1]];
            let depth = RunDepth {
                perspective: rng.random_range(0..2) == 0,
                ..RunDepth::of(&triangle(vertices, attributes), false)
            };
            let range = match rng.random_range(0..3) {
                0 => (f64::NEG_INFINITY, f64::INFINITY),
                _ => (rng.random_range(-1.0..0.5), rng.random_range(0.5..2.0)),
            };
            let test = DepthTest {
                depth: &depth,
                range,
                object_id: 7,
            };
            let stored: Vec<f32> = (0..len + 3)
                .map(|_| match rng.random_range(0..8) {
                    n if n < stored_values.len() => stored_values[n],
                    _ => rng.random_range(-1.0..3.0),
                })
                .collect();
            let ids: Vec<u32> = (0..len as u32 + 3).collect();
            let with_ids = rng.random_range(0..2) == 0;
            let tested = |kernels: RunKernels| {
                let (mut depth, mut ids) = (stored.clone(), ids.clone());
                let run_ids = with_ids.then_some(&mut ids[..len]);
                kernels.test(&test, &run, &mut depth[..len], run_ids);
                (depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>(), ids)
            };
            assert_eq!(
                tested(kernels),
                tested(RunKernels::Portable),
                "case {case}: {len} samples, perspective {}, range {range:?}",
                depth.perspective
            );
        }
    }
}
