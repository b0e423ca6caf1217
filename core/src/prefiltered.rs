//! Prefiltered single scattering on the rectified shadow map (dissertation §4.3): the
//! visibility step is expanded in a Fourier basis (Eq. 4.7), so that the
//! transmittance-weighted visibility along any stretch of a view ray is one dot product
//! between the ray's coefficients and a difference of weighted prefix sums of the basis
//! along its slice.
//!
//! - Keys (rectified values, oriented so that larger means more shadowed) are warped per
//!   slice by quantiles of the slice's ray keys and of the texel keys among them into
//!   [`RAY_MARGIN`, 1 − `RAY_MARGIN`], which spends the basis' resolution where rays
//!   and nearby occluders are and keeps differences clear of the series' periodic jump.
//! - Each row of prefix sums adds [`SAMPLES_PER_ROW`] rectified samples, so that the map
//!   follows the shadow map twice per texel while the tables keep one row per texel.
//! - Weights follow a reference ray (Eq. 4.8–4.12). One reference per slice is the
//!   paper's choice; it fails where a slice's rays cross texels at very different speeds
//!   (near an on-screen sun, where the slowest rays run almost along the light). Each
//!   slice therefore keeps *bands* of references whose speeds are an octave apart (a
//!   fraction of one in dense media, [`bands_per_octave`]), and a ray blends the two
//!   bands either side of its own speed. A slow ray's weights fade within few texels, so
//!   its band's table ends there: all bands together cost little more than one.
//! - Weights are stored normalized (the filtered basis stays in [−1, 1]), with the
//!   cumulative weight beside them. Coefficients and basis are tabulated, so neither
//!   building nor evaluating takes trigonometry per texel or per pixel.
//! - The sunlight's attenuation inside a `box` medium is smooth, so it is factored out of
//!   the visibility integral piecewise: the ray is cut into pieces over which it changes
//!   by a bounded optical depth ([`box_pieces`]), and each piece's weighted visibility
//!   multiplies its exact unshadowed in-scattering. One piece per ray was 11% off where
//!   light enters the box through an opening and dims farther in. The view ray's own
//!   optical depth bounds the pieces too, where they stay long enough for lookups.
//! - A stretch of a ray that the rectified map shows lit, or shadowed, over every sample
//!   it crosses is answered exactly from a table of the map's sample bounds
//!   ([`UniformityTable`]) instead of from the series, whose damped residue was most of
//!   the error on views where many rays never cross a shadow (torus 0.34% → 0.07%).

use std::f64::consts::PI;
use std::sync::OnceLock;

use glam::{DVec3, Mat4};
use rayon::prelude::*;

use crate::basis_kernels::{padded, BandRead, BasisValue, Kernels};
use crate::camera::{CameraModel, Ray};
use crate::epipolar::{bounded_slice_index, EpipolarMap, RaySlice};
use crate::error::{Error, Result, Sizing};
use crate::reference::{integral_exp, medium_segment, weighted_visibility, BoxMedium, RaySample};
use crate::scene::{BasisStorage, ExactRayEnds, Extent, Medium, RenderSettings, Sun};
use crate::spare::Spare;
use crate::total_order::{from_total_order_bits, total_order_bits};
use crate::uniformity::UniformityTable;

/// Basis coefficients M: sine and cosine of M/2 frequencies.
pub const MIN_BASES: u32 = 4;
pub const MAX_BASES: u32 = 64;

/// The longest coefficient row, at M = [`MAX_BASES`] (a whole number of lanes).
const MAX_STRIDE: usize = MAX_BASES as usize;
const _: () = assert!(MAX_STRIDE.is_multiple_of(crate::basis_kernels::LANES));

/// Quantiles of the ray keys kept per slice.
const KNOTS: usize = 9;
/// Resolution of the tabulated basis and coefficients over warped keys in [0, 1]: the
/// highest frequency's phase moves by at most 31π/8192 ≈ 0.012 rad between entries.
const TABLE_STEPS: usize = 8192;
/// Reference optical depth at which sample weights end: past it, differences of prefix
/// sums would be f32 rounding. A lookup then ends there too, and a stretch that starts
/// there is walked ([`CONDITION_LIMIT`]). (Weights that stayed at the cap's instead gave
/// the far end of a ray starting a few optical depths along its slice, an orthographic
/// camera's, an eighth of its weight: 5% bright under a roof in fog of 0.6 /m.)
const MAX_REFERENCE_DEPTH: f64 = 10.0;
/// Octaves of speed that a slice's bands cover at most; the slowest takes every ray
/// slower than it.
const MAX_OCTAVES: usize = 7;
/// Optical depth (extinction times the tables' reach) up to which bands an octave apart
/// suffice. A ray between two bands takes the blend of their weighted averages, whose
/// weights decay as e^(−σt) of rays up to √2 faster or slower than itself, and in dense
/// fog that blend is far off where a ray's light comes from past a shadow: a camera
/// under a closed roof in fog of 0.2 /m looking out (optical depth 14) read 54% off the
/// reference (+49% signed) with octaves, 20% with two bands an octave, 16% with three,
/// 15% with four, the rest the series'. Each band more an octave costs rows: colonnade
/// at 0.2 /m took 129 ms at 1080p with octaves, 143 with two, 154 with three.
pub const OCTAVE_BAND_DEPTH: f64 = 6.0;
/// Most bands per octave of speed.
pub const MAX_BANDS_PER_OCTAVE: u32 = 4;

/// Bands per octave of speed for a medium of `extinction` whose tables reach `reach`
/// along the fastest rays: one where the optical depth is at most
/// [`OCTAVE_BAND_DEPTH`], more in proportion beyond.
pub fn bands_per_octave(extinction: f64, reach: f64) -> u32 {
    // NaN converts to 0, which the clamp makes one.
    ((extinction * reach / OCTAVE_BAND_DEPTH).ceil() as u32).clamp(1, MAX_BANDS_PER_OCTAVE)
}

/// Optical depth from which a ray's remaining in-scattering (below e^−16) is negligible:
/// a band's table ends where its fastest ray gets there.
const NEGLIGIBLE_DEPTH: f64 = 16.0;
/// Largest ratio between a slice's fastest and slowest ray considered for its references.
const MAX_SPEED_RATIO: f64 = 4096.0;
/// Rectified samples summed into one row of prefix sums. Resampling the shadow map once
/// per texel along a slice skips or repeats texels, which widens or narrows thin shafts
/// by a whole sample (4.4% on `plane` seen sideways, against 1.7% for min-max on a map
/// sampled twice per texel). Two samples per row keep that fidelity at the memory and
/// per-pixel cost of one row per texel.
pub const SAMPLES_PER_ROW: usize = 2;

/// Reads per ray in [`Prefiltered::look_up`]: two bands in each of two slices.
const LANES_PER_RAY: usize = 4;

/// Rows of prefix sums along a slice of `map`.
fn row_count(map: &EpipolarMap) -> usize {
    (map.samples as usize).div_ceil(SAMPLES_PER_ROW)
}

/// The continuous row coordinate of `s`: row r spans [r, r + 1].
#[inline]
fn row_coordinate(map: &EpipolarMap, s: f64) -> f64 {
    map.sample_coordinate(s) * (1.0 / SAMPLES_PER_ROW as f64)
}

/// What the prefiltered method needs besides the map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrefilteredDesc {
    /// M, even, in [`MIN_BASES`]..=[`MAX_BASES`] (validated by the settings).
    pub bases: u32,
    /// Longest stretch of a view ray that is evaluated: bounds the tables' lengths.
    pub max_distance: f64,
    /// Subtract the stretch between the camera and the near clip plane (one more lookup
    /// per slice). Media that begin later along the ray (a `box`) always subtract it.
    pub near_plane_correction: bool,
    /// Integrate exactly the stretch before each ray's end where the samples close in on
    /// the ray (`Prefiltered::exact_end`); in a box, in a ray's last piece.
    pub exact_ray_ends: ExactRayEnds,
    pub storage: BasisStorage,
    /// Half-width in pixels of the block around an on-screen epipole that is ray-marched
    /// instead: its rays need no tables.
    pub epipole_block: f64,
    /// Whether the frame is nearly dark, so that rays its lookups read dark are walked
    /// wherever it is ([`dark_lookup_limit`]); the frame decides, from a probe of its rays
    /// (`crate::render::frame_is_dark`).
    pub dark_frame: bool,
}

impl PrefilteredDesc {
    pub fn from_settings(settings: &RenderSettings) -> Self {
        Self {
            bases: settings.bases,
            max_distance: settings.max_distance as f64,
            near_plane_correction: settings.near_plane_correction,
            exact_ray_ends: settings.exact_ray_ends,
            storage: settings.basis_storage,
            epipole_block: settings.epipole_block as f64,
            dark_frame: false,
        }
    }
}

/// Warped keys of a slice's rays lie this far inside [0, 1]. Keys beyond the rays' range
/// compare like the nearest end, so the margin only has to keep them clear of the series'
/// jump at a difference of ±1. A quarter (the first choice) wasted half the resolution:
/// 0.1 took colonnade's default view from 3.7% to 2.2% at M = 32, and no view got worse
/// by more than 0.15 points.
const RAY_MARGIN: f64 = 0.1;

/// A monotone map of keys into [0, 1], piecewise linear between quantiles.
#[derive(Clone, Copy, Debug)]
struct Warp {
    /// Keys at evenly spaced warped positions in [`RAY_MARGIN`, 1 − `RAY_MARGIN`], strictly
    /// increasing.
    knots: [f64; KNOTS],
    /// Per segment, warped units per unit of key, so that warping a key (once per pixel
    /// and band) takes no division.
    slopes: [f64; KNOTS - 1],
    /// Where the warp spans keys beyond its knots ([`Warp::spanning`]): the keys that
    /// reach 0 and 1 in the margins, and the margins' slopes towards them.
    outer: Option<OuterKeys>,
}

/// Keys beyond a [`Warp`]'s knots that it keeps apart in its margins.
#[derive(Clone, Copy, Debug)]
struct OuterKeys {
    keys: [f64; 2],
    slopes: [f64; 2],
}

impl OuterKeys {
    /// The warp `z` of `key`, by its end segments, kept apart from the other outer keys
    /// in the margins ([`Warp::spanning`]); the same within the knots.
    #[cold]
    fn in_margins(&self, key: f64, z: f64) -> f64 {
        let low = lesser((key - self.keys[0]) * self.slopes[0], Warp::HALF_MARGIN);
        let high = greater(
            1.0 - (self.keys[1] - key) * self.slopes[1],
            1.0 - Warp::HALF_MARGIN,
        );
        lesser(high, greater(low, z))
    }
}

/// `a` where it is below `b`, else `b` (NaN in `a` gives `b`, as `_mm256_min_pd` does).
#[inline(always)]
fn lesser(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// `a` where it is above `b`, else `b` (as `_mm256_max_pd` does).
#[inline(always)]
fn greater(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

impl Warp {
    /// Warped length of one segment between knots.
    const SEGMENT: f64 = (1.0 - 2.0 * RAY_MARGIN) / (KNOTS - 1) as f64;

    /// Half the margin: where [`Warp::spanning`] starts to hold outer keys apart.
    const HALF_MARGIN: f64 = RAY_MARGIN / 2.0;

    fn from_knots(knots: [f64; KNOTS]) -> Self {
        Self {
            knots,
            slopes: std::array::from_fn(|i| Self::SEGMENT / (knots[i + 1] - knots[i])),
            outer: None,
        }
    }

    /// This warp, but for keys from `lowest` to `highest` (a band's slice's rays, where the
    /// band's own rays span less) in its margins: within half of a margin of its end each
    /// such key warps to at least as far in as it did before, from 0 at `lowest` and 1 at
    /// `highest`. Beyond its knots a warp's end segments reach 0 and 1 soon, and keys past
    /// that meet the texels beyond at one end of the series, which reads half lit: with
    /// 4,096 slices at 384×216 a dense-fog view was still 8% off the reference once the
    /// border's rays reached every slice ([`border_rays`]), where rays of one speed had
    /// been sampled along a part of their slices only (1.5% with this). A side that the
    /// knots span holds as many keys again beyond them in the same way. Unchanged where its
    /// end segments already keep both keys inside (0, 1).
    fn spanning(self, lowest: f64, highest: f64) -> Self {
        let [first, last] = [self.knots[0], self.knots[KNOTS - 1]];
        if self.warp(lowest) > 0.0 && self.warp(highest) < 1.0 {
            return self;
        }
        let range = last - first;
        let keys = [
            if lowest < first {
                lowest
            } else {
                first - range
            },
            if highest > last {
                highest
            } else {
                last + range
            },
        ];
        Self {
            outer: Some(OuterKeys {
                keys,
                slopes: [
                    Self::HALF_MARGIN / (first - keys[0]),
                    Self::HALF_MARGIN / (keys[1] - last),
                ],
            }),
            ..self
        }
    }

    /// Position in [0, 1] for a key; rays land in [`RAY_MARGIN`, 1 − `RAY_MARGIN`].
    #[inline]
    fn warp(&self, key: f64) -> f64 {
        let k = &self.knots;
        let index = self.inner_knots_at_or_below(key);
        let z = RAY_MARGIN + Self::SEGMENT * index as f64 + (key - k[index]) * self.slopes[index];
        // Keys inside the knots (nearly every ray's) warp as without outer keys.
        let z = match &self.outer {
            Some(outer) if !(k[0] <= key && key <= k[KNOTS - 1]) => outer.in_margins(key, z),
            _ => z,
        };
        z.clamp(0.0, 1.0)
    }

    /// How many inner knots lie at or below `key` (none for NaN): the segment it lies in.
    #[inline]
    fn inner_knots_at_or_below(&self, key: f64) -> usize {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::*;
            const { assert!(KNOTS == 9) };
            let k = &self.knots;
            // SAFETY: SSE2 is part of x86_64; every load reads two knots of the array.
            unsafe {
                let key = _mm_set1_pd(key);
                let pair = |i: usize| {
                    // m − m/2 is the number of set bits of a two-bit mask.
                    let mask = _mm_movemask_pd(_mm_cmple_pd(_mm_loadu_pd(k.as_ptr().add(i)), key));
                    (mask - (mask >> 1)) as usize
                };
                let last = _mm_movemask_pd(_mm_cmple_sd(_mm_load_sd(&k[7]), key)) & 1;
                pair(1) + pair(3) + pair(5) + last as usize
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self.knots[1..KNOTS - 1]
                .iter()
                .filter(|&&knot| knot <= key)
                .count()
        }
    }

    /// The key that warps to `z` ([`Warp::warp`]'s inverse inside [0, 1]).
    #[inline]
    fn unwarp(&self, z: f64) -> f64 {
        let position = (z - RAY_MARGIN) / Self::SEGMENT;
        let index = (position.max(0.0) as usize).min(KNOTS - 2);
        let gap = self.knots[index + 1] - self.knots[index];
        let key = self.knots[index]
            + (z - RAY_MARGIN - Self::SEGMENT * index as f64) / Self::SEGMENT * gap;
        match &self.outer {
            // Where the margins' lines hold the keys, the lesser key (the greater one
            // above) warps to `z`.
            Some(outer) if z < Self::HALF_MARGIN => key.min(outer.keys[0] + z / outer.slopes[0]),
            Some(outer) if z > 1.0 - Self::HALF_MARGIN => {
                key.max(outer.keys[1] - (1.0 - z) / outer.slopes[1])
            }
            _ => key,
        }
    }

    /// The coefficient-table index of each key's warp, `Tables::index(self.warp(key))`,
    /// into `entries` (as many as both hold); with AVX2, four keys at a time in the same
    /// arithmetic, bit for bit.
    fn table_indices(&self, kernels: Kernels, keys: &[f64], entries: &mut [u32]) {
        let count = keys.len().min(entries.len());
        let (keys, entries) = (&keys[..count], &mut entries[..count]);
        let done = match kernels {
            Kernels::Portable => 0,
            // SAFETY: `Kernels::detect` only chose this variant where the CPU has AVX2.
            #[cfg(target_arch = "x86_64")]
            Kernels::Avx2Fma => unsafe { self.table_indices_avx2(keys, entries) },
        };
        for (entry, &key) in entries[done..].iter_mut().zip(&keys[done..]) {
            *entry = Tables::index(self.warp(key)) as u32;
        }
    }

    /// [`Warp::table_indices`] for whole groups of four keys; returns how many it did.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn table_indices_avx2(&self, keys: &[f64], entries: &mut [u32]) -> usize {
        use std::arch::x86_64::*;
        let inner: [__m256d; KNOTS - 2] =
            std::array::from_fn(|j| _mm256_set1_pd(self.knots[j + 1]));
        let (one, zero) = (_mm256_set1_pd(1.0), _mm256_setzero_pd());
        let (margin, segment) = (_mm256_set1_pd(RAY_MARGIN), _mm256_set1_pd(Self::SEGMENT));
        let (steps, half) = (_mm256_set1_pd(TABLE_STEPS as f64), _mm256_set1_pd(0.5));
        let outer = self.outer.map(|outer| {
            (
                outer.keys.map(|key| _mm256_set1_pd(key)),
                outer.slopes.map(|slope| _mm256_set1_pd(slope)),
            )
        });
        let (half_margin, one_less_half_margin) = (
            _mm256_set1_pd(Self::HALF_MARGIN),
            _mm256_set1_pd(1.0 - Self::HALF_MARGIN),
        );
        for (keys, entries) in keys.chunks_exact(4).zip(entries.chunks_exact_mut(4)) {
            let key = _mm256_loadu_pd(keys.as_ptr());
            // How many inner knots lie at or below each key (none for NaN), as in `warp`.
            let mut index = zero;
            for knot in inner {
                index = _mm256_add_pd(
                    index,
                    _mm256_and_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(knot, key), one),
                );
            }
            // At most KNOTS − 2: inside both gathered arrays.
            let lanes = _mm256_cvttpd_epi32(index);
            let knot = _mm256_i32gather_pd::<8>(self.knots.as_ptr(), lanes);
            let slope = _mm256_i32gather_pd::<8>(self.slopes.as_ptr(), lanes);
            let z = _mm256_add_pd(
                _mm256_add_pd(margin, _mm256_mul_pd(segment, index)),
                _mm256_mul_pd(_mm256_sub_pd(key, knot), slope),
            );
            // `lesser` and `greater` are `_mm256_min_pd` and `_mm256_max_pd`, operand for
            // operand.
            let z = match &outer {
                None => z,
                Some((outer_keys, outer_slopes)) => {
                    let low = _mm256_min_pd(
                        _mm256_mul_pd(_mm256_sub_pd(key, outer_keys[0]), outer_slopes[0]),
                        half_margin,
                    );
                    let high = _mm256_max_pd(
                        _mm256_sub_pd(
                            one,
                            _mm256_mul_pd(_mm256_sub_pd(outer_keys[1], key), outer_slopes[1]),
                        ),
                        one_less_half_margin,
                    );
                    _mm256_min_pd(high, _mm256_max_pd(low, z))
                }
            };
            // `clamp`; a NaN becomes 0 here, and index 0 in `Tables::index` either way.
            let z = _mm256_min_pd(_mm256_max_pd(z, zero), one);
            let table = _mm256_cvttpd_epi32(_mm256_add_pd(_mm256_mul_pd(z, steps), half));
            _mm_storeu_si128(entries.as_mut_ptr().cast(), table);
        }
        keys.len() / 4 * 4
    }
}

/// Per slice: the warp of all its rays, and their speeds.
#[derive(Clone, Copy, Debug)]
struct SliceFrame {
    warp: Warp,
    /// Texels per unit of t of the slice's fastest and slowest rays.
    fastest: f64,
    slowest: f64,
    /// Where the slice's rays are at t = 0 (the smallest such position).
    origin: f64,
    /// Where the first of them enters the medium: the transmittance weights decay from
    /// there. `None` where no sampled ray meets a `box`: weights are even.
    medium_start: Option<f64>,
    log2_fastest: f64,
    /// Bands per octave of speed ([`bands_per_octave`]).
    bands_per_octave: u32,
}

impl SliceFrame {
    /// Bands at speeds fastest·2^(−j/n), n bands an octave, down to the first at or below
    /// the slowest ray.
    fn band_count(&self) -> usize {
        let ratio = (self.fastest / self.slowest).max(1.0);
        let n = self.bands_per_octave as usize;
        let octaves = ratio.ln() / std::f64::consts::LN_2;
        let steps = (octaves * n as f64 - 1e-9).ceil().max(0.0) as usize;
        (steps + 1).min(MAX_OCTAVES * n + 1)
    }

    /// Band j's reference speed.
    fn band_rate(&self, j: usize) -> f64 {
        let n = self.bands_per_octave as usize;
        let (octaves, part) = (j / n, j % n);
        self.fastest / (2.0f64.powi(octaves as i32) * 2.0f64.powf(part as f64 / n as f64))
    }

    /// Where a ray of log₂(rate) falls between the bands: band index plus fraction.
    #[inline]
    fn band_position(&self, log2_rate: f64, count: usize) -> f64 {
        band_position(
            self.log2_fastest,
            log2_rate,
            self.bands_per_octave as f64,
            count,
        )
    }
}

/// Where a ray of log₂(rate) falls among `count` bands, `bands_per_octave` an octave,
/// from a slice's fastest ray: band index plus fraction.
#[inline]
fn band_position(log2_fastest: f64, log2_rate: f64, bands_per_octave: f64, count: usize) -> f64 {
    ((log2_fastest - log2_rate) * bands_per_octave).clamp(0.0, (count - 1) as f64)
}

/// One reference ray's table: `rows` boundaries from `first_row` on.
#[derive(Clone, Copy, Debug)]
struct Band {
    /// Texels per unit of t of the reference.
    rate: f64,
    /// The warp of the keys of the rays that read this band. A band's rays share a
    /// narrow range of speeds, and with an epipolar layout of angles to the light, so
    /// their keys span a fraction of the slice's: near an on-screen sun a slice's keys
    /// span most of [−1, 1] and one warp for them all blurred rays grazing an occluder.
    warp: Warp,
    first_row: usize,
    rows: usize,
}

impl Band {
    /// A continuous boundary position, clamped to the table, as the boundaries either side:
    /// the lower one, below the last (its fraction then 1 at the table's end), and the
    /// fraction towards the next. A read always blends both rows: the empty prefix
    /// (boundary 0) is a stored row of zeros, of zero weight.
    #[inline]
    fn straddle(&self, x: f64) -> (usize, f64) {
        // `plan_bands` gives every band at least one row of samples besides the empty prefix.
        debug_assert!(self.rows >= 2);
        let last = (self.rows - 1) as f64;
        let x = x.clamp(0.0, last);
        let lower = (x as u32 as usize).min(self.rows - 2);
        (lower, x - lower as f64)
    }
}

/// Per slice, where its bands are, and its fastest ray's log₂ speed ([`SliceFrame`]'s),
/// which places each pixel's ray among them without reading the whole frame.
#[derive(Clone, Copy, Debug)]
struct SliceBands {
    first: u32,
    count: u32,
    log2_fastest: f64,
}

/// Basis and coefficients over warped keys, shared by every frame with the same M.
struct Tables {
    /// Row i: [cos(c·z)…, sin(c·z)…] at z = i / TABLE_STEPS, padded with zeros.
    basis: Vec<f32>,
    /// Row i: [(2/c)·σ·sin(c·z)…, −(2/c)·σ·cos(c·z)…], so that the dot product with a
    /// basis row is Σ (2/c)·σ·sin(c·(z_ray − z_texel)), σ = [`damping`] of the frequency.
    coefficients: Vec<f32>,
    /// Per frequency c, 2·sin(c·[`BLUR_WIDTH`]): what turns a coefficient row into its
    /// blur row ([`Tables::blur_of`]).
    blur_factors: Vec<f32>,
}

impl Tables {
    fn get(frequencies: usize) -> &'static Tables {
        static CACHE: [OnceLock<Tables>; MAX_BASES as usize / 2 + 1] =
            [const { OnceLock::new() }; MAX_BASES as usize / 2 + 1];
        CACHE[frequencies].get_or_init(|| Tables::new(frequencies))
    }

    fn new(frequencies: usize) -> Self {
        let row = padded(2 * frequencies);
        let mut basis = vec![0.0f32; (TABLE_STEPS + 1) * row];
        let mut coefficients = vec![0.0f32; (TABLE_STEPS + 1) * row];
        let mut values = vec![0.0f64; 2 * frequencies];
        // Per frequency, not per row: a sine and a power for each of 8,193 rows were most
        // of a process's first prefiltered frame's 23 million instructions here.
        let scales: Vec<f64> = (0..frequencies)
            .map(|m| damping(m, frequencies) * 2.0 / frequency(m))
            .collect();
        for (i, (basis, coefficients)) in basis
            .chunks_exact_mut(row)
            .zip(coefficients.chunks_exact_mut(row))
            .enumerate()
        {
            harmonics(i as f64 / TABLE_STEPS as f64, frequencies, &mut values);
            for (m, &scale) in scales.iter().enumerate() {
                let (cos, sin) = (values[m], values[frequencies + m]);
                basis[m] = cos as f32;
                basis[frequencies + m] = sin as f32;
                coefficients[m] = (scale * sin) as f32;
                coefficients[frequencies + m] = (-scale * cos) as f32;
            }
        }
        let blur_factors = (0..frequencies)
            .map(|m| (2.0 * (frequency(m) * BLUR_WIDTH).sin()) as f32)
            .collect();
        Self {
            basis,
            coefficients,
            blur_factors,
        }
    }

    /// Into `out`, the coefficients [`BLUR_WIDTH`] above the warped key of the row
    /// `coefficients` less those as far below, so that a lookup dotted with it gives how
    /// much its visibility changes across that window about the ray's key
    /// ([`BLURRED_SHARE_LIMIT`]). Found from the row itself, where it is already in cache:
    /// in a profile of colonnade's frames, lookups took 12.8% without the check, 15.7% with
    /// it, and 16.7% with blur rows read from a table of their own (a second random read
    /// per band). Per frequency c, sin(c(z + w)) − sin(c(z − w)) = 2·sin(cw)·cos(cz)
    /// and cos(c(z + w)) − cos(c(z − w)) = −2·sin(cw)·sin(cz), so each half of the blur row
    /// is the other half of the coefficient row, scaled.
    #[inline]
    fn blur_of(&self, coefficients: &[f32], out: &mut [f32]) {
        let frequencies = self.blur_factors.len();
        let (sines, cosines) = coefficients.split_at(frequencies);
        let (out_sines, out_cosines) = out.split_at_mut(frequencies);
        // Zipped, not indexed, so that the loops vectorize.
        for ((out, &factor), &cosine) in out_sines.iter_mut().zip(&self.blur_factors).zip(cosines) {
            *out = -factor * cosine;
        }
        for ((out, &factor), &sine) in out_cosines.iter_mut().zip(&self.blur_factors).zip(sines) {
            *out = factor * sine;
        }
        out_cosines[frequencies..].fill(0.0);
    }

    #[inline]
    fn index(z: f64) -> usize {
        // z ∈ [0, 1]: rounding by truncation avoids a libm call.
        (z * TABLE_STEPS as f64 + 0.5) as u32 as usize
    }
}

// The last frame's filtered basis and its plan's arrays, kept for the next (see
// `crate::spare`): the plan's page faults took 15% of tree's preparation.
static SPARE_F32_BASIS: Spare<f32> = Spare::on_huge_pages(Sizing::Rectified);
static SPARE_SNORM16_BASIS: Spare<i16> = Spare::on_huge_pages(Sizing::Rectified);
static SPARE_ENTRIES: Spare<u32> = Spare::new(Sizing::Rectified);
static SPARE_SAMPLE_WEIGHTS: Spare<f32> = Spare::new(Sizing::Rectified);
static SPARE_SCALES: Spare<f32> = Spare::new(Sizing::Rectified);
static SPARE_ROW_WEIGHTS: Spare<f32> = Spare::on_huge_pages(Sizing::Rectified);
static SPARE_KEYED_RAYS: Spare<(u64, f64)> = Spare::new(Sizing::Image);

/// Lets go of the kept filtered bases and plans ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_F32_BASIS.clear();
    SPARE_SNORM16_BASIS.clear();
    SPARE_ENTRIES.clear();
    SPARE_SAMPLE_WEIGHTS.clear();
    SPARE_SCALES.clear();
    SPARE_ROW_WEIGHTS.clear();
    SPARE_KEYED_RAYS.clear();
}

/// The filtered-basis storage.
pub struct Prefiltered<'a> {
    map: &'a EpipolarMap,
    /// M rounded up to whole lanes: the stride of every basis and coefficient row.
    stride: usize,
    kernels: Kernels,
    tables: &'static Tables,
    slice_bands: Vec<SliceBands>,
    bands: Vec<Band>,
    /// Per band, `rows` rows of M: the weighted mean of the basis over the slice's
    /// samples before each boundary.
    basis: FilteredBasis,
    /// The cumulative weight at each boundary.
    weight: Vec<f32>,
    rays: RaySettings,
    /// Where a stretch of a ray is lit or shadowed all along, it needs no lookup.
    uniformity: UniformityTable,
}

/// How rays are integrated, fixed by the plan ([`PrefilteredPlan`]) and read by every ray.
#[derive(Clone, Copy, Debug)]
struct RaySettings {
    extinction: f64,
    near_plane_correction: bool,
    box_medium: Option<BoxMedium>,
    light_travel: DVec3,
    /// M/2: the step's width in warped keys is about 1/`frequencies`.
    frequencies: usize,
    /// Of the slices' bands ([`bands_per_octave`]).
    bands_per_octave: f64,
    exact_ray_ends: bool,
    /// Looked-up visibility below which a ray is declined ([`dark_lookup_limit`]).
    dark_lookup_limit: f64,
}

fn frequency(m: usize) -> f64 {
    PI * (2 * m + 1) as f64
}

/// Exponent of the Lanczos σ-factors that damp the series. The truncated series
/// overshoots the visibility step by 9% (Gibbs): beside an occluder it rings, which shows
/// as ripples in dark shafts and rings around an on-screen sun. Lanczos' factors take the
/// overshoot to 1.2% but widen the step's 10–90% transition 1.8×, and a wider step leaks
/// light under occluders that rays graze. Their square root takes the overshoot to 3.2%
/// and widens the step 1.4× (M = 32). Against the undamped series it lowered the error on
/// 22 of 23 random views of the built-in scenes and on 9 of the 16 test views (the worst
/// from 2.3% to 2.0%); orthographic views, where rays see little ringing, lost up to 0.4
/// points.
const RINGING_DAMPING: f64 = 0.5;

/// The σ-factor of frequency m of `frequencies`: sinc(π(2m + 1)/(2F + 1)) to the power
/// [`RINGING_DAMPING`].
fn damping(m: usize, frequencies: usize) -> f64 {
    let x = PI * (2 * m + 1) as f64 / (2 * frequencies + 1) as f64;
    (x.sin() / x).powf(RINGING_DAMPING)
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

/// The filtered basis in the precision the settings ask for: per band, `rows` rows of
/// [`PrefixPlan::stride`] values.
#[derive(Clone, Debug, PartialEq)]
pub enum FilteredBasis {
    F32(Vec<f32>),
    Snorm16(Vec<i16>),
}

impl<'a> Prefiltered<'a> {
    /// `epipoles` are where the sun and anti-sun points appear in the image, if they do:
    /// slices crowd there, so frames sample every pixel around them.
    pub fn build(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
    ) -> Result<Self> {
        let plan = PrefilteredPlan::new(map, camera, epipoles, desc, sun, medium, None)?;
        let basis = plan.prefix.sums_on_cpu(plan.kernels)?;
        plan.finish(basis)
    }

    /// [`Prefiltered::build_with`] on the CPU with every row planned, for tests of the
    /// rows' cut.
    #[cfg(test)]
    pub(crate) fn build_with_every_row(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
        slice_reaches: &[f64],
    ) -> Result<Self> {
        let plan = PrefilteredPlan::with_rows_to(
            map,
            camera,
            epipoles,
            desc,
            sun,
            medium,
            Some(slice_reaches),
            None,
        )?;
        let basis = plan.prefix.sums_on_cpu(plan.kernels)?;
        plan.finish(basis)
    }

    /// What [`Prefiltered::build`] hands its prefix sums, for other backends and tests.
    pub fn prefix_plan(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
    ) -> Result<PrefixPlan> {
        Ok(PrefilteredPlan::new(map, camera, epipoles, desc, sun, medium, None)?.prefix)
    }

    /// [`Prefiltered::build`] with the prefix sums computed by `prefix` (another backend),
    /// each slice's only as far as `slice_reaches` (see [`PrefilteredPlan::new`]).
    #[allow(clippy::too_many_arguments)]
    pub fn build_with(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
        slice_reaches: Option<&[f64]>,
        prefix: &dyn PrefixSums,
    ) -> Result<Self> {
        let plan = PrefilteredPlan::new(map, camera, epipoles, desc, sun, medium, slice_reaches)?;
        Self::from_plan(plan, prefix)
    }

    /// The second half of [`Prefiltered::build_with`]: `plan`'s prefix sums by `prefix`,
    /// checked, and the method that evaluates pixels from them.
    pub fn from_plan(plan: PrefilteredPlan<'a>, prefix: &dyn PrefixSums) -> Result<Self> {
        let basis = prefix.prefix_sums(&plan.prefix)?;
        let expected = plan.prefix.total_rows * plan.prefix.stride;
        let got = match &basis {
            FilteredBasis::F32(values) => values.len(),
            FilteredBasis::Snorm16(values) => values.len(),
        };
        if got != expected {
            return Err(Error::Internal(format!(
                "prefix sums returned {got} values, expected {expected}"
            )));
        }
        plan.finish(basis)
    }
}

/// Computes the filtered basis from a [`PrefixPlan`]: the CPU's kernels or a GPU.
pub trait PrefixSums {
    fn prefix_sums(&self, plan: &PrefixPlan) -> Result<FilteredBasis>;
}

/// The CPU backend's prefix sums.
pub struct CpuPrefixSums;

impl PrefixSums for CpuPrefixSums {
    fn prefix_sums(&self, plan: &PrefixPlan) -> Result<FilteredBasis> {
        plan.sums_on_cpu(Kernels::detect())
    }
}

/// One band's rows in a [`PrefixPlan`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrefixBand {
    /// Its first row (the empty prefix, all zeros) in the filtered basis.
    pub first_row: usize,
    /// Rows including the empty prefix: `rows − 1` rows of samples.
    pub rows: usize,
}

impl PrefixBand {
    /// Where band `index`'s rows start in the plan's per-row arrays (`scales`); its
    /// samples start [`PrefixPlan::samples_per_row`] times farther in the per-sample ones.
    pub fn sample_offset(&self, index: usize) -> usize {
        self.first_row - index
    }
}

/// Everything the weighted prefix sums of the basis read (Eq. 4.8–4.12), laid out for any
/// backend. Band b's row i (k = its sample offset + i) first adds, for each of its
/// `samples_per_row` samples j, `weights[n]` × basis-table row `entries[n]` to a running
/// sum (n = k·`samples_per_row` + j, in order); its output row `first_row + 1 + i` is then
/// that sum × `scales[k]`, stored as `storage` says.
#[derive(Clone, Debug)]
pub struct PrefixPlan {
    pub storage: BasisStorage,
    /// Values per row: 2·(M/2) padded to whole lanes.
    pub stride: usize,
    pub total_rows: usize,
    pub bands: Vec<PrefixBand>,
    pub samples_per_row: usize,
    /// Per sample.
    pub entries: Vec<u32>,
    pub weights: Vec<f32>,
    /// Per row.
    pub scales: Vec<f32>,
    /// The basis table: row e holds the basis at warped key e / TABLE_STEPS.
    pub table: &'static [f32],
}

impl PrefixPlan {
    fn sums_on_cpu(&self, kernels: Kernels) -> Result<FilteredBasis> {
        fn fill<T: BasisValue>(plan: &PrefixPlan, kernels: Kernels, basis: &mut [T]) {
            let row = plan.stride;
            let mut parts = Vec::with_capacity(plan.bands.len());
            let mut rest = basis;
            for (index, band) in plan.bands.iter().enumerate() {
                let (part, tail) = rest.split_at_mut(band.rows * row);
                rest = tail;
                parts.push((index, band, part));
            }
            let per_row = plan.samples_per_row;
            parts.into_par_iter().for_each(|(index, band, part)| {
                let rows = band.sample_offset(index)..band.sample_offset(index) + band.rows - 1;
                let samples = rows.start * per_row..rows.end * per_row;
                part[..row].fill(T::default());
                kernels.prefix_sums(
                    plan.table,
                    &plan.entries[samples.clone()],
                    &plan.weights[samples],
                    &plan.scales[rows],
                    &mut part[row..],
                );
            });
        }
        // `fill` writes every value, so a kept buffer's old values do not matter.
        let values = self.total_rows * self.stride;
        let what = || format!("the filtered basis ({} rows)", self.total_rows);
        Ok(match self.storage {
            BasisStorage::F32 => {
                let mut basis = SPARE_F32_BASIS.try_take(values, what)?;
                fill(self, kernels, &mut basis);
                FilteredBasis::F32(basis)
            }
            BasisStorage::Snorm16 => {
                let mut basis = SPARE_SNORM16_BASIS.try_take(values, what)?;
                fill(self, kernels, &mut basis);
                FilteredBasis::Snorm16(basis)
            }
        })
    }
}

/// How many of a slice's first samples prefiltering reads where the rays that read the
/// slice reach no farther than `reach` along it ([`crate::slice_reach`]), of `map`'s
/// layout: the texels of its warps and the samples of its rows, two a row up to the row
/// after the reach's. (The uniformity table's block past them may take other values:
/// its entries only spare reading samples, which then decide.)
pub fn samples_read(map: &EpipolarMap, reach: f64) -> usize {
    let samples = map.samples as usize;
    let end = map.sample_coordinate(reach).ceil();
    if end.is_nan() || end >= samples as f64 {
        return samples;
    }
    (end.max(0.0) as usize + 2 * SAMPLES_PER_ROW).min(samples)
}

/// A [`Prefiltered`] but for its filtered basis: the planning on the rectified map.
pub struct PrefilteredPlan<'a> {
    map: &'a EpipolarMap,
    prefix: PrefixPlan,
    kernels: Kernels,
    tables: &'static Tables,
    frames: Vec<SliceFrame>,
    slice_bands: Vec<SliceBands>,
    bands: Vec<Band>,
    weight: Vec<f32>,
    rays: RaySettings,
    /// Per slice, the samples its rays read at most (see `slice_reaches`).
    sample_reaches: Option<Vec<usize>>,
}

impl<'a> PrefilteredPlan<'a> {
    /// Everything [`Prefiltered::build`] computes before the prefix sums; backends that
    /// keep the filtered basis to themselves evaluate pixels from this and their own copy.
    /// `slice_reaches`, where given, bound how far along each slice rays read
    /// ([`crate::slice_reach`]): rows past that are not planned, and texels past it take
    /// no part in the warps.
    pub fn new(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
        slice_reaches: Option<&[f64]>,
    ) -> Result<Self> {
        Self::with_rows_to(
            map,
            camera,
            epipoles,
            desc,
            sun,
            medium,
            slice_reaches,
            slice_reaches,
        )
    }

    /// [`PrefilteredPlan::new`] with the warps' texels cut at `slice_reaches` and the rows
    /// at `row_reaches`.
    #[allow(clippy::too_many_arguments)]
    fn with_rows_to(
        map: &'a EpipolarMap,
        camera: &CameraModel,
        epipoles: &[[f64; 2]],
        desc: &PrefilteredDesc,
        sun: &Sun,
        medium: &Medium,
        slice_reaches: Option<&[f64]>,
        row_reaches: Option<&[f64]>,
    ) -> Result<Self> {
        let frequencies = (desc.bases / 2) as usize;
        let row = padded(2 * frequencies);
        let extinction = medium.extinction as f64;
        let light_travel = sun.direction.as_dvec3().normalize();
        let box_medium = BoxMedium::new(&medium.extent, sun);
        // Transmittance weights decay from where a slice's first ray enters the medium
        // (`SliceFrame::medium_start`): counted from the slice's start, they had decayed to
        // rounding where the rays reach a box 15 m off at σ = 0.3, and every ray through it
        // was too imprecise. Tables end where the rays' light stops mattering: past the
        // negligible optical depth, or past the box. Inside a box a ray's stretch is also at
        // most the box's longest chord, however far off the box lies: that, not the reach,
        // is what the bands per octave follow.
        let (reach, stretch) = match &medium.extent {
            Extent::Box { world_from_cube } => {
                let reach = desc
                    .max_distance
                    .min(farthest_in_box(camera, world_from_cube));
                (reach, reach.min(longest_chord(world_from_cube)))
            }
            Extent::Unbounded if extinction > 0.0 => {
                let reach = desc.max_distance.min(NEGLIGIBLE_DEPTH / extinction);
                (reach, reach)
            }
            Extent::Unbounded => (desc.max_distance, desc.max_distance),
        };
        let tables = Tables::get(frequencies);
        // Per slice, the samples up to its reach and the one the reach lies in.
        let sample_reaches: Option<Vec<usize>> = slice_reaches.map(|reaches| {
            reaches
                .iter()
                .map(|&s| {
                    let end = map.sample_coordinate(s).ceil().max(0.0) + 1.0;
                    end.min(map.samples as f64) as usize
                })
                .collect()
        });
        let bands_per_octave = bands_per_octave(extinction, stretch);
        let (frames, warps) = slice_frames(
            map,
            camera,
            epipoles,
            desc.epipole_block,
            box_medium.as_ref(),
            sample_reaches.as_deref(),
            bands_per_octave,
        )?;
        let (slice_bands, bands) = plan_bands(map, &frames, &warps, reach, row_reaches);
        let total_rows = bands.last().map_or(0, |b| b.first_row + b.rows);
        // `plan_slices` writes every value, so kept buffers' old values do not matter.
        let what = || format!("the prefiltered method's plan ({total_rows} rows)");
        let mut weight = SPARE_ROW_WEIGHTS.try_take(total_rows, what)?;
        let rows_total = total_rows - bands.len();
        let mut entries = SPARE_ENTRIES.try_take(rows_total * SAMPLES_PER_ROW, what)?;
        let mut weights = SPARE_SAMPLE_WEIGHTS.try_take(rows_total * SAMPLES_PER_ROW, what)?;
        let mut scales = SPARE_SCALES.try_take(rows_total, what)?;
        let kernels = Kernels::detect();
        plan_slices(
            map,
            kernels,
            &frames,
            &slice_bands,
            &bands,
            extinction,
            &mut entries,
            &mut weights,
            &mut scales,
            &mut weight,
        );
        // Scenes are z-up: light travelling upward comes from below the horizon.
        let light_from_below = light_travel.z > 0.0;
        let prefix = PrefixPlan {
            storage: desc.storage,
            stride: row,
            total_rows,
            bands: bands
                .iter()
                .map(|b| PrefixBand {
                    first_row: b.first_row,
                    rows: b.rows,
                })
                .collect(),
            samples_per_row: SAMPLES_PER_ROW,
            entries,
            weights,
            scales,
            table: &tables.basis,
        };
        Ok(Self {
            map,
            prefix,
            kernels,
            tables,
            frames,
            slice_bands,
            bands,
            weight,
            rays: RaySettings {
                extinction,
                near_plane_correction: desc.near_plane_correction,
                box_medium,
                light_travel,
                frequencies,
                bands_per_octave: bands_per_octave as f64,
                exact_ray_ends: desc
                    .exact_ray_ends
                    .applies(box_medium.is_some(), light_from_below),
                dark_lookup_limit: dark_lookup_limit(
                    box_medium.is_some(),
                    light_from_below,
                    bands_per_octave,
                    desc.dark_frame,
                ),
            },
            sample_reaches,
        })
    }

    /// The method evaluating pixels from the filtered basis `basis`; an error where its
    /// uniformity table's memory cannot be allocated.
    pub fn finish(self, basis: FilteredBasis) -> Result<Prefiltered<'a>> {
        let PrefilteredPlan {
            map,
            prefix,
            kernels,
            tables,
            frames: _,
            slice_bands,
            bands,
            weight,
            rays,
            sample_reaches,
        } = self;
        let row = prefix.stride;
        Ok(Prefiltered {
            map,
            stride: row,
            kernels,
            tables,
            slice_bands,
            bands,
            basis,
            weight,
            rays,
            uniformity: UniformityTable::build(map, sample_reaches.as_deref())?,
        })
    }
}

/// A [`Prefiltered`]'s tables as plain numbers, for backends that evaluate pixels.
pub struct PrefilteredTables<'b> {
    /// Values per basis and coefficient row.
    pub stride: usize,
    /// Per slice: log₂ of its fastest ray's speed.
    pub log2_fastest: Vec<f64>,
    /// Per slice: (first band, band count).
    pub slice_bands: Vec<[u32; 2]>,
    /// Per band: (first row, rows).
    pub bands: Vec<[u32; 2]>,
    /// Per band: its warp's knots.
    pub band_knots: Vec<[f64; KNOTS]>,
    /// Cumulative weight per row.
    pub weight: &'b [f32],
    /// Row e: the coefficients at warped key e / `TABLE_STEPS`.
    pub coefficients: &'static [f32],
    pub near_plane_correction: bool,
    pub exact_ray_ends: bool,
    /// Looked-up visibility below which a ray is declined ([`dark_lookup_limit`]).
    pub dark_lookup_limit: f64,
    /// M/2.
    pub frequencies: usize,
    /// Bands per octave of speed: a ray's place among its slice's bands is this times
    /// log₂ of its slice's fastest speed over its own.
    pub bands_per_octave: f64,
    /// Rectified samples per row: a row boundary's coordinate is the map's sample
    /// coordinate over this.
    pub samples_per_row: usize,
}

/// Quantiles kept per slice, and the tables' resolution over warped keys; see the
/// private constants they equal.
pub const WARP_KNOTS: usize = KNOTS;
pub const COEFFICIENT_STEPS: usize = TABLE_STEPS;
/// Warped keys of a slice's rays lie this far inside [0, 1].
pub const WARP_MARGIN: f64 = RAY_MARGIN;

impl<'a> PrefilteredPlan<'a> {
    /// What the prefix sums read.
    pub fn prefix(&self) -> &PrefixPlan {
        &self.prefix
    }

    /// Everything per-pixel evaluation reads besides the filtered basis.
    pub fn tables(&self) -> PrefilteredTables<'_> {
        PrefilteredTables {
            stride: self.prefix.stride,
            log2_fastest: self.frames.iter().map(|f| f.log2_fastest).collect(),
            slice_bands: self
                .slice_bands
                .iter()
                .map(|b| [b.first, b.count])
                .collect(),
            bands: self
                .bands
                .iter()
                .map(|b| [b.first_row as u32, b.rows as u32])
                .collect(),
            band_knots: self.bands.iter().map(|b| b.warp.knots).collect(),
            weight: &self.weight,
            coefficients: &self.tables.coefficients,
            near_plane_correction: self.rays.near_plane_correction,
            exact_ray_ends: self.rays.exact_ray_ends,
            dark_lookup_limit: self.rays.dark_lookup_limit,
            frequencies: self.rays.frequencies,
            bands_per_octave: self.rays.bands_per_octave,
            samples_per_row: SAMPLES_PER_ROW,
        }
    }
}

impl Drop for Prefiltered<'_> {
    fn drop(&mut self) {
        match std::mem::replace(&mut self.basis, FilteredBasis::F32(Vec::new())) {
            FilteredBasis::F32(values) => SPARE_F32_BASIS.keep(values),
            FilteredBasis::Snorm16(values) => SPARE_SNORM16_BASIS.keep(values),
        }
        SPARE_ROW_WEIGHTS.keep(std::mem::take(&mut self.weight));
    }
}

impl Drop for PrefixPlan {
    fn drop(&mut self) {
        SPARE_ENTRIES.keep(std::mem::take(&mut self.entries));
        SPARE_SAMPLE_WEIGHTS.keep(std::mem::take(&mut self.weights));
        SPARE_SCALES.keep(std::mem::take(&mut self.scales));
    }
}

impl<'a> Prefiltered<'a> {
    pub fn memory_bytes(&self) -> usize {
        let basis = match &self.basis {
            FilteredBasis::F32(values) => std::mem::size_of_val(values.as_slice()),
            FilteredBasis::Snorm16(values) => std::mem::size_of_val(values.as_slice()),
        };
        basis + std::mem::size_of_val(self.weight.as_slice()) + self.uniformity.memory_bytes()
    }

    /// The one or two bands whose references bracket a ray crossing 2^`log2_rate` texels
    /// per unit of t, with their shares (linear in the logarithm of the speed).
    #[inline(always)]
    fn bands_for(&self, slice: u32, log2_rate: f64) -> [(&Band, f64); 2] {
        let range = self.slice_bands[slice as usize];
        let first = range.first as usize;
        let position = band_position(
            range.log2_fastest,
            log2_rate,
            self.rays.bands_per_octave,
            range.count as usize,
        );
        let j = (position as u32 as usize).min(range.count as usize - 1);
        let fraction = position - j as f64;
        let next = (j + 1).min(range.count as usize - 1);
        [
            (&self.bands[first + j], 1.0 - fraction),
            (&self.bands[first + next], fraction),
        ]
    }

    /// `band`'s boundary at continuous position `x`: its lower row in the filtered basis,
    /// and the cumulative weights of that row and the next, each times its share of the
    /// position ([`Band::straddle`]).
    #[inline]
    fn boundary_rows(&self, band: &Band, x: f64) -> (u32, [f64; 2]) {
        let (lower, fraction) = band.straddle(x);
        let row = band.first_row + lower;
        let (w0, w1) = (self.weight[row] as f64, self.weight[row + 1] as f64);
        (row as u32, [(1.0 - fraction) * w0, fraction * w1])
    }

    /// The coefficients of a ray's `key` under `band`'s warp.
    #[inline]
    fn coefficients(&self, band: &Band, key: f64) -> &'static [f32] {
        let z = band.warp.warp(key);
        &self.tables.coefficients[Tables::index(z) * self.stride..][..self.stride]
    }

    /// Each boundary's blended prefix rows dotted with `coefficients`, into `out`
    /// ([`Kernels::boundary_dots`]).
    #[inline]
    fn boundary_dots(&self, coefficients: &[f32], rows: &[(u32, [f32; 2])], out: &mut [f32]) {
        match &self.basis {
            FilteredBasis::F32(stored) => {
                self.kernels.boundary_dots(stored, coefficients, rows, out)
            }
            FilteredBasis::Snorm16(stored) => {
                self.kernels.boundary_dots(stored, coefficients, rows, out)
            }
        }
    }

    /// The reads' blended prefix rows dotted with their coefficients, and the same rows
    /// dotted with `others` instead, in the stored precision
    /// ([`Kernels::blend_dots_twice`]).
    #[inline]
    fn blend_dots_twice(&self, reads: &[BandRead<'_>], others: &[&[f32]]) -> [f64; 2] {
        let dots = match &self.basis {
            FilteredBasis::F32(stored) => self.kernels.blend_dots_twice(stored, reads, others),
            FilteredBasis::Snorm16(stored) => self.kernels.blend_dots_twice(stored, reads, others),
        };
        dots.map(f64::from)
    }

    /// Weighted average visibility between continuous boundary positions `x0 < x1`
    /// (`x0` ≤ 0 is the slice's start), blended over the two slices and the bands that
    /// bracket the ray's speed. Per slice, its bands' prefix rows are blended and dotted
    /// with the coefficients of the ray's key under each band's warp in one kernel call.
    /// A lookup darker than [`dark_lookup_limit`], or decided by its blur
    /// ([`BLURRED_SHARE_LIMIT`]), declines the ray.
    #[inline]
    fn average(&self, located: &RaySlice, key: f64, x0: f64, x1: f64) -> Average {
        match self.uniform_visibility(located, x0, x1) {
            Some(visibility) => Average::Visibility(visibility),
            None => match self.look_up(located, key, x0, x1) {
                (Average::Visibility(visibility), blurred)
                    if visibility < self.rays.dark_lookup_limit
                        || blurred > BLURRED_SHARE_LIMIT =>
                {
                    Average::Imprecise
                }
                (looked_up, _) => looked_up,
            },
        }
    }

    /// [`Prefiltered::average`] from the filtered basis alone, and the share of its weight
    /// on samples about the ray's key ([`BLURRED_SHARE_LIMIT`]; 0 unless a visibility).
    #[inline]
    fn look_up(&self, located: &RaySlice, key: f64, x0: f64, x1: f64) -> (Average, f64) {
        let log2_rate = located.s_per_t.log2();
        let slices = self.map.neighbours(located.slice);
        // Four lanes, both bands of both slices, each step done for all four in turn:
        // the lanes are independent, so their loads and divisions overlap rather than
        // queue one band after another.
        // Not `slices.map(..)`: its closure was called, not inlined, and its bands came back
        // through the stack in halves that wider loads then waited on.
        let [(lower_slice, lower_share), (upper_slice, upper_share)] = slices;
        let lower = (self.bands_for(lower_slice, log2_rate), lower_share);
        let upper = (self.bands_for(upper_slice, log2_rate), upper_share);
        let lanes = [lower.0[0], lower.0[1], upper.0[0], upper.0[1]];
        let slice_shares = [lower.1, lower.1, upper.1, upper.1];
        let bands = lanes.map(|(band, _)| band);
        let parts: [f64; LANES_PER_RAY] =
            std::array::from_fn(|lane| slice_shares[lane] * lanes[lane].1);
        // As slices and bands of no share are skipped.
        let active: [bool; LANES_PER_RAY] =
            std::array::from_fn(|lane| slice_shares[lane] != 0.0 && lanes[lane].1 != 0.0);
        let end = bands.map(|band| self.boundary_rows(band, x1));
        // Boundary 0 is the empty prefix, of no weight.
        let start = (x0 > 0.0).then(|| bands.map(|band| self.boundary_rows(band, x0)));
        let before: [f64; LANES_PER_RAY] = std::array::from_fn(|lane| {
            start.map_or(0.0, |start| start[lane].1[0] + start[lane].1[1])
        });
        let dw: [f64; LANES_PER_RAY] =
            std::array::from_fn(|lane| end[lane].1[0] + end[lane].1[1] - before[lane]);
        for lane in 0..LANES_PER_RAY {
            if !active[lane] {
                continue;
            }
            // First: a stretch past the weights' depth cap holds no weight either.
            if before[lane] > CONDITION_LIMIT * dw[lane] {
                return (Average::Imprecise, 0.0);
            }
            if dw[lane] <= 0.0 {
                return (Average::OffTheMap, 0.0);
            }
        }
        let scale: [f64; LANES_PER_RAY] = std::array::from_fn(|lane| parts[lane] / dw[lane]);
        let mut visibility = 0.0;
        // The share of the stretch's weight whose samples lie about the ray's key, within
        // the window of [`Tables::blur_of`].
        let mut blurred = 0.0;
        // Each read's blur row; `blur_of` writes a row's whole stride, so one zeroing serves
        // both slices.
        let mut blur = [[0.0f32; MAX_STRIDE]; 2];
        for (s, (_, share)) in slices.into_iter().enumerate() {
            if share == 0.0 {
                continue;
            }
            let mut reads = [BandRead {
                rows: [(0, 0.0); 4],
                count: 0,
                coefficients: &[],
            }; 2];
            let mut read_count = 0;
            let mut shares = 0.0;
            for lane in 2 * s..2 * s + 2 {
                if !active[lane] {
                    continue;
                }
                let read = &mut reads[read_count];
                read_count += 1;
                let scale = scale[lane];
                let (row, [lower, upper]) = end[lane];
                read.rows[0] = (row, (scale * lower) as f32);
                read.rows[1] = (row + 1, (scale * upper) as f32);
                read.count = 2;
                if let Some(start) = &start {
                    let (row, [lower, upper]) = start[lane];
                    read.rows[2] = (row, (-scale * lower) as f32);
                    read.rows[3] = (row + 1, (-scale * upper) as f32);
                    read.count = 4;
                }
                shares += parts[lane];
                read.coefficients = self.coefficients(bands[lane], key);
            }
            for (read, blur) in reads.iter().zip(&mut blur).take(read_count) {
                self.tables
                    .blur_of(read.coefficients, &mut blur[..self.stride]);
            }
            let [dot, blur_dot] = self.blend_dots_twice(
                &reads[..read_count],
                &[&blur[0][..self.stride], &blur[1][..self.stride]],
            );
            visibility += (0.5 * shares + dot).clamp(0.0, shares);
            blurred += blur_dot;
        }
        (Average::Visibility(visibility), blurred)
    }

    /// The visibility between continuous boundary positions `x0 < x1` where each slice
    /// the ray reads is lit, or shadowed, over the whole of every sample between them
    /// ([`UniformityTable`]): exact, where the series would leave its residue. `None`
    /// otherwise. Past the map's end counts as lit, as in [`Prefiltered::average`].
    #[inline]
    fn uniform_visibility(&self, located: &RaySlice, x0: f64, x1: f64) -> Option<f64> {
        let samples = self.map.samples as usize;
        let c0 = x0.max(0.0) * SAMPLES_PER_ROW as f64;
        let c1 = x1 * SAMPLES_PER_ROW as f64;
        if !(c0 < c1 && c0 < samples as f64) {
            return None;
        }
        let past_the_end = c1 > samples as f64;
        let (first, last) = (c0 as usize, (c1.ceil() as usize).min(samples) - 1);
        let threshold = located.threshold as f32;
        let mut visibility = 0.0;
        for (slice, share) in self.map.neighbours(located.slice) {
            if share == 0.0 {
                continue;
            }
            match self
                .uniformity
                .uniformity(self.map, slice, threshold, first, last)?
            {
                true => visibility += share,
                false if past_the_end => return None,
                false => {}
            }
        }
        Some(visibility)
    }

    /// [`Prefiltered::look_up`] over each stretch between consecutive `boundaries` (the
    /// first ≤ 0 is the slice's start) into `visibilities`, or the exact visibility for all
    /// where the whole is uniform ([`Prefiltered::uniform_visibility`]): the pieces of a ray
    /// in a box share their boundaries, so each boundary's rows are read and dotted once
    /// per band rather than twice. `None` where a piece is too imprecise
    /// ([`CONDITION_LIMIT`]), where the pieces, weighted by the light `lights` of each,
    /// read darker than [`dark_lookup_limit`], or where the whole is decided by its blur
    /// ([`BLURRED_SHARE_LIMIT`]).
    fn average_pieces(
        &self,
        located: &RaySlice,
        key: f64,
        boundaries: &[f64],
        lights: &[f64],
        visibilities: &mut [f64],
    ) -> Option<()> {
        const MOST: usize = MAX_BOX_PIECES as usize + 1;
        let log2_rate = located.s_per_t.log2();
        let pieces = visibilities.len();
        debug_assert_eq!(boundaries.len(), pieces + 1);
        // A ray lit or shadowed all along is exact, as in `average`. Pieces are not tested
        // one by one: on tree's box that cost 10%, and exact pieces beside looked-up ones
        // read the box under a slotted roof 0.163% off, against 0.057% for the whole ray.
        if let Some(visibility) =
            self.uniform_visibility(located, boundaries[0], boundaries[pieces])
        {
            visibilities.fill(visibility);
            return Some(());
        }
        visibilities.fill(0.0);
        // As in `look_up`, over the whole stretch looked up, each band's blur row in `blur`.
        let mut blurred = 0.0;
        let mut blur = [0.0f32; MAX_STRIDE];
        // Pieces off the map in some band count as lit, as in `average`.
        let mut off_the_map = [false; MOST];
        for (slice, share) in self.map.neighbours(located.slice) {
            if share == 0.0 {
                continue;
            }
            let mut dots = [0.0f64; MOST];
            let mut shares = 0.0;
            for (band, band_share) in self.bands_for(slice, log2_rate) {
                if band_share == 0.0 {
                    continue;
                }
                let coefficients = self.coefficients(band, key);
                // Per boundary: its cumulative weight, and its prefix row dotted with the
                // coefficients and scaled by that weight, all dotted in one kernel call.
                // Boundaries at or before the slice's start, the first few (boundaries
                // rise along the ray), are the empty prefix: (0, 0).
                let mut cumulative = [(0.0f64, 0.0f64); MOST];
                let mut rows = [(0, [0.0; 2]); MOST];
                let first = boundaries.iter().take_while(|x| **x <= 0.0).count();
                for ((x, at), read) in boundaries
                    .iter()
                    .zip(&mut cumulative)
                    .zip(&mut rows)
                    .skip(first)
                {
                    let (row, parts) = self.boundary_rows(band, *x);
                    *read = (row, parts.map(|part| part as f32));
                    at.0 = parts[0] + parts[1];
                }
                let mut row_dots = [0.0f32; MOST];
                let count = boundaries.len();
                self.boundary_dots(coefficients, &rows[first..count], &mut row_dots[first..]);
                for (at, dot) in cumulative.iter_mut().zip(row_dots).skip(first) {
                    at.1 = dot as f64;
                }
                let part = share * band_share;
                // Over the whole stretch, from its first boundary (the empty prefix, of no
                // weight, where that lies at or before the slice's start) to its last.
                self.tables.blur_of(coefficients, &mut blur[..self.stride]);
                let mut ends = [0.0f32; 2];
                self.boundary_dots(&blur[..self.stride], &[rows[0], rows[count - 1]], &mut ends);
                let dw = cumulative[count - 1].0 - cumulative[0].0;
                if dw > 0.0 {
                    blurred += part * (ends[1] - ends[0]) as f64 / dw;
                }
                for k in 0..pieces {
                    // As in `average`, the first band to find a piece off the map or
                    // imprecise decides it.
                    if off_the_map[k] {
                        continue;
                    }
                    let ((w0, d0), (w1, d1)) = (cumulative[k], cumulative[k + 1]);
                    let dw = w1 - w0;
                    if w0 > CONDITION_LIMIT * dw {
                        return None;
                    }
                    if dw <= 0.0 {
                        off_the_map[k] = true;
                        continue;
                    }
                    dots[k] += part * (d1 - d0) / dw;
                }
                shares += part;
            }
            for (visibility, dot) in visibilities.iter_mut().zip(dots) {
                *visibility += (0.5 * shares + dot).clamp(0.0, shares);
            }
        }
        for (visibility, off) in visibilities.iter_mut().zip(off_the_map) {
            if off {
                *visibility = 1.0;
            }
        }
        if blurred > BLURRED_SHARE_LIMIT {
            return None;
        }
        // As in `average`, a ray the lookups read nearly dark is integrated exactly: here
        // its pieces' visibilities weighted by their light.
        let light: f64 = lights.iter().sum();
        let seen: f64 = visibilities.iter().zip(lights).map(|(v, l)| v * l).sum();
        if light > 0.0 && seen < self.rays.dark_lookup_limit * light {
            return None;
        }
        Some(())
    }

    /// The slice with the larger share of a located ray.
    #[inline]
    fn dominant_slice(&self, located: &RaySlice) -> u32 {
        let [(lower, lower_share), (upper, upper_share)] = self.map.neighbours(located.slice);
        if upper_share > lower_share {
            upper
        } else {
            lower
        }
    }

    /// [`Prefiltered::exact_end`] of a ray over [`t_start`, `t_end`] in an open medium,
    /// from where its lookup starts; `None` in a box, whose rays find theirs in
    /// [`Prefiltered::march`] itself, in their last piece.
    #[inline]
    fn exact_end_of(&self, located: &RaySlice, t_start: f64, t_end: f64) -> Option<ExactEnd> {
        if !self.rays.exact_ray_ends || self.rays.box_medium.is_some() || t_end <= t_start {
            return None;
        }
        let from = if self.rays.near_plane_correction {
            t_start
        } else {
            0.0
        };
        let sigma = self.rays.extinction;
        self.exact_end(located, from, t_end, |t0, t1| {
            (-sigma * (t0 - t_start)).exp() * integral_exp(sigma, t1 - t0)
        })
    }

    /// The stretch before a ray's end, after `t_from`, where the samples of its slice (the
    /// one with the larger share) lie within [`EXACT_END_WIDTH`] of the ray's key under its
    /// band's warp, at most [`MAX_EXACT_END_SAMPLES`] back; `None` if the sample under the
    /// end does not. A lookup reads such samples about half lit whichever side they are
    /// on, and a ray closes in on the surface it ends on: a lit one over many texels where
    /// it grazes the ground or runs near the light's direction (tree seen 12° off the
    /// light read 2.2% dark), a shadowed one where the surface is nearly its own occluder.
    /// So the stretch is integrated exactly on the rectified samples, each lit or not at
    /// its centre, and only the rest is looked up.
    fn exact_end(
        &self,
        located: &RaySlice,
        t_from: f64,
        t_end: f64,
        mut lit_light: impl FnMut(f64, f64) -> f64,
    ) -> Option<ExactEnd> {
        let slice = self.dominant_slice(located);
        let [(band, share), (other, other_share)] = self.bands_for(slice, located.s_per_t.log2());
        let band = if other_share > share { other } else { band };
        let row = self.map.row(slice);
        let s_at = |t: f64| located.s_origin + located.s_per_t * t;
        let (s_from, s_end) = (s_at(t_from), s_at(t_end));
        let end = self.map.sample_coordinate(s_end);
        if !(end > 0.0 && end < row.len() as f64) {
            return None;
        }
        let last = end as usize;
        let z = band.warp.warp(self.map.order_key(located.threshold));
        let width = EXACT_END_WIDTH / self.rays.frequencies as f64;
        // Warps clamp to [0, 1], which leaves the range open on a side it reaches past.
        let (upper, lower) = (z + width, z - width);
        let (open_upper, open_lower) = (upper >= 1.0, lower <= 0.0);
        // Most rays' ends are far from closing in: told apart by the end sample's warped
        // key, before the range's ends are unwarped (four divisions, a quarter of this
        // function's samples in perf). The rest test it again in values below, as the
        // scan tests its samples, so that both agree at the range's rounding edges.
        let end_z = band.warp.warp(self.map.order_key(row[last] as f64));
        if !((open_upper || end_z < upper) && (open_lower || end_z > lower)) {
            return None;
        }
        // Keys within the width of the ray's in warped units, as values. Keys fall as
        // values rise. (Not the warp's slope at the ray's key: rays' keys are the knots,
        // where the slope jumps, and which side a ray took differed between f64 and f32.)
        let low = if open_upper {
            f64::NEG_INFINITY
        } else {
            self.map.value_of_key(band.warp.unwarp(upper))
        };
        let high = if open_lower {
            f64::INFINITY
        } else {
            self.map.value_of_key(band.warp.unwarp(lower))
        };
        let near = |value: f32| low < value as f64 && (value as f64) < high;
        if !near(row[last]) {
            return None;
        }
        let first = (self.map.sample_coordinate(s_from).max(0.0) as usize)
            .max(last.saturating_sub(MAX_EXACT_END_SAMPLES - 1))
            .min(last);
        let cut = row[first..last]
            .iter()
            .rposition(|&value| !near(value))
            .map_or(first, |far| first + far + 1);
        let s_cut = self.map.sample_interval(cut).0.max(s_from);
        let t_at = |s: f64| (s - located.s_origin) / located.s_per_t;
        let t_cut = t_at(s_cut);
        let lit = |value: f32| located.threshold <= value as f64;
        let stretch = &row[cut..=last];
        if stretch.iter().all(|&value| lit(value)) {
            return Some(ExactEnd {
                t_cut,
                scattering: None,
            });
        }
        // Runs of lit samples, each integrated in closed form.
        let mut scattering = 0.0;
        let mut run = |s0: f64, s1: f64| scattering += lit_light(t_at(s0), t_at(s1));
        let mut run_start = None;
        for (i, &value) in (cut..).zip(stretch) {
            match (lit(value), run_start) {
                (true, None) => run_start = Some(self.map.sample_interval(i).0.max(s_cut)),
                (false, Some(start)) => {
                    run(start, self.map.sample_interval(i).0);
                    run_start = None;
                }
                _ => {}
            }
        }
        if let Some(start) = run_start {
            run(start, s_end);
        }
        Some(ExactEnd {
            t_cut,
            scattering: Some(scattering),
        })
    }

    /// Integrates one ray over [t_start, t_end]; `None` when the ray runs along the light.
    pub fn march(&self, ray: &Ray, t_start: f64, t_end: f64) -> Option<RaySample> {
        self.march_located(ray, t_start, t_end, self.map.locate(ray).as_ref())
    }

    /// [`Prefiltered::march`] for `count` rays, `ray(i)` giving ray i and its span, into
    /// `out`, bit for bit. Frames shade sparse pixels, whose data is rarely in cache: each
    /// ray is located sixteen rays ahead, and with exact ray ends the rectified sample
    /// under its end prefetched. Prefetching the filtered-basis rows each ray would read,
    /// eight rays ahead, no longer paid once rays lit or shadowed all along were answered
    /// from the uniformity table (83% of torus' shaded rays read no rows): without it,
    /// shading took 3–11% less, open and in box media, and no scene took longer.
    pub fn march_many<'r>(
        &self,
        count: usize,
        ray: impl Fn(usize) -> (&'r Ray, f64, f64),
        out: &mut [Option<RaySample>],
    ) {
        const AHEAD: usize = 16;
        let locate = |i: usize| {
            let (ray, _, t_end) = ray(i);
            let located = self.map.locate(ray);
            if let (Some(located), true) = (&located, self.rays.exact_ray_ends) {
                self.prefetch_end_sample(located, t_end);
            }
            located
        };
        let mut located: [Option<RaySlice>; AHEAD] =
            std::array::from_fn(|i| if i < count { locate(i) } else { None });
        // Each ray is marched from its place in the ring, which was written long before:
        // a copy taken just before the call was still in the store buffer when the march
        // read it, in halves too narrow for its loads.
        for (i, out) in out.iter_mut().enumerate().take(count) {
            let slot = i % AHEAD;
            let (ray, t_start, t_end) = ray(i);
            *out = self.march_located(ray, t_start, t_end, located[slot].as_ref());
            if i + AHEAD < count {
                located[slot] = locate(i + AHEAD);
            }
        }
    }

    /// Asks the CPU to fetch the rectified sample a ray ending at `t_end` ends on, which
    /// [`Prefiltered::exact_end`] reads first.
    #[inline]
    fn prefetch_end_sample(&self, located: &RaySlice, t_end: f64) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let row = self.map.row(self.dominant_slice(located));
            let end = self
                .map
                .sample_coordinate(located.s_origin + located.s_per_t * t_end);
            if end > 0.0 && end < row.len() as f64 {
                // SAFETY: prefetching is only a hint, and never faults.
                unsafe {
                    _mm_prefetch::<_MM_HINT_T0>(row.as_ptr().wrapping_add(end as usize).cast())
                };
            }
        }
    }

    /// [`Prefiltered::march`] with the ray already located (`None`: along the light).
    fn march_located(
        &self,
        ray: &Ray,
        t_start: f64,
        t_end: f64,
        located: Option<&RaySlice>,
    ) -> Option<RaySample> {
        let located = located?;
        if t_end <= t_start {
            return Some(RaySample::EMPTY);
        }
        if self.map.is_short(located, t_start, t_end) {
            return None;
        }
        if is_along_the_light(ray.direction, self.rays.light_travel) {
            return None;
        }
        let key = self.map.order_key(located.threshold);
        let x = |t: f64| row_coordinate(self.map, located.s_origin + located.s_per_t * t);
        let sigma = self.rays.extinction;
        let Some((a, b)) = medium_segment(self.rays.box_medium.as_ref(), ray, t_start, t_end)
        else {
            // Off the map (shorter than a sample) counts as lit, like the other methods.
            let visibility = self.average(located, key, x(t_start), x(t_end)).value()?;
            return Some(RaySample {
                visibility,
                ..RaySample::EMPTY
            });
        };
        if self.map.is_short_in_medium(located, a, b, sigma) {
            return None;
        }
        // Rays start at the slice's origin; what lies before the medium is subtracted when
        // asked to, where the medium begins later than the near clip plane, and in a box
        // always: there the stretch would be averaged into the ray's first piece rather
        // than the whole ray (a camera inside a box, its clip 1 m out, read 43% bright),
        // and subtracting it costs a row read, not a lookup.
        let from =
            if self.rays.near_plane_correction || a > t_start || self.rays.box_medium.is_some() {
                a
            } else {
                0.0
            };
        let alpha = -(-sigma * (b - a)).exp_m1();
        let Some(box_medium) = &self.rays.box_medium else {
            let unshadowed = if sigma * (b - a) >= 1e-8 {
                alpha / sigma
            } else {
                integral_exp(sigma, b - a)
            };
            let Some(end) = self.exact_end_of(located, t_start, t_end) else {
                let visibility = self.average(located, key, x(from), x(b)).value()?;
                return Some(RaySample {
                    scattering: visibility * unshadowed,
                    alpha,
                    visibility,
                });
            };
            // The end is integrated exactly, the rest looked up: unless that rest
            // is too short for a lookup of its own.
            if end.t_cut <= a || self.map.is_short_stretch(located, from, end.t_cut) {
                return None;
            }
            let visibility = self.average(located, key, x(from), x(end.t_cut)).value()?;
            let before = integral_exp(sigma, end.t_cut - a);
            let after = end.scattering.unwrap_or(unshadowed - before);
            let scattering = visibility * before + after;
            return Some(RaySample {
                scattering,
                alpha,
                visibility: weighted_visibility(scattering, unshadowed).unwrap_or(visibility),
            });
        };
        // The sunlight's attenuation inside the box varies along the ray, and where it
        // correlates with visibility (light entering through an opening, dimmer farther
        // in) one average visibility times the unshadowed integral is off by 10% and more.
        // So the stretch is cut into pieces, each its own average times its own integral.
        // Each piece is its own lookup, and one crossing too few texels reads the smooth
        // step around keys it cannot resolve: a short stretch of box in a long view ray
        // (looking up out of a fog layer towards the sun) read 35% too dark.
        let along = box_medium.along(ray);
        let sunward_change = sigma * along.sunward_change(a, b);
        let sunward_pieces = box_pieces(sunward_change, 0.0);
        let mut pieces = box_pieces(sunward_change, sigma * (b - a));
        // Pieces for the view ray's depth alone refine what one lookup would read; where
        // they would be too short for lookups of their own, the sunlight's are enough.
        let short = |pieces: u32| {
            self.map
                .is_short_stretch(located, a, a + (b - a) / pieces as f64)
        };
        let mut too_short = short(pieces);
        if too_short && pieces > sunward_pieces {
            pieces = sunward_pieces;
            too_short = short(pieces);
        }
        if too_short {
            return None;
        }
        let t_at = |k: u32| a + (b - a) * k as f64 / pieces as f64;
        let start_of = |k: u32| if k == 0 { from } else { t_at(k) };
        // A ray that ends on a surface inside the box may close in on it in its last piece
        // ([`Prefiltered::exact_end`]): that piece is then looked up only to the cut, or
        // not at all.
        let last = pieces - 1;
        let end = if self.rays.exact_ray_ends && b >= t_end {
            self.exact_end(located, start_of(last), b, |t0, t1| {
                along.integrate(t0, t1, a, sigma)
            })
        } else {
            None
        };
        let (looked_up, last_end) = match &end {
            None => (pieces, t_at(pieces)),
            Some(end) if end.t_cut <= t_at(last) => {
                if last == 0 {
                    return None;
                }
                (last, t_at(last))
            }
            Some(end) => {
                if self
                    .map
                    .is_short_stretch(located, start_of(last), end.t_cut)
                {
                    return None;
                }
                (pieces, end.t_cut)
            }
        };
        let end_of = |k: u32| if k == last { last_end } else { t_at(k + 1) };
        let mut boundaries = [0.0; MAX_BOX_PIECES as usize + 1];
        for (k, boundary) in boundaries[..=looked_up as usize].iter_mut().enumerate() {
            *boundary = x(if k == 0 { from } else { end_of(k as u32 - 1) });
        }
        let mut visibilities = [0.0; MAX_BOX_PIECES as usize];
        let visibilities = &mut visibilities[..looked_up as usize];
        // Each piece's unshadowed light, and the part of it that is looked up.
        let mut piece_light = [0.0; MAX_BOX_PIECES as usize];
        let mut looked_up_light = [0.0; MAX_BOX_PIECES as usize];
        for k in 0..pieces {
            let piece = along.integrate(t_at(k), t_at(k + 1), a, sigma);
            piece_light[k as usize] = piece;
            looked_up_light[k as usize] = if end.is_some() && k == last {
                along.integrate(t_at(k), last_end, a, sigma)
            } else {
                piece
            };
        }
        self.average_pieces(
            located,
            key,
            &boundaries[..=looked_up as usize],
            &looked_up_light[..looked_up as usize],
            visibilities,
        )?;
        let (mut scattering, mut unshadowed) = (0.0, 0.0);
        for k in 0..pieces as usize {
            unshadowed += piece_light[k];
            if let Some(visibility) = visibilities.get(k) {
                scattering += visibility * looked_up_light[k];
            }
        }
        if let Some(end) = end {
            scattering += end
                .scattering
                .unwrap_or_else(|| along.integrate(end.t_cut, b, a, sigma));
        }
        Some(RaySample {
            scattering,
            alpha,
            visibility: weighted_visibility(scattering, unshadowed).unwrap_or(1.0),
        })
    }
}

/// Half-width, in warped keys times M/2, within which samples count as closing in on a
/// ray's key (`Prefiltered::exact_end`): the damped step is within 5% of 0 or 1 from
/// 0.37 on. On the test views 0.25 kept 90% of the gain in accuracy, and 0.5 or 1.0 gained
/// no more than 0.35.
pub const EXACT_END_WIDTH: f64 = 0.35;

/// Half-width, in warped keys, of the window about a ray's key over which a lookup's blur
/// is measured ([`BLURRED_SHARE_LIMIT`]): [`EXACT_END_WIDTH`] at the default M = 32, and
/// the same at every M, so that a lower M still trades accuracy for time (with a window
/// as wide as each M's own step, M = 8 walked so many rays that it came closer to the
/// reference than M = 32).
pub const BLUR_WIDTH: f64 = EXACT_END_WIDTH / 16.0;

/// Share of a lookup's weight lying within [`BLUR_WIDTH`] of the ray's key above which
/// the ray is declined and integrated exactly: found as how much the looked-up visibility
/// changes between the keys that far either side, from the ray's coefficient row and the
/// same blended rows in the same kernel call ([`Kernels::blend_dots_twice`]). Such
/// samples are read by the series' smooth step rather than by their order, each up to
/// half wrong, and where they are a good part of the stretch the step decides the
/// answer: occluders extruded along the view rays (silhouette dilation) keep rays just
/// past them within a texel's depth of their key all along, and an orthographic view of
/// `plane` so styled, in a thin fog box, read 8.1% dark (0.16% with this; min-max
/// 0.41%). On the test views it lowered the error at M = 32 by up to 0.3
/// points (`plane` orthographic 0.78% → 0.46%) and declined no ray of the built-in
/// scenes' default views at 1080p but 964 of `colonnade`'s.
pub const BLURRED_SHARE_LIMIT: f64 = 0.1;

/// Most samples back from a ray's end integrated exactly (32 texels): a bound on the cost
/// of a ray that closes in on a surface over hundreds of texels. 32 samples kept about a
/// sixth less of the gain on `plane`'s default view; no bound, a little more.
pub const MAX_EXACT_END_SAMPLES: usize = 64;

/// Where a ray's exact end starts, and its in-scattering exact on the rectified samples
/// (its lit runs weighed as the caller's medium weighs them); `None` where every sample of
/// it is lit.
#[derive(Clone, Copy, Debug)]
struct ExactEnd {
    t_cut: f64,
    scattering: Option<f64>,
}

/// Sine of the widest angle between a ray and the light's travel at which the ray is
/// integrated exactly instead ([`is_along_the_light`]): about 8.6°.
pub const ALONG_THE_LIGHT_SIN: f64 = 0.15;

/// Whether a ray runs within [`ALONG_THE_LIGHT_SIN`] of the light's own direction. Such
/// a ray closes in on the surface it ends on over many texels in key, and the smooth
/// step reads about half along all of them: an orthographic view 6.7° off the light, the
/// sun behind the camera, read fully lit rays at 0.81–0.95 (9.2% off). The exact walk
/// costs texels crossed, which is what these rays cross fewest of. Rays towards the
/// light end on surfaces lit from behind them, whose keys are an object's thickness away.
#[inline]
pub fn is_along_the_light(direction: DVec3, light_travel: DVec3) -> bool {
    let cos = direction.dot(light_travel);
    cos > 0.0 && 1.0 - cos * cos < ALONG_THE_LIGHT_SIN * ALONG_THE_LIGHT_SIN
}

/// Largest ratio of the weight before a ray to the weight along it. Past it the ray
/// starts where its bands' transmittance weights have decayed: differences of stored
/// prefix sums there are mostly snorm16 rounding, and past the weights' depth cap
/// (`MAX_REFERENCE_DEPTH`) there are none. An orthographic camera's rays start all along
/// their slices, and in a dense medium (σ = 0.6 /m) a limit of 10³ left colonnade 17%
/// off, 10² took it to 0.3%, and 10 walked so many rays that the frame took 5× as long.
pub const CONDITION_LIMIT: f64 = 100.0;

/// Looked-up visibility below which the ray is declined and integrated exactly instead,
/// where [`dark_lookup_limit`] applies. The series' residue is about 0.005 of visibility
/// wherever a ray crosses shadows, so a ray that reads darker than this is mostly residue:
/// from under a slotted roof in fog of 0.6 /m, looking level towards the sun, rays whose
/// shafts let through 0.02–0.3% of the light read 0.5% and the frame was 36% off the
/// reference (1.5% with this; 3.0% at 0.01, which also left a roof closed by a silhouette
/// in fog of 0.2 /m 9.2% off rather than 2.6%). Ray-wide uniform stretches are answered
/// exactly before any lookup, so rays in full shadow are not walked. In a `box` the
/// looked-up pieces' visibilities weighted by their light are tested: a nearly dark view
/// of `plane` in a fog box read 3.5% off, 0.4% with this, and the built-in scenes'
/// fog-box frames took 0–7% longer; in open fog of 0.2–0.6 /m `plane` took 15–40% longer
/// (`bench --extinction 0.6`: 56 → 74–77 ms), the other scenes as long.
pub const DARK_LOOKUP_VISIBILITY: f64 = 0.02;

/// [`DARK_LOOKUP_VISIBILITY`] where frames tend to be dark, 0 (no ray declined for its
/// darkness) elsewhere: in a `box`, under light from below (the ground then shadows most
/// rays), and in fog dense enough for more than one band an octave, whose light comes from
/// a few optical depths near the camera, where a roof or a crown shadows most of it; and
/// in a `dark_frame`, nearly all of whose light is that faint. In thin open media dark
/// rays are otherwise a few among lit ones, and walking them bought little: the built-in
/// scenes' default views, whose errors moved by 0 to −0.26 points, took 8% (`plane`, 7,200
/// rays walked at 1080p) and 10% (`colonnade`, 23,000) longer.
pub fn dark_lookup_limit(
    box_medium: bool,
    light_from_below: bool,
    bands_per_octave: u32,
    dark_frame: bool,
) -> f64 {
    if box_medium || light_from_below || bands_per_octave > 1 || dark_frame {
        DARK_LOOKUP_VISIBILITY
    } else {
        0.0
    }
}

/// What [`Prefiltered::average`] makes of a stretch of a ray.
enum Average {
    Visibility(f64),
    /// A band holds no weight there nor before: off the map, or shorter than a sample.
    /// Counted as lit, like the other methods.
    OffTheMap,
    /// Too far along the slice for the stored prefix sums' precision
    /// ([`CONDITION_LIMIT`]), too dark for the series ([`DARK_LOOKUP_VISIBILITY`]), or
    /// decided by its blur ([`BLURRED_SHARE_LIMIT`]): the ray is declined and integrated
    /// exactly.
    Imprecise,
}

impl Average {
    /// The visibility, or `None` where the ray must be marched instead.
    fn value(self) -> Option<f64> {
        match self {
            Average::Visibility(visibility) => Some(visibility),
            Average::OffTheMap => Some(1.0),
            Average::Imprecise => None,
        }
    }
}

/// How much the sunlight's optical depth through the box may change within one piece of
/// a ray inside a `box` medium (see [`Prefiltered::march`]). Within a piece that
/// attenuation is taken as even, which is off by the first order in its change where
/// visibility correlates with it; the view ray's own transmittance is in the filtering
/// weights. In a box of fog under a slotted roof: 0.66% off at 0.1, 0.14% at 0.05 (pieces
/// of 0.1 of the view ray's optical depth, as before, 0.30%). A ray across plane's deep
/// fog box with the sun overhead needs one piece where it took twenty.
pub const BOX_PIECE_DEPTH: f64 = 0.05;
/// The view ray's own optical depth in one piece of a ray inside a `box` medium. One
/// lookup over a long stretch of box reads each filtering weight where the slice's
/// reference ray has it, farther off the ray's own the deeper the stretch: under a sun
/// that the box does not dim (one piece by the sunlight) the slotted roof's box read 0.81%
/// off in one piece, 0.37% in pieces of 1, 0.21% of 0.5 and 0.15% of 0.1; open fog there
/// reads 0.24%. Boxes whose sunlight changes enough are cut finer anyway.
pub const BOX_PIECE_VIEW_DEPTH: f64 = 0.5;
/// Most pieces a ray inside a `box` medium is cut into.
pub const MAX_BOX_PIECES: u32 = 20;

/// Pieces for a stretch inside a `box` medium along which the sunlight's optical depth
/// through the box changes by `sunward_change` in all, and whose own optical depth is
/// `view_depth`.
#[inline]
pub fn box_pieces(sunward_change: f64, view_depth: f64) -> u32 {
    let sunward = (sunward_change / BOX_PIECE_DEPTH).ceil();
    let view = (view_depth / BOX_PIECE_VIEW_DEPTH).ceil();
    (sunward.max(view) as u32).clamp(1, MAX_BOX_PIECES)
}

/// Lays out every slice's bands: how many, their references, and how far each table
/// reaches. A band's table ends where its fastest ray's weight has become negligible or
/// the ray can go no farther, whichever comes first; the fastest band spans the slice.
/// `warps` holds each slice's band warps ([`band_warps`]).
fn plan_bands(
    map: &EpipolarMap,
    frames: &[SliceFrame],
    warps: &[Vec<Warp>],
    reach_t: f64,
    slice_reaches: Option<&[f64]>,
) -> (Vec<SliceBands>, Vec<Band>) {
    let map_rows = row_count(map);
    // Rows up to position s: the row it lies in and the next, which boundaries blend;
    // every row for s = ∞ (or NaN).
    let rows_to =
        |s: f64| (row_coordinate(map, s).ceil().max(0.0) + 1.0).min(map_rows as f64) as usize;
    let mut slice_bands = Vec::with_capacity(frames.len());
    let mut bands = Vec::new();
    let mut next_row = 0;
    for (slice, (frame, warps)) in frames.iter().zip(warps).enumerate() {
        // Every band keeps a row of samples besides the empty prefix.
        let rows = slice_reaches.map_or(map_rows, |reaches| rows_to(reaches[slice]).max(1));
        let count = frame.band_count();
        slice_bands.push(SliceBands {
            first: bands.len() as u32,
            count: count as u32,
            log2_fastest: frame.log2_fastest,
        });
        debug_assert_eq!(warps.len(), count);
        for (j, &warp) in warps.iter().enumerate() {
            let rate = frame.band_rate(j);
            // Rays read band j only while slower than band j − 1's reference.
            let fastest = frame.band_rate(j.saturating_sub(1));
            let used = if j == 0 {
                rows
            } else {
                rows_to(frame.origin + fastest * reach_t).min(rows)
            };
            bands.push(Band {
                rate,
                warp,
                first_row: next_row,
                rows: used + 1,
            });
            next_row += used + 1;
        }
    }
    (slice_bands, bands)
}

/// The farthest along its ray any camera ray can be inside the box: a perspective
/// camera's rays start at its position, an orthographic camera's on its view plane.
fn farthest_in_box(camera: &CameraModel, world_from_cube: &Mat4) -> f64 {
    let world_from_cube = world_from_cube.as_dmat4();
    let position = camera.position();
    let forward = camera
        .world_from_camera
        .transform_vector3(DVec3::NEG_Z)
        .normalize();
    (0..8)
        .map(|corner| {
            let sign = |bit: u32| if corner & bit == 0 { -1.0 } else { 1.0 };
            let corner = world_from_cube.transform_point3(DVec3::new(sign(1), sign(2), sign(4)));
            if camera.is_perspective() {
                corner.distance(position)
            } else {
                (corner - position).dot(forward)
            }
        })
        .fold(0.0, f64::max)
}

/// The longest straight stretch inside the box `world_from_cube` maps the cube [−1, 1]³
/// to: its longest diagonal.
fn longest_chord(world_from_cube: &Mat4) -> f64 {
    let world_from_cube = world_from_cube.as_dmat4();
    [
        DVec3::new(2.0, 2.0, 2.0),
        DVec3::new(-2.0, 2.0, 2.0),
        DVec3::new(2.0, -2.0, 2.0),
        DVec3::new(2.0, 2.0, -2.0),
    ]
    .into_iter()
    .map(|diagonal| world_from_cube.transform_vector3(diagonal).length())
    .fold(0.0, f64::max)
}

/// Fewest sampled rays that give a band its own warp; a band with fewer keeps its
/// slice's.
const MIN_BAND_RAYS: usize = 2 * KNOTS;

/// Per band of `frame`, the warp of the sampled rays that read it (see [`Band::warp`])
/// and of the texels among them; bands read by too few rays keep the slice's warp.
/// `texels` are sorted by key.
fn band_warps(frame: &SliceFrame, rays: &SortedRays, texels: &[f64]) -> Vec<Warp> {
    let count = frame.band_count();
    let mut warps = vec![frame.warp; count];
    if count < 2 || rays.keys.len() < MIN_BAND_RAYS {
        return warps;
    }
    // Rays come sorted by key, so each band's keys do too.
    let mut reading: Vec<Vec<f64>> = (0..count)
        .map(|_| Vec::with_capacity(rays.keys.len()))
        .collect();
    for (&key, &log2_rate) in rays.keys.iter().zip(&rays.log2_rates) {
        let position = frame.band_position(log2_rate, count);
        let lower = position as usize;
        reading[lower].push(key);
        if lower + 1 < count && position > lower as f64 {
            reading[lower + 1].push(key);
        }
    }
    let (lowest, highest) = (rays.keys[0], rays.keys[rays.keys.len() - 1]);
    for (warp, keys) in warps.iter_mut().zip(&reading) {
        if keys.len() >= MIN_BAND_RAYS {
            *warp = Warp::of(keys, texels).spanning(lowest, highest);
        }
    }
    warps
}

/// One key per texel of a slice (enough for quantiles), sorted: those strictly between
/// `lowest` and `highest`, the slice's ray keys, which are all that its warps read
/// ([`Warp::of`]). On the built-in scenes that is from a half (torus, plane) to an eighth
/// (colonnade) of them, and sorting only those took 1–2 ms off a frame's preparation.
/// Only samples before `reach` count: no ray reads past it ([`crate::slice_reach`]), and
/// texels there took quantiles from those the rays read (colonnade's default view 1.14%
/// off the reference at M = 32 with them, 1.12% without; plane's 1.91%, 1.87%).
fn texel_keys(
    map: &EpipolarMap,
    slice: usize,
    lowest: f64,
    highest: f64,
    reach: usize,
) -> Vec<f64> {
    let row = map.row(slice as u32);
    let row = &row[..reach.min(row.len())];
    let mut keys = vec![0u64; row.len().div_ceil(SAMPLES_PER_ROW)];
    // Every key is written and only those in range are kept, without a branch on which:
    // keys in and out of range alternate unpredictably along a slice.
    let mut kept = 0;
    for &value in row.iter().step_by(SAMPLES_PER_ROW) {
        let key = map.order_key(value as f64);
        keys[kept] = total_order_bits(key);
        kept += usize::from(key > lowest && key < highest);
    }
    keys.truncate(kept);
    keys.sort_unstable();
    keys.into_iter().map(from_total_order_bits).collect()
}

/// Fills every band's per-sample inputs of the prefix sums, its per-row scales and the
/// cumulative weights, in parallel over slices. A slice's bands are contiguous, in rows
/// and in samples.
#[allow(clippy::too_many_arguments)]
fn plan_slices(
    map: &EpipolarMap,
    kernels: Kernels,
    frames: &[SliceFrame],
    slice_bands: &[SliceBands],
    bands: &[Band],
    extinction: f64,
    entries: &mut [u32],
    weights: &mut [f32],
    scales: &mut [f32],
    weight: &mut [f32],
) {
    let mut parts = Vec::with_capacity(frames.len());
    let (mut entries_rest, mut weights_rest, mut scales_rest, mut weight_rest) =
        (entries, weights, scales, weight);
    for (slice, range) in slice_bands.iter().enumerate() {
        let own = &bands[range.first as usize..(range.first + range.count) as usize];
        let rows: usize = own.iter().map(|b| b.rows).sum();
        let filled = rows - own.len();
        let sampled = filled * SAMPLES_PER_ROW;
        let (entries_part, e_rest) = entries_rest.split_at_mut(sampled);
        let (weights_part, w_rest) = weights_rest.split_at_mut(sampled);
        let (scales_part, s_rest) = scales_rest.split_at_mut(filled);
        let (weight_part, t_rest) = weight_rest.split_at_mut(rows);
        (entries_rest, weights_rest, scales_rest, weight_rest) = (e_rest, w_rest, s_rest, t_rest);
        parts.push((
            slice,
            own,
            entries_part,
            weights_part,
            scales_part,
            weight_part,
        ));
    }
    parts.into_par_iter().for_each(
        |(slice, own, entries_part, weights_part, scales_part, weight_part)| {
            let frame = &frames[slice];
            // Keys as far as the slice's longest band reads: past its reach a slice's
            // samples are planned for no band.
            let read = own
                .iter()
                .map(|band| (band.rows - 1) * SAMPLES_PER_ROW)
                .max();
            let samples = map.row(slice as u32);
            let keys = map.order_keys(&samples[..read.unwrap_or(0).min(samples.len())]);
            let (mut sample, mut row, mut filled) = (0, 0, 0);
            for band in own {
                let count = (band.rows - 1) * SAMPLES_PER_ROW;
                // A last row that the map's samples do not fill takes empty samples (of
                // zero weight, reading table row 0).
                let band_entries = &mut entries_part[sample..sample + count];
                band.warp.table_indices(kernels, &keys, band_entries);
                band_entries[keys.len().min(count)..].fill(0);
                band_weights(
                    map,
                    frame.medium_start.unwrap_or(frame.origin),
                    band.rate,
                    if frame.medium_start.is_some() {
                        extinction
                    } else {
                        0.0
                    },
                    &mut weights_part[sample..sample + count],
                    &mut scales_part[filled..filled + band.rows - 1],
                    &mut weight_part[row..row + band.rows],
                );
                sample += count;
                filled += band.rows - 1;
                row += band.rows;
            }
        },
    );
}

/// One band's sample weights, the scales that normalize its prefix sums per row, and its
/// cumulative weight per row boundary (boundary 0 is empty, boundary r + 1 follows row
/// r). Weights are the reference ray's transmittance integral over each sample,
/// ∫ σ e^(−σt) dt, which is uniform as σ → 0; samples past the map's end weigh nothing.
fn band_weights(
    map: &EpipolarMap,
    origin: f64,
    rate: f64,
    extinction: f64,
    weights: &mut [f32],
    scales: &mut [f32],
    weight: &mut [f32],
) {
    weight[0] = 0.0;
    let samples = map.samples as usize;
    // No sample lies before the map's first: weights decaying from there instead of from
    // an origin before it are all scaled alike, which lookups divide out, and the first
    // samples never lie past the depth cap, where samples weigh nothing.
    let origin = origin.max(map.sample_interval(0).0);
    let depth_of = |s: f64| (extinction * ((s - origin) / rate).max(0.0)).min(MAX_REFERENCE_DEPTH);
    // Before the origin, every sample keeps the weight it would have at the cap.
    let flat_per_s = (-MAX_REFERENCE_DEPTH).exp() * extinction / rate;
    // Between the origin and the depth cap, evenly spaced samples each multiply the
    // transmittance by the same factor: one exp per band rather than one per sample.
    // Others (a projective map's) take each sample's own interval: the cross-ratio weights.
    let step_factor = map
        .uniform_step()
        .map(|step| (-extinction * step / rate).exp());
    let unclamped = |s: f64| extinction * (s - origin) / rate;
    // The samples whose transmittance is the previous one's times `step_factor`: those
    // from the origin to the depth cap. With s rising along the samples both bounds are
    // monotone, so bisection finds the run once, rather than two divisions per sample.
    let stepped = match map.uniform_step() {
        Some(step) if extinction > 0.0 && step >= 0.0 => {
            let s = |i: usize| map.sample_interval(i).0;
            let start = first_failing(samples, |i| {
                let depth = unclamped(s(i));
                depth < 0.0 || depth.is_nan()
            });
            let end = first_failing(samples, |i| unclamped(s(i + 1)) <= MAX_REFERENCE_DEPTH);
            start..end.max(start)
        }
        _ => 0..0,
    };
    // Before the origin and past the cap the depth is clamped: no exp there.
    let capped = (-MAX_REFERENCE_DEPTH).exp();
    let transmittance = |s: f64| {
        let depth = depth_of(s);
        if depth == 0.0 {
            1.0
        } else if depth == MAX_REFERENCE_DEPTH {
            capped
        } else {
            (-depth).exp()
        }
    };
    debug_assert_eq!(weights.len(), scales.len() * SAMPLES_PER_ROW);
    // Sample i's weight between the transmittance `before` it and `after` it, which then
    // becomes `before`; where the transmittance no longer falls across it, by its length
    // before the origin, and none past the depth cap. A sample's interval is found anew
    // rather than carried from the one before: both are `sample_interval`'s same
    // arithmetic.
    let fall = |i: usize, before: &mut f64, after: f64| {
        let w = if after < *before {
            *before - after
        } else {
            let (s0, s1) = map.sample_interval(i);
            if depth_of(s0) < MAX_REFERENCE_DEPTH {
                flat_per_s * (s1 - s0)
            } else {
                0.0
            }
        };
        *before = after;
        w
    };
    // Sample i's weight, anywhere in the map or past its end.
    let weigh = |i: usize, before: &mut f64| {
        if i >= samples {
            0.0
        } else if extinction > 0.0 {
            let after = match step_factor {
                Some(factor) if stepped.contains(&i) => *before * factor,
                _ => transmittance(map.sample_interval(i).1),
            };
            fall(i, before, after)
        } else {
            1.0
        }
    };
    let factor = step_factor.unwrap_or(1.0);
    let mut total = 0.0f64;
    let mut before = transmittance(map.sample_interval(0).0);
    for (row, ((weights, scale), cumulative)) in weights
        .chunks_exact_mut(SAMPLES_PER_ROW)
        .zip(scales.iter_mut())
        .zip(&mut weight[1..])
        .enumerate()
    {
        let first = row * SAMPLES_PER_ROW;
        if stepped.start <= first && first + SAMPLES_PER_ROW <= stepped.end {
            // The whole row in the stepped run: `weigh`'s arithmetic there without its
            // tests, whose instructions bounded the loop more than its chains did.
            for (k, w32) in weights.iter_mut().enumerate() {
                let after = before * factor;
                let w = fall(first + k, &mut before, after);
                *w32 = w as f32;
                total += w;
            }
        } else {
            for (k, w32) in weights.iter_mut().enumerate() {
                let w = weigh(first + k, &mut before);
                *w32 = w as f32;
                total += w;
            }
        }
        *scale = (1.0 / total) as f32;
        *cumulative = total as f32;
    }
}

/// The first of `0..len` where `holds` fails, given that it holds up to some index and
/// fails from there on.
fn first_failing(len: usize, holds: impl Fn(usize) -> bool) -> usize {
    let (mut low, mut high) = (0, len);
    while low < high {
        let middle = low + (high - low) / 2;
        if holds(middle) {
            low = middle + 1;
        } else {
            high = middle;
        }
    }
    low
}

/// Rays sampled for the slices' frames, each with the two slices it belongs to.
type SampledRays = Vec<([u32; 2], SampledRay)>;

/// One ray sampled for a slice's frame.
#[derive(Clone, Copy)]
struct SampledRay {
    key: f64,
    rate: f64,
    origin: f64,
    /// Where along the slice the ray enters the medium, if it does.
    medium_entry: Option<f64>,
}

/// Per slice, key quantiles and ray speeds, from the rays of the image's border (where
/// each slice's extreme rays are, with the epipoles), a regular grid of pixels inside
/// dense enough for about `RAYS_PER_SLICE` rays per slice (the quantiles need no more),
/// and a denser grid near an epipole, where slices are closer than two pixels
/// ([`sampled_columns`]), but none in the block around it that is ray-marched instead.
/// Slices that no sampled ray touches take their nearest sampled neighbour's frame.
fn slice_frames(
    map: &EpipolarMap,
    camera: &CameraModel,
    epipoles: &[[f64; 2]],
    block: f64,
    box_medium: Option<&BoxMedium>,
    sample_reaches: Option<&[usize]>,
    bands_per_octave: u32,
) -> Result<(Vec<SliceFrame>, Vec<Vec<Warp>>)> {
    // 128 took a third longer (colonnade's frames 15 → 11 ms, tree's 6.4 → 4.8 at 1080p)
    // for errors against the reference 0–0.04 points lower on twelve 1080p views; 32 cost
    // plane's default view another 0.12 points.
    const RAYS_PER_SLICE: f64 = 64.0;
    let pixels = camera.width as f64 * camera.height as f64;
    // The nearest stride, not the next smaller: truncated, 1080p frames sampled up to 1.8×
    // the rays (colonnade's stride 3.98 became 3), which cost 2–5 ms of preparation and
    // moved no error by more than 0.005 points.
    let ideal = (pixels / (map.slices as f64 * RAYS_PER_SLICE)).sqrt();
    let interior_stride = (ideal.round() as u32).max(1);
    let (w, h) = (camera.width, camera.height);
    // Slices 2 px apart: at distance r from the epipole they are 2π·r/slices apart.
    let dense_radius = 2.0 * map.slices as f64 / std::f64::consts::TAU;
    // A sampled ray, with its slice coordinate and the two slices it belongs to.
    let sample = |x: f64, y: f64| -> Option<(f64, [u32; 2], SampledRay)> {
        let ray = camera.ray(x, y);
        let located = map.locate(&ray)?;
        let entry_t = match box_medium {
            None => Some(0.0),
            Some(box_medium) => box_medium
                .clip(&ray)
                .filter(|&(_, far)| far > 0.0)
                .map(|(near, _)| near.max(0.0)),
        };
        let [(lower, _), (upper, _)] = map.neighbours(located.slice);
        let sampled = SampledRay {
            key: map.order_key(located.threshold),
            rate: located.s_per_t,
            origin: located.s_origin,
            medium_entry: entry_t.map(|t| located.s_origin + located.s_per_t * t),
        };
        Some((located.slice, [lower, upper], sampled))
    };
    // The border in order around the image, each point once.
    let perimeter: Vec<(f64, f64)> = (0..w)
        .map(|x| (x as f64, 0.0))
        .chain((0..h).map(|y| (w as f64, y as f64)))
        .chain((1..=w).rev().map(|x| (x as f64, h as f64)))
        .chain((1..=h).rev().map(|y| (0.0, y as f64)))
        .collect();
    let around: Vec<Option<BorderRay>> = perimeter.par_iter().map(|&(x, y)| sample(x, y)).collect();
    let border = border_rays(&around, map.slices, map.wraps_around(), |k| map.slice_of(k));
    // One vector per pixel row, each allocated once: extending one vector from all rows
    // grew and copied it, a fifth of colonnade's slice frames.
    let interior: Vec<SampledRays> = (0..h)
        .into_par_iter()
        .map(|y| {
            let py = y as f64 + 0.5;
            let columns = sampled_columns(y, w, interior_stride, epipoles, dense_radius, block);
            let mut row = Vec::with_capacity(columns.len());
            row.extend(
                columns
                    .into_iter()
                    .filter_map(|x| sample(x as f64 + 0.5, py).map(|(_, pair, ray)| (pair, ray))),
            );
            row
        })
        .collect();
    let rows: Vec<SampledRays> = std::iter::once(border).chain(interior).collect();
    let slices = map.slices as usize;
    let mut by_slice = RaysBySlice::of(&rows, slices)?;
    let sampled_frames: Vec<Option<(SliceFrame, Vec<Warp>)>> = by_slice
        .slices_mut()
        .into_par_iter()
        .enumerate()
        .map(|(slice, (keyed, extremes))| {
            let (frame, sorted, texels) =
                frame_of(keyed, extremes, bands_per_octave, |lowest, highest| {
                    let reach = sample_reaches.map_or(usize::MAX, |reaches| reaches[slice]);
                    texel_keys(map, slice, lowest, highest, reach)
                })?;
            Some((frame, band_warps(&frame, &sorted, &texels)))
        })
        .collect();
    let frames: Vec<Option<SliceFrame>> = sampled_frames
        .iter()
        .map(|sampled| sampled.as_ref().map(|(frame, _)| *frame))
        .collect();
    // Fill unsampled slices from the nearest sampled one, scanning both ways.
    let sampled: Vec<usize> = (0..frames.len()).filter(|&i| frames[i].is_some()).collect();
    let fallback = SliceFrame {
        warp: Warp::from_knots(std::array::from_fn(|i| i as f64)),
        fastest: 1.0,
        slowest: 1.0,
        origin: 0.0,
        medium_start: Some(0.0),
        log2_fastest: 0.0,
        bands_per_octave,
    };
    let frames: Vec<SliceFrame> = (0..frames.len())
        .map(|i| {
            frames[i].unwrap_or_else(|| {
                let nearest = sampled
                    .iter()
                    .min_by_key(|&&j| (j as isize - i as isize).unsigned_abs());
                nearest.and_then(|&j| frames[j]).unwrap_or(fallback)
            })
        })
        .collect();
    // A slice that took a neighbour's frame has no rays of its own: one warp for all bands.
    let warps = sampled_frames
        .into_iter()
        .zip(&frames)
        .map(|(sampled, frame)| match sampled {
            Some((_, warps)) => warps,
            None => vec![frame.warp; frame.band_count()],
        })
        .collect();
    Ok((frames, warps))
}

/// A ray of the image's border: its slice coordinate, the two slices it lies between, and
/// the ray.
type BorderRay = (f64, [u32; 2], SampledRay);

/// The rays of the image's border, given in order around it (`None` along the light), as
/// [`slice_frames`] samples them: each ray belongs to the two slices it lies between, and
/// where the border jumps more than a slice between it and a ray beside it, to every slice
/// whose neighbourhood (the slice either side, which rays between them read too) the
/// border crosses there. A slice's extreme keys lie where its line crosses the border,
/// and slices thinner than the border's spacing fell between its points: their warps held
/// none of the keys near their ends, which warped to one end with the texels beyond them
/// and read half lit (a dense-fog view with 4,096 slices at 1152×648 was 18% off the
/// reference). Rays come in pairs of slices, as [`RaysBySlice`] takes them; `slices` go
/// round a full turn where `wraps`, and `slice_of` gives the slice of a whole index past
/// either end ([`EpipolarMap::slice_of`]).
fn border_rays(
    around: &[Option<BorderRay>],
    slices: u32,
    wraps: bool,
    slice_of: impl Fn(i64) -> usize,
) -> SampledRays {
    let count = around.len();
    let turn = slices as f64;
    let slice_of = |k: i64| slice_of(k) as u32;
    let mut rays = Vec::with_capacity(count + count / 8);
    for (k, point) in around.iter().enumerate() {
        let Some((slice, pair, ray)) = *point else {
            continue;
        };
        rays.push((pair, ray));
        for beside in [around[(k + count - 1) % count], around[(k + 1) % count]] {
            let Some((other, _, _)) = beside else {
                continue;
            };
            // Across the ends of a full turn the short way round.
            let other = match other - slice {
                jump if wraps && jump > turn / 2.0 => other - turn,
                jump if wraps && jump < -turn / 2.0 => other + turn,
                _ => other,
            };
            // Within a slice the two rays' own pairs cover every slice between them.
            if (other - slice).abs() <= 1.0 {
                continue;
            }
            // Slice j is read by the rays between j − 1 and j + 1.
            let (lowest, highest) = (slice.min(other), slice.max(other));
            let within = |k: i64| bounded_slice_index(k, slices, wraps);
            let (first, last) = (
                within(lowest.floor() as i64),
                within(highest.floor() as i64 + 1),
            );
            for j in (first..=last).step_by(2) {
                rays.push(([slice_of(j), slice_of((j + 1).min(last))], ray));
            }
        }
    }
    rays
}

/// Within this many pixels of an epipole (both axes) [`slice_frames`] samples every pixel;
/// farther in its dense square, every other pixel of every other row to half the square's
/// radius, and every fourth pixel of every fourth row beyond. The slices are wedges that
/// widen away from the epipole, so that the sparser samples still give each of 1024 slices
/// about 35 rays within 326 px, before the image's grid, while the slowest rays, next to
/// the ray-marched block, are all sampled. Every other pixel across the whole square gave
/// about 80 (a quarter as many as every pixel, and colonnade's preparation 18% faster);
/// the fourths sample 17% fewer of colonnade's rays (102K of 123K), and moved the errors
/// against the reference at 1920×1080 on the five views with the sun in the image by
/// −0.027 to +0.003 points.
const EVERY_PIXEL_RADIUS: f64 = 64.0;

/// The columns of pixel row `y` (of `w`) that [`slice_frames`] samples: those on the grid
/// of `stride`, and within `dense_radius` of an epipole (both axes) every one up to
/// [`EVERY_PIXEL_RADIUS`], the even ones of even rows to half of `dense_radius` and every
/// fourth of every fourth row beyond, except those within `block` of one. Visits the grid
/// and each epipole's dense square (with a pixel's margin) rather than the whole row; the
/// exact test decides.
fn sampled_columns(
    y: u32,
    w: u32,
    stride: u32,
    epipoles: &[[f64; 2]],
    dense_radius: f64,
    block: f64,
) -> Vec<u32> {
    let py = y as f64 + 0.5;
    let within = |x: f64, radius: f64| {
        epipoles
            .iter()
            .any(|e| (x - e[0]).abs() <= radius && (py - e[1]).abs() <= radius)
    };
    let on_grid_row = y.is_multiple_of(stride);
    let mut dense: Vec<(u32, u32)> = epipoles
        .iter()
        .filter(|e| (py - e[1]).abs() <= dense_radius + 1.0)
        .map(|e| {
            let column = |x: f64| x.clamp(0.0, w as f64) as u32;
            (
                column(e[0] - dense_radius - 1.5),
                column(e[0] + dense_radius + 1.5),
            )
        })
        .collect();
    dense.sort_unstable();
    let mut merged: Vec<(u32, u32)> = Vec::with_capacity(dense.len());
    for (lo, hi) in dense {
        match merged.last_mut() {
            Some(last) if lo <= last.1 => last.1 = last.1.max(hi),
            _ => merged.push((lo, hi)),
        }
    }
    let in_dense = |x: u32| merged.iter().any(|&(lo, hi)| lo <= x && x < hi);
    let grid = (0..if on_grid_row { w } else { 0 })
        .step_by(stride as usize)
        .filter(|&x| !in_dense(x));
    merged
        .iter()
        .flat_map(|&(lo, hi)| lo..hi)
        .chain(grid)
        .filter(|&x| {
            // The parities first: most pixels of a dense square then test two radii, not
            // four.
            let px = x as f64 + 0.5;
            let on_grid = on_grid_row && x % stride == 0;
            let fourth = || x % 4 == 0 && y.is_multiple_of(4) && within(px, dense_radius);
            let even = || x % 2 == 0 && y.is_multiple_of(2) && within(px, dense_radius / 2.0);
            let every = || within(px, EVERY_PIXEL_RADIUS.min(dense_radius));
            (on_grid || fourth() || even() || every()) && !within(px, block)
        })
        .collect()
}

/// A slice's sampled rays in key order: their keys, and their speeds' log₂.
struct SortedRays {
    keys: Vec<f64>,
    log2_rates: Vec<f64>,
}

/// Sampled rays grouped by slice (a ray belongs to two): a counting sort over groups of
/// pixel rows in parallel, each group's rays after the earlier groups' in every slice.
/// Each slice keeps its rays' keys and speeds, all that its frame sorts, and their
/// extremes.
struct RaysBySlice {
    /// Per slice, where its rays start in `keyed`; one more, for the end.
    offsets: Vec<usize>,
    /// [`total_order_bits`] of each ray's key, and its speed's log₂ (taken once per
    /// ray, not in each of its slices).
    keyed: Vec<(u64, f64)>,
    /// Per group of rows, per slice.
    extremes: Vec<Vec<RayExtremes>>,
}

impl RaysBySlice {
    /// Groups of rows counted and scattered in parallel: enough to share the work out,
    /// few enough that their per-slice tallies stay small.
    const GROUPS: usize = 32;

    fn of(rows: &[SampledRays], slices: usize) -> Result<Self> {
        let groups: Vec<&[SampledRays]> = rows
            .chunks(rows.len().div_ceil(Self::GROUPS).max(1))
            .collect();
        let tallies: Vec<(Vec<usize>, Vec<RayExtremes>)> = groups
            .par_iter()
            .map(|group| {
                let mut counts = vec![0usize; slices];
                let mut extremes = vec![RayExtremes::NONE; slices];
                for (pair, ray) in group.iter().flatten() {
                    for &slice in pair {
                        counts[slice as usize] += 1;
                        extremes[slice as usize].include(ray);
                    }
                }
                (counts, extremes)
            })
            .collect();
        let total: usize = tallies.iter().flat_map(|(counts, _)| counts).sum();
        // Every place is written below, so a kept buffer's old values do not matter.
        let mut keyed = SPARE_KEYED_RAYS.try_take(total, || {
            format!("the plan's sampled rays ({total} in {slices} slices)")
        })?;
        // Each group's place in each slice, slice by slice.
        let mut offsets = Vec::with_capacity(slices + 1);
        let mut places: Vec<Vec<&mut [(u64, f64)]>> =
            groups.iter().map(|_| Vec::with_capacity(slices)).collect();
        let mut rest = keyed.as_mut_slice();
        let mut at = 0;
        for slice in 0..slices {
            offsets.push(at);
            for (place, (counts, _)) in places.iter_mut().zip(&tallies) {
                let (own, tail) = rest.split_at_mut(counts[slice]);
                rest = tail;
                at += counts[slice];
                place.push(own);
            }
        }
        offsets.push(at);
        groups
            .into_par_iter()
            .zip(places)
            .for_each(|(group, mut places)| {
                let mut filled = vec![0usize; slices];
                for (pair, ray) in group.iter().flatten() {
                    let entry = (total_order_bits(ray.key), ray.rate.log2());
                    for &slice in pair {
                        let slice = slice as usize;
                        places[slice][filled[slice]] = entry;
                        filled[slice] += 1;
                    }
                }
            });
        Ok(Self {
            offsets,
            keyed,
            extremes: tallies.into_iter().map(|(_, extremes)| extremes).collect(),
        })
    }

    /// Each slice's rays, as [`frame_of`] takes them, in place.
    fn slices_mut(&mut self) -> Vec<(&mut [(u64, f64)], RayExtremes)> {
        let mut rest = self.keyed.as_mut_slice();
        let mut slices = Vec::with_capacity(self.offsets.len().saturating_sub(1));
        for (slice, range) in self.offsets.windows(2).enumerate() {
            let (own, tail) = rest.split_at_mut(range[1] - range[0]);
            rest = tail;
            let extremes = self
                .extremes
                .iter()
                .fold(RayExtremes::NONE, |all, group| all.merge(&group[slice]));
            slices.push((own, extremes));
        }
        slices
    }
}

impl Drop for RaysBySlice {
    fn drop(&mut self) {
        SPARE_KEYED_RAYS.keep(std::mem::take(&mut self.keyed));
    }
}

/// The extremes of a slice's sampled rays that its frame keeps.
#[derive(Clone, Copy)]
struct RayExtremes {
    fastest: f64,
    slowest: f64,
    origin: f64,
    /// Where the first of them enters the medium, if any does.
    medium_start: Option<f64>,
}

impl RayExtremes {
    const NONE: Self = Self {
        fastest: 0.0,
        slowest: f64::INFINITY,
        origin: f64::INFINITY,
        medium_start: None,
    };

    #[inline]
    fn include(&mut self, ray: &SampledRay) {
        *self = self.merge(&Self {
            fastest: ray.rate,
            slowest: ray.rate,
            origin: ray.origin,
            medium_start: ray.medium_entry,
        });
    }

    #[inline]
    fn merge(self, other: &Self) -> Self {
        Self {
            fastest: f64::max(self.fastest, other.fastest),
            slowest: f64::min(self.slowest, other.slowest),
            origin: f64::min(self.origin, other.origin),
            medium_start: match (self.medium_start, other.medium_start) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            },
        }
    }
}

/// A slice's frame from its sampled rays, given as their keys' [`total_order_bits`] and
/// speeds' log₂ (sorted here by key: moving whole rays cost twice as much) and their extremes,
/// and those rays sorted by key. `texels` gives the slice's texel keys between the rays'
/// lowest and highest, which it is called with; they are returned too, for the bands'
/// warps.
fn frame_of(
    keyed: &mut [(u64, f64)],
    extremes: RayExtremes,
    bands_per_octave: u32,
    texels: impl FnOnce(f64, f64) -> Vec<f64>,
) -> Option<(SliceFrame, SortedRays, Vec<f64>)> {
    if keyed.is_empty() {
        return None;
    }
    let RayExtremes {
        fastest,
        slowest,
        origin,
        medium_start,
    } = extremes;
    let slowest = slowest.max(fastest / MAX_SPEED_RATIO);
    keyed.sort_unstable_by_key(|&(key, _)| key);
    let sorted = SortedRays {
        keys: keyed
            .iter()
            .map(|&(key, _)| from_total_order_bits(key))
            .collect(),
        log2_rates: keyed.iter().map(|&(_, log2_rate)| log2_rate).collect(),
    };
    let texels = texels(sorted.keys[0], sorted.keys[sorted.keys.len() - 1]);
    let frame = SliceFrame {
        warp: Warp::of(&sorted.keys, &texels),
        fastest,
        slowest,
        origin,
        medium_start,
        log2_fastest: fastest.log2(),
        bands_per_octave,
    };
    Some((frame, sorted, texels))
}

impl Warp {
    /// The warp of sorted ray keys and of sorted texel keys. The inner knots are quantiles of the
    /// rays and of the texels whose keys lie among the rays', weighed half and half: a
    /// ray's visibility blurs over keys within about 1/M of its own, so resolution belongs
    /// where rays and the occluders they pass close to are. Rays alone left the top eighth
    /// of colonnade's default view (rays grazing its roof) in a tenth of the range, and the
    /// roof leaked light through the blur.
    fn of(rays: &[f64], texels: &[f64]) -> Self {
        let (lowest, highest) = (rays[0], rays[rays.len() - 1]);
        let first = texels.partition_point(|&key| key <= lowest);
        let texels = &texels[first..texels.partition_point(|&key| key < highest).max(first)];
        let mut knots = [0.0; KNOTS];
        knots[0] = lowest;
        knots[KNOTS - 1] = highest;
        let ray_share = if texels.is_empty() { 1.0 } else { 0.5 };
        let (ray_weight, texel_weight) = (
            ray_share / rays.len() as f64,
            (1.0 - ray_share) / texels.len().max(1) as f64,
        );
        // Walk both sorted lists in key order, cutting at each (KNOTS − 1)-th of the weight.
        let (mut r, mut t, mut cumulative, mut next) = (0, 0, 0.0, 1);
        while next < KNOTS - 1 && (r < rays.len() || t < texels.len()) {
            let key = if t >= texels.len() || (r < rays.len() && rays[r] <= texels[t]) {
                r += 1;
                cumulative += ray_weight;
                rays[r - 1]
            } else {
                t += 1;
                cumulative += texel_weight;
                texels[t - 1]
            };
            while next < KNOTS - 1 && cumulative >= next as f64 / (KNOTS - 1) as f64 - 1e-12 {
                knots[next] = key;
                next += 1;
            }
        }
        for knot in &mut knots[next..KNOTS - 1] {
            *knot = highest;
        }
        // Strictly increasing, so that every segment has a slope.
        let spread = (knots[KNOTS - 1] - knots[0]).max(1e-9);
        for i in 1..KNOTS {
            knots[i] = knots[i].max(knots[i - 1] + spread * 1e-6);
        }
        Self::from_knots(knots)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampled_columns_are_the_grid_and_the_squares_around_epipoles() {
        let (w, h, stride) = (297u32, 161u32, 5u32);
        let layouts: [&[[f64; 2]]; 7] = [
            &[],
            &[[40.3, 30.7]],
            &[[140.3, 80.7]],
            &[[-3.0, 2.0]],
            &[[296.5, 160.5], [10.0, 55.0]],
            &[[50.0, 30.0], [58.0, 33.0]],
            &[[f64::NAN, 20.0]],
        ];
        for epipoles in layouts {
            for (dense_radius, block) in [(12.0, 3.0), (12.5, 0.0), (2.0, 4.0), (200.0, 16.0)] {
                for y in 0..h {
                    let py = y as f64 + 0.5;
                    let within = |px: f64, radius: f64| {
                        epipoles
                            .iter()
                            .any(|e| (px - e[0]).abs() <= radius && (py - e[1]).abs() <= radius)
                    };
                    let expected: Vec<u32> = (0..w)
                        .filter(|&x| {
                            let px = x as f64 + 0.5;
                            let on_grid = x % stride == 0 && y % stride == 0;
                            let every = within(px, EVERY_PIXEL_RADIUS.min(dense_radius));
                            let even = within(px, dense_radius / 2.0) && x % 2 == 0 && y % 2 == 0;
                            let fourth = within(px, dense_radius) && x % 4 == 0 && y % 4 == 0;
                            (on_grid || every || even || fourth) && !within(px, block)
                        })
                        .collect();
                    let mut got = sampled_columns(y, w, stride, epipoles, dense_radius, block);
                    got.sort_unstable();
                    assert_eq!(got, expected, "{epipoles:?}, r {dense_radius}, row {y}");
                }
            }
        }
    }

    /// The integer image of `total_cmp`'s order sorts alike and maps back exactly,
    /// signed zeros, infinities and NaNs included.
    #[test]
    fn total_order_bits_sort_like_total_cmp() {
        let mut values = vec![
            0.0,
            -0.0,
            1.5,
            -1.5,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            -f64::NAN,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            1e-310,
            -1e-310,
            f64::MAX,
            f64::MIN,
        ];
        values.extend((0..200).map(|i| ((i as f64) * 0.731).sin() * 10f64.powi(i % 9 - 4)));
        let mut by_cmp = values.clone();
        by_cmp.sort_by(f64::total_cmp);
        let mut by_bits: Vec<u64> = values.iter().map(|&v| total_order_bits(v)).collect();
        by_bits.sort_unstable();
        let by_bits: Vec<u64> = by_bits
            .into_iter()
            .map(|bits| from_total_order_bits(bits).to_bits())
            .collect();
        let by_cmp: Vec<u64> = by_cmp.iter().map(|v| v.to_bits()).collect();
        assert_eq!(by_bits, by_cmp);
    }

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

    /// The coefficient row at `z_ray` for `frequencies`, as `of` makes it, dotted with the
    /// basis row at `z_texel`, as a lookup's kernel dots them.
    fn table_dot(
        frequencies: usize,
        of: impl Fn(&Tables, &[f32]) -> Vec<f32>,
        z_ray: f64,
        z_texel: f64,
    ) -> f64 {
        let tables = Tables::get(frequencies);
        let row = padded(2 * frequencies);
        let at = |table: &[f32], z: f64| table[Tables::index(z) * row..][..row].to_vec();
        let ray = of(tables, &at(&tables.coefficients, z_ray));
        let texel = at(&tables.basis, z_texel);
        let read = BandRead {
            rows: [(0, 1.0); 4],
            count: 1,
            coefficients: &ray,
        };
        Kernels::Portable.blend_dots(&texel, &[read]) as f64
    }

    /// ½ + coefficients(z_ray) · basis(z_texel) is a step: 1 where the ray's key exceeds
    /// the texel's, 0 below, ½ at the jump, within the ringing of a truncated series.
    #[test]
    fn the_tables_reconstruct_the_visibility_step() {
        let frequencies = 32;
        let visibility = |z_ray: f64, z_texel: f64| {
            0.5 + table_dot(frequencies, |_, row| row.to_vec(), z_ray, z_texel)
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

    /// A ray's blur row, dotted with a texel's basis row, reads about 1 for a texel at the
    /// ray's own warped key and about 0 for one a few windows away, at the default M; with
    /// fewer bases the step is wider than the window and reads less.
    #[test]
    fn the_blur_row_finds_texels_about_the_ray_s_key() {
        let blurred = |frequencies: usize, z_ray: f64, z_texel: f64| {
            let blur = |tables: &Tables, coefficients: &[f32]| {
                let mut row = vec![0.0; coefficients.len()];
                tables.blur_of(coefficients, &mut row);
                row
            };
            table_dot(frequencies, blur, z_ray, z_texel)
        };
        for z in [0.2, 0.5, 0.8] {
            let at_key = blurred(16, z, z);
            assert!(at_key > 0.85, "{at_key} at {z}");
            for away in [-4.0, 4.0, 8.0] {
                let far = blurred(16, z, z + away * BLUR_WIDTH);
                assert!(far.abs() < 0.05, "{far} at {away} windows from {z}");
            }
            // M = 8: the same window holds less of a step four times as wide.
            let wide = blurred(4, z, z);
            assert!(wide < 0.5 * at_key, "{wide} against {at_key}");
        }
    }

    /// `scene`'s camera, its rectified map, and the epipoles ahead of the camera, as a frame
    /// hands them to [`Prefiltered::build`].
    fn frame_inputs(scene: &crate::scene::Scene) -> (CameraModel, EpipolarMap, Vec<[f64; 2]>) {
        use crate::epipolar::test_support::rectified;
        use crate::epipolar::{epipoles_in_image, RectifyDesc};
        let (camera, shadow, map) = rectified(
            scene,
            scene.render.rectification,
            &RectifyDesc::prefiltered(scene.render.epipolar_slices),
        );
        let epipoles = epipoles_in_image(&camera, &shadow, f64::INFINITY).collect();
        (camera, map, epipoles)
    }

    #[test]
    fn dark_lookups_are_declined_only_where_frames_tend_to_be_dark() {
        // (box medium, light from below, bands per octave, dark frame) and the limit.
        for (box_medium, below, bands, dark, limit) in [
            (false, false, 1, false, 0.0),
            (true, false, 1, false, DARK_LOOKUP_VISIBILITY),
            (false, true, 1, false, DARK_LOOKUP_VISIBILITY),
            (false, false, 2, false, DARK_LOOKUP_VISIBILITY),
            (false, false, 1, true, DARK_LOOKUP_VISIBILITY),
        ] {
            assert_eq!(dark_lookup_limit(box_medium, below, bands, dark), limit);
        }
        // The built-in scenes' fog (0.05 /m over 70 m) keeps one band an octave.
        assert_eq!(bands_per_octave(0.05, 70.0), 1);
        assert_eq!(bands_per_octave(0.2, 70.0), 3);
    }

    /// The pieces of a ray in a box, looked up with shared boundaries, read what each
    /// piece reads on its own, on every 53rd pixel of torus in a box.
    #[test]
    fn shared_piece_boundaries_read_what_each_piece_reads_alone() {
        let mut scene = crate::builtin_scene("torus").expect("built-in scene");
        scene.camera.width = 96;
        scene.camera.height = 54;
        scene.medium.extinction = 0.3;
        scene.medium.extent = Extent::Box {
            world_from_cube: Mat4::from_translation(glam::Vec3::new(0.5, -0.5, 3.0))
                * Mat4::from_scale(glam::Vec3::new(5.0, 4.0, 3.0)),
        };
        let (camera, map, epipoles) = frame_inputs(&scene);
        let desc = PrefilteredDesc::from_settings(&scene.render);
        let method = Prefiltered::build(&map, &camera, &epipoles, &desc, &scene.sun, &scene.medium)
            .expect("memory for the method");
        let (mut compared, mut worst) = (0, 0.0f64);
        for pixel in (0..96 * 54).step_by(53) {
            let ray = camera.ray((pixel % 96) as f64 + 0.5, (pixel / 96) as f64 + 0.5);
            let Some(located) = map.locate(&ray) else {
                continue;
            };
            let key = map.order_key(located.threshold);
            let x = |t: f64| row_coordinate(&map, located.s_origin + located.s_per_t * t);
            let boundaries: Vec<f64> = [0.0, 2.0, 4.5, 7.0, 11.0, 16.0].map(x).to_vec();
            let mut shared = [0.0; 5];
            // Pieces of no light: the rule for dark rays is not what this compares.
            let shared = method
                .average_pieces(&located, key, &boundaries, &[0.0; 5], &mut shared)
                .map(|()| shared);
            // Pieces are tested for uniformity, and for their blur, only as a whole ray.
            let whole = method.uniform_visibility(&located, boundaries[0], boundaries[5]);
            let (_, blurred) = method.look_up(&located, key, boundaries[0], boundaries[5]);
            let alone: Option<Vec<f64>> = boundaries
                .windows(2)
                .map(|ends| match whole {
                    Some(visibility) => Some(visibility),
                    None if blurred > BLURRED_SHARE_LIMIT => None,
                    None => method.look_up(&located, key, ends[0], ends[1]).0.value(),
                })
                .collect();
            match (shared, alone) {
                (Some(shared), Some(alone)) => {
                    compared += 1;
                    for (a, b) in shared.iter().zip(&alone) {
                        worst = worst.max((a - b).abs());
                    }
                }
                (None, None) => {}
                (shared, alone) => panic!("pixel {pixel}: {shared:?} against {alone:?}"),
            }
        }
        assert!(compared >= 50, "only {compared} rays compared");
        assert!(worst < 1e-5, "{worst}");
    }

    /// Where the rectified map says a ray is lit, or shadowed, over every sample it
    /// crosses, prefiltering gives min-max's exact answer, not its series' estimate.
    #[test]
    fn rays_lit_or_shadowed_all_along_are_exact() {
        use crate::minmax::{MinMaxMethod, MinMaxMipmap};
        use crate::uniformity::uniformity_of_every_sample;
        use rand::{RngExt, SeedableRng};
        let mut scene = crate::builtin_scene("torus").expect("built-in scene");
        scene.camera.width = 96;
        scene.camera.height = 54;
        let (camera, map, epipoles) = frame_inputs(&scene);
        let desc = PrefilteredDesc::from_settings(&scene.render);
        let method = Prefiltered::build(&map, &camera, &epipoles, &desc, &scene.sun, &scene.medium)
            .expect("memory for the method");
        let mipmap = MinMaxMipmap::build(&map).expect("memory for the mipmaps");
        let exact = MinMaxMethod::new(&map, &mipmap, &scene.sun, &scene.medium);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let (mut lit, mut shadowed, mut mixed) = (0, 0, 0);
        for pixel in 0..96 * 54 {
            let ray = camera.ray((pixel % 96) as f64 + 0.5, (pixel / 96) as f64 + 0.5);
            // Stretches of rays, so that some lie wholly in the torus' shadow.
            let t_start = rng.random_range(0.0..25.0) + camera.clip_start * ray.distance_per_depth;
            let t_end = t_start + rng.random_range(2.0..20.0);
            let Some(located) = map.locate(&ray) else {
                continue;
            };
            let Some(sample) = method.march(&ray, t_start, t_end) else {
                continue;
            };
            let coordinate = |t: f64| map.sample_coordinate(located.s_origin + located.s_per_t * t);
            let (c0, c1) = (coordinate(t_start), coordinate(t_end));
            if !(c0 >= 0.0 && c1 <= map.samples as f64) {
                continue;
            }
            let (first, last) = (c0 as usize, c1.ceil() as usize - 1);
            let threshold = located.threshold as f32;
            let mut states = map
                .neighbours(located.slice)
                .into_iter()
                .filter(|&(_, share)| share > 0.0)
                .map(|(slice, _)| uniformity_of_every_sample(&map, slice, threshold, first, last));
            let Some(state) = states.next().flatten() else {
                mixed += 1;
                continue;
            };
            if !states.all(|other| other == Some(state)) {
                mixed += 1;
                continue;
            }
            let expected = exact.march(&ray, t_start, t_end).expect("min-max walks it");
            assert_eq!(
                sample.visibility,
                if state { 1.0 } else { 0.0 },
                "pixel {pixel}"
            );
            assert!(
                (sample.scattering - expected.scattering).abs()
                    <= 1e-9 * expected.scattering.max(1e-9),
                "pixel {pixel}: {} against min-max's {}",
                sample.scattering,
                expected.scattering
            );
            if state {
                lit += 1;
            } else {
                shadowed += 1;
            }
        }
        assert!(
            lit > 200 && shadowed > 20 && mixed > 200,
            "{lit} lit, {shadowed} shadowed, {mixed} mixed"
        );
    }

    #[test]
    fn only_rays_travelling_with_the_light_and_close_to_it_count_as_along_it() {
        let light = DVec3::new(0.0, 0.0, -1.0);
        let tilted = |degrees: f64| {
            let a = degrees.to_radians();
            DVec3::new(a.sin(), 0.0, -a.cos())
        };
        assert!(is_along_the_light(light, light));
        assert!(is_along_the_light(tilted(8.0), light));
        assert!(!is_along_the_light(tilted(9.0), light));
        assert!(!is_along_the_light(-light, light), "towards the light");
        assert!(
            !is_along_the_light(tilted(175.0), light),
            "towards the light"
        );
        assert!(!is_along_the_light(tilted(90.0), light));
    }

    #[test]
    fn tables_reach_the_far_side_of_a_box_from_either_camera() {
        use crate::scene::Camera;
        let (eye, target) = (glam::Vec3::ZERO, glam::Vec3::X);
        let camera = Camera::pinhole_looking_at(eye, target, 35.0, 64, 36);
        let cube = Mat4::from_translation(glam::Vec3::new(10.0, 0.0, 0.0));
        let far = farthest_in_box(&CameraModel::new(&camera), &cube);
        assert!((far - (121.0f64 + 2.0).sqrt()).abs() < 1e-5, "{far}");
        let camera = Camera::orthographic_looking_at(eye, target, 4.0, 64, 36);
        let far = farthest_in_box(&CameraModel::new(&camera), &cube);
        assert!((far - 11.0).abs() < 1e-5, "{far}");
    }

    #[test]
    fn box_pieces_bound_the_sunward_change_and_the_view_depth_in_each() {
        assert_eq!(box_pieces(0.0, 0.0), 1);
        assert_eq!(box_pieces(BOX_PIECE_DEPTH, 0.0), 1);
        assert_eq!(box_pieces(1.04 * BOX_PIECE_DEPTH, 0.0), 2);
        assert_eq!(box_pieces(7.6 * BOX_PIECE_DEPTH, 0.0), 8);
        assert_eq!(box_pieces(50.0, 0.0), MAX_BOX_PIECES);
        assert_eq!(box_pieces(0.0, BOX_PIECE_VIEW_DEPTH), 1);
        assert_eq!(box_pieces(0.0, 2.1 * BOX_PIECE_VIEW_DEPTH), 3);
        assert_eq!(
            box_pieces(2.5 * BOX_PIECE_DEPTH, 2.1 * BOX_PIECE_VIEW_DEPTH),
            3
        );
        assert_eq!(
            box_pieces(3.5 * BOX_PIECE_DEPTH, 2.1 * BOX_PIECE_VIEW_DEPTH),
            4
        );
        assert_eq!(box_pieces(0.0, 1e9), MAX_BOX_PIECES);
    }

    /// The damped step overshoots by about a third of the truncated series' 9%, and its
    /// transition widens by less than half.
    #[test]
    fn damping_trades_overshoot_for_a_slightly_wider_step() {
        let frequencies = 16;
        let step = |z: f64, damped: bool| {
            0.5 + (0..frequencies)
                .map(|m| {
                    let sigma = if damped { damping(m, frequencies) } else { 1.0 };
                    sigma * 2.0 / frequency(m) * (frequency(m) * z).sin()
                })
                .sum::<f64>()
        };
        let measure = |damped: bool| {
            let zs: Vec<f64> = (0..=20000).map(|i| -0.5 + i as f64 / 20000.0).collect();
            let values: Vec<f64> = zs.iter().map(|&z| step(z, damped)).collect();
            let overshoot = values.iter().cloned().fold(f64::MIN, f64::max) - 1.0;
            let crossing = |level: f64| zs[values.iter().position(|&v| v > level).unwrap()];
            (overshoot, crossing(0.9) - crossing(0.1))
        };
        let (plain_overshoot, plain_width) = measure(false);
        let (overshoot, width) = measure(true);
        assert!((plain_overshoot - 0.09).abs() < 0.005, "{plain_overshoot}");
        assert!(overshoot < 0.035, "{overshoot}");
        assert!(
            width > plain_width && width < 1.5 * plain_width,
            "{width} {plain_width}"
        );
    }

    #[test]
    fn first_failing_finds_where_a_prefix_ends() {
        for len in 0..12 {
            for end in 0..=len {
                assert_eq!(first_failing(len, |i| i < end), end, "{len} {end}");
            }
        }
    }

    #[test]
    fn border_rays_belong_to_every_slice_the_border_crosses_beside_them() {
        let ray = |key: f64| SampledRay {
            key,
            rate: 1.0,
            origin: 0.0,
            medium_entry: None,
        };
        let holding = |rays: &SampledRays, slice: u32| -> Vec<f64> {
            let mut keys: Vec<f64> = rays
                .iter()
                .filter(|(pair, _)| pair.contains(&slice))
                .map(|(_, ray)| ray.key)
                .collect();
            keys.sort_by(f64::total_cmp);
            keys.dedup();
            keys
        };
        // A border ray at slice coordinate `slice`, between its two slices by `slice_of`.
        let at = |slice: f64, key: f64, slice_of: &dyn Fn(i64) -> usize| -> Option<BorderRay> {
            let lower = slice.floor() as i64;
            let pair = [slice_of(lower) as u32, slice_of(lower + 1) as u32];
            Some((slice, pair, ray(key)))
        };
        // Slices 10, clamped; the border jumps 0.4 → 3.7 and 4.1 → 0.2 (round the end of
        // the border) between points (slices thinner than its spacing), and one point looks
        // along the light.
        let clamped = |k: i64| k.clamp(0, 9) as usize;
        let around = [
            at(0.2, 1.0, &clamped),
            at(0.4, 2.0, &clamped),
            at(3.7, 3.0, &clamped),
            at(3.9, 4.0, &clamped),
            None,
            at(4.1, 5.0, &clamped),
        ];
        let rays = border_rays(&around, 10, false, clamped);
        // Slice j is read between j − 1 and j + 1: 0.4 → 3.7 crosses slices 0 to 4.
        for slice in 0..=4 {
            let keys = holding(&rays, slice);
            assert!(
                keys.contains(&2.0) && keys.contains(&3.0),
                "slice {slice}: {keys:?}"
            );
        }
        // The border closes: the last point and the first lie beside each other.
        assert_eq!(holding(&rays, 5), [1.0, 5.0]);
        assert!(holding(&rays, 6).is_empty());
        // 3.9 lies beside 3.7 and the point along the light only: its own slices, 3 and 4.
        assert_eq!(holding(&rays, 3), [1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(holding(&rays, 0), [1.0, 2.0, 3.0, 5.0]);
        assert_eq!(holding(&rays, 1), [1.0, 2.0, 3.0, 5.0]);
        // Slices 8 round a full turn: 7.2 → 1.5 crosses the ends the short way.
        let turn = |k: i64| k.rem_euclid(8) as usize;
        let around = [
            at(7.2, 1.0, &turn),
            at(1.5, 2.0, &turn),
            at(4.0, 3.0, &turn),
        ];
        let rays = border_rays(&around, 8, true, turn);
        for slice in [7, 0, 1, 2] {
            let keys = holding(&rays, slice);
            assert!(
                keys.contains(&1.0) && keys.contains(&2.0),
                "slice {slice}: {keys:?}"
            );
        }
        assert!(!holding(&rays, 6).contains(&2.0));
        // Rays a slice apart or less keep to their own pairs.
        let around = [at(2.2, 1.0, &turn), at(3.1, 2.0, &turn)];
        let rays = border_rays(&around, 8, true, turn);
        assert_eq!(rays.len(), 2);
        assert_eq!((rays[0].0, rays[1].0), ([2, 3], [3, 4]));
    }

    /// Rays grouped by slice, over rows of every length (none too), hold exactly the
    /// rays of each slice, in row order, with their extremes; more rows than groups and
    /// fewer both.
    #[test]
    fn rays_by_slice_hold_each_slice_s_rays_and_their_extremes() {
        use rand::RngExt;
        use rand_pcg::Pcg64;
        let mut rng = Pcg64::new(0x5eed, 0x51ce);
        for (row_count, slices) in [(3usize, 5usize), (70, 13), (200, 64)] {
            let rows: Vec<SampledRays> = (0..row_count)
                .map(|_| {
                    let len = rng.random_range(0..40);
                    (0..len)
                        .map(|_| {
                            let lower = rng.random_range(0..slices as u32);
                            let upper = (lower + rng.random_range(0..2)).min(slices as u32 - 1);
                            let ray = SampledRay {
                                key: rng.random_range(-1.0..1.0),
                                rate: rng.random_range(0.1..10.0),
                                origin: rng.random_range(-5.0..5.0),
                                medium_entry: rng
                                    .random_bool(0.5)
                                    .then(|| rng.random_range(0.0..9.0)),
                            };
                            ([lower, upper], ray)
                        })
                        .collect()
                })
                .collect();
            let mut grouped = RaysBySlice::of(&rows, slices).unwrap();
            let grouped = grouped.slices_mut();
            for slice in 0..slices {
                let mut expected = RayExtremes::NONE;
                let mut keyed = Vec::new();
                for (pair, ray) in rows.iter().flatten() {
                    for &s in pair {
                        if s as usize == slice {
                            expected.include(ray);
                            keyed.push((total_order_bits(ray.key), ray.rate.log2()));
                        }
                    }
                }
                let (got, extremes) = grouped.get(slice).expect("a slice");
                assert_eq!(*got, keyed.as_slice(), "slice {slice}");
                assert_eq!(
                    (extremes.fastest, extremes.slowest, extremes.origin),
                    (expected.fastest, expected.slowest, expected.origin)
                );
                assert_eq!(extremes.medium_start, expected.medium_start);
            }
        }
    }

    /// Band weights with the stepped run found by bisection equal those of the loop that
    /// tested every sample for it, bit for bit, and so do the per-row scales and
    /// cumulative weights summed from them: slices' origins before, inside and past the
    /// map, references slow and fast, media thin and dense, and one so thin that each
    /// step's factor rounds to 1 (every stepped sample then takes the flat weight). Every
    /// band weighs its first sample, and none past the depth cap.
    #[test]
    fn band_weights_match_testing_every_sample() {
        fn weights_testing_each(
            map: &EpipolarMap,
            origin: f64,
            rate: f64,
            extinction: f64,
            count: usize,
        ) -> Vec<f64> {
            let samples = map.samples as usize;
            let origin = origin.max(map.sample_interval(0).0);
            let depth_of =
                |s: f64| (extinction * ((s - origin) / rate).max(0.0)).min(MAX_REFERENCE_DEPTH);
            let flat_per_s = (-MAX_REFERENCE_DEPTH).exp() * extinction / rate;
            let step_factor = map
                .uniform_step()
                .map(|step| (-extinction * step / rate).exp());
            let (mut s0, _) = map.sample_interval(0);
            let mut before = (-depth_of(s0)).exp();
            (0..count)
                .map(|i| {
                    if i >= samples {
                        return 0.0;
                    }
                    let (_, s1) = map.sample_interval(i);
                    let unclamped = |s: f64| extinction * (s - origin) / rate;
                    let after = match step_factor {
                        Some(factor)
                            if unclamped(s0) >= 0.0 && unclamped(s1) <= MAX_REFERENCE_DEPTH =>
                        {
                            before * factor
                        }
                        _ => (-depth_of(s1)).exp(),
                    };
                    let w = if after < before {
                        before - after
                    } else if depth_of(s0) < MAX_REFERENCE_DEPTH {
                        flat_per_s * (s1 - s0)
                    } else {
                        0.0
                    };
                    s0 = s1;
                    before = after;
                    w
                })
                .collect()
        }
        let scene = crate::builtin_scene("colonnade").expect("built-in scene");
        let (_, map, _) = frame_inputs(&scene);
        let samples = map.samples as usize;
        let rows = samples.div_ceil(SAMPLES_PER_ROW) + 1;
        let (first, _) = map.sample_interval(0);
        let (_, last) = map.sample_interval(samples - 1);
        for origin in [first - 3.0, first, 0.5 * (first + last), last + 1.0] {
            for rate in [0.05, 1.0, 40.0] {
                for extinction in [0.0, 1e-15, 1e-4, 0.04, 3.0] {
                    let count = (rows - 1) * SAMPLES_PER_ROW;
                    let mut weights = vec![0.0; count];
                    let mut scales = vec![0.0; rows - 1];
                    let mut cumulative = vec![0.0; rows];
                    band_weights(
                        &map,
                        origin,
                        rate,
                        extinction,
                        &mut weights,
                        &mut scales,
                        &mut cumulative,
                    );
                    let expected = if extinction > 0.0 {
                        weights_testing_each(&map, origin, rate, extinction, count)
                    } else {
                        (0..count)
                            .map(|i| if i < samples { 1.0 } else { 0.0 })
                            .collect()
                    };
                    let same = weights
                        .iter()
                        .zip(&expected)
                        .all(|(a, b)| a.to_bits() == (*b as f32).to_bits());
                    assert!(same, "origin {origin} rate {rate} σ {extinction}");
                    assert!(
                        weights[0] > 0.0,
                        "origin {origin} rate {rate} σ {extinction}"
                    );
                    if extinction > 0.0 {
                        let start = origin.max(first);
                        let past_cap = (0..samples).find(|&i| {
                            extinction * (map.sample_interval(i).0 - start) / rate
                                >= MAX_REFERENCE_DEPTH
                        });
                        if let Some(i) = past_cap {
                            assert!(weights[i..].iter().all(|&w| w == 0.0), "σ {extinction}");
                        }
                    }
                    let mut total = 0.0f64;
                    let (mut expected_scales, mut expected_cumulative) = (vec![], vec![0.0f32]);
                    for pair in expected.chunks_exact(SAMPLES_PER_ROW) {
                        for w in pair {
                            total += w;
                        }
                        expected_scales.push((1.0 / total) as f32);
                        expected_cumulative.push(total as f32);
                    }
                    let bits =
                        |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&scales), bits(&expected_scales), "σ {extinction}");
                    assert_eq!(
                        bits(&cumulative),
                        bits(&expected_cumulative),
                        "σ {extinction}"
                    );
                }
            }
        }
    }

    /// [`texel_keys`] keeps, sorted, exactly the keys of every other sample strictly
    /// between its bounds, on every slice of a map with shadowed, lit and empty samples
    /// (infinite keys), under bounds inside, around and outside the keys.
    #[test]
    fn texel_keys_are_the_sorted_keys_strictly_between_the_bounds_before_the_reach() {
        use rand::{RngExt, SeedableRng};
        let scene = crate::builtin_scene("tree").expect("built-in scene");
        let (_, map, _) = frame_inputs(&scene);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let mut kept_some = 0;
        for slice in 0..map.slices as usize {
            let keys: Vec<f64> = map
                .row(slice as u32)
                .iter()
                .step_by(SAMPLES_PER_ROW)
                .map(|&value| map.order_key(value as f64))
                .collect();
            let finite: Vec<f64> = keys.iter().copied().filter(|k| k.is_finite()).collect();
            let pick = |rng: &mut rand_pcg::Pcg64| match rng.random_range(0..4) {
                0 => f64::NEG_INFINITY,
                1 => f64::INFINITY,
                _ if finite.is_empty() => 0.0,
                _ => finite[rng.random_range(0..finite.len())],
            };
            let (a, b) = (pick(&mut rng), pick(&mut rng));
            let (lowest, highest) = (a.min(b), a.max(b));
            // Samples before a random reach, or all of them.
            let reach = match rng.random_range(0..3) {
                0 => usize::MAX,
                _ => rng.random_range(0..map.samples as usize + 8),
            };
            let mut expected: Vec<f64> = keys
                .iter()
                .enumerate()
                .filter(|&(index, &key)| {
                    index * SAMPLES_PER_ROW < reach && key > lowest && key < highest
                })
                .map(|(_, &key)| key)
                .collect();
            expected.sort_by(f64::total_cmp);
            let kept = texel_keys(&map, slice, lowest, highest, reach);
            let bits = |keys: &[f64]| keys.iter().map(|k| k.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&kept), bits(&expected), "slice {slice}");
            kept_some += usize::from(!kept.is_empty() && kept.len() < keys.len());
        }
        assert!(
            kept_some > map.slices as usize / 8,
            "{kept_some} slices kept a part"
        );
    }

    /// [`frame_of`] over rays as [`slice_frames`] gives them.
    fn frame_of_rays(
        rays: &[SampledRay],
        texels: impl FnOnce(f64, f64) -> Vec<f64>,
    ) -> Option<(SliceFrame, SortedRays, Vec<f64>)> {
        let mut extremes = RayExtremes::NONE;
        let mut keyed: Vec<(u64, f64)> = rays
            .iter()
            .map(|ray| {
                extremes.include(ray);
                (total_order_bits(ray.key), ray.rate.log2())
            })
            .collect();
        frame_of(&mut keyed, extremes, 1, texels)
    }

    #[test]
    fn warp_is_monotone_and_puts_ray_keys_inside_the_margins() {
        let rays: Vec<SampledRay> = (0..100)
            .map(|i| SampledRay {
                key: (i as f64 * 0.37).sin() * 3.0 + i as f64 * 0.01,
                rate: 1.0 + i as f64,
                origin: 0.0,
                medium_entry: Some(0.0),
            })
            .collect();
        let (frame, sorted, _) = frame_of_rays(&rays, |_, _| Vec::new()).expect("a frame");
        let mut keys: Vec<f64> = rays.iter().map(|ray| ray.key).collect();
        keys.sort_by(f64::total_cmp);
        assert_eq!(sorted.keys, keys);
        let (lo, hi) = (keys[0], keys[99]);
        assert!((frame.warp.warp(lo) - RAY_MARGIN).abs() < 1e-9);
        assert!((frame.warp.warp(hi) - (1.0 - RAY_MARGIN)).abs() < 1e-9);
        let mut last = -1.0;
        for i in 0..=1000 {
            let key = lo - 5.0 + (hi - lo + 10.0) * i as f64 / 1000.0;
            let z = frame.warp.warp(key);
            assert!((0.0..=1.0).contains(&z) && z >= last);
            last = z;
        }
        assert_eq!((frame.fastest, frame.slowest), (100.0, 1.0));
    }

    #[test]
    fn inner_knots_at_or_below_count_like_comparing_each() {
        let knots: [f64; KNOTS] = std::array::from_fn(|i| (i as f64 - 3.0) * 0.37);
        let warp = Warp::from_knots(knots);
        let mut keys = vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, 0.0];
        keys.extend(knots);
        keys.extend(knots.map(|k| k - 1e-12));
        keys.extend((0..200).map(|i| -1.5 + i as f64 * 0.0175));
        for key in keys {
            let each = knots[1..KNOTS - 1].iter().filter(|&&k| k <= key).count();
            assert_eq!(warp.inner_knots_at_or_below(key), each, "key {key}");
        }
    }

    /// `unwarp` inverts the warp over [0, 1], on the knots and between them (where the
    /// exact ends' width is measured: ray keys are the knots, where the warp's slope jumps),
    /// and in the margins of warps that span keys beyond their knots.
    #[test]
    fn unwarp_inverts_the_warp() {
        let knots = [
            -0.36, -0.352_213, -0.352_212, -0.24, -0.12, -0.11, -0.10, 0.07, 0.19,
        ];
        let plain = Warp::from_knots(knots);
        for warp in [
            plain,
            plain.spanning(-0.9, 0.5),
            plain.spanning(-0.36, 2.0),
            plain.spanning(-0.361, 0.19),
        ] {
            for i in 0..=1000 {
                let z = i as f64 / 1000.0;
                let key = warp.unwarp(z);
                assert!((warp.warp(key) - z).abs() < 1e-9, "z {z}: key {key}");
            }
            for knot in knots {
                assert!(
                    (warp.unwarp(warp.warp(knot)) - knot).abs() < 1e-12,
                    "{knot}"
                );
            }
        }
    }

    /// A band's warp spanning its slice's keys keeps them apart in its margins, where its
    /// own end segments had sent them all to 0 or 1, and warps its own keys as before.
    #[test]
    fn warps_spanning_outer_keys_keep_them_apart_in_the_margins() {
        let knots: [f64; KNOTS] = std::array::from_fn(|i| 0.01 * i as f64);
        let plain = Warp::from_knots(knots);
        let (lowest, highest) = (-1.0, 0.5);
        let spanning = plain.spanning(lowest, highest);
        // Keys a tenth of the way out already left the plain warp at 0 and 1.
        assert_eq!(plain.warp(-0.1), 0.0);
        assert_eq!(plain.warp(0.13), 1.0);
        let mut last = -1.0;
        for i in 0..=3000 {
            let key = -1.5 + 2.5 * i as f64 / 3000.0;
            let z = spanning.warp(key);
            assert!((0.0..=1.0).contains(&z) && z >= last, "key {key}: {z}");
            if (lowest..=knots[0]).contains(&key) && key > lowest {
                assert!(z > last && z <= RAY_MARGIN, "key {key}: {z} after {last}");
            }
            if (knots[KNOTS - 1]..highest).contains(&key) {
                assert!(
                    z > last && z >= 1.0 - RAY_MARGIN,
                    "key {key}: {z} after {last}"
                );
            }
            if (knots[0]..=knots[KNOTS - 1]).contains(&key) {
                assert_eq!(z, plain.warp(key), "key {key}");
            }
            last = z;
        }
        assert_eq!(spanning.warp(lowest), 0.0);
        assert_eq!(spanning.warp(highest), 1.0);
        // Near its knots the margin keeps the end segment's resolution.
        let near = knots[0] - 0.001;
        assert_eq!(spanning.warp(near), plain.warp(near));
        // Keys that the end segments keep inside (0, 1) leave the warp as it was.
        assert!(plain.spanning(0.0, 0.08).outer.is_none());
        assert!(plain.spanning(-0.005, 0.085).outer.is_none());
    }

    /// Every kernel gives each key the table index of its warp bit for bit, in groups of
    /// four and in the rest: keys on and between the knots, outside them, ±∞, NaN and ±0.
    #[test]
    fn table_indices_are_the_warps_indices_with_every_kernel() {
        let texels: Vec<f64> = (0..40).map(|i| -1.0 + 0.1 * i as f64).collect();
        let rays: Vec<f64> = (0..200).map(|i| (i as f64 * 0.61).sin() * 2.0).collect();
        let mut sorted = rays.clone();
        sorted.sort_by(f64::total_cmp);
        let plain = Warp::of(&sorted, &texels);
        for warp in [plain, plain.spanning(-2.5, 2.2), plain.spanning(-1.99, 2.9)] {
            table_indices_match_the_warp(warp);
        }
    }

    fn table_indices_match_the_warp(warp: Warp) {
        let mut keys: Vec<f64> = warp.knots.to_vec();
        keys.extend(warp.knots.iter().map(|k| k + 1e-12));
        keys.extend((0..=400).map(|i| -3.0 + 6.0 * i as f64 / 400.0));
        keys.extend([
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            0.0,
            -0.0,
            1e300,
            -1e300,
        ]);
        let expected: Vec<u32> = keys
            .iter()
            .map(|&key| Tables::index(warp.warp(key)) as u32)
            .collect();
        let mut kernels = vec![Kernels::Portable];
        #[cfg(target_arch = "x86_64")]
        if let Kernels::Avx2Fma = Kernels::detect() {
            kernels.push(Kernels::Avx2Fma);
        }
        for kernels in kernels {
            for count in [keys.len(), keys.len() - 1, 5, 3, 0] {
                // One entry more than keys: it keeps its value.
                let mut entries = vec![u32::MAX; count + 1];
                warp.table_indices(kernels, &keys[..count], &mut entries);
                assert_eq!(
                    &entries[..count],
                    &expected[..count],
                    "{kernels:?}, {count} keys"
                );
                assert_eq!(entries[count], u32::MAX);
            }
        }
    }

    /// Texel keys among the rays' share the knots with them: a cluster of occluder keys
    /// just above most rays gets half the warped range, texels beyond the rays none.
    #[test]
    fn knots_follow_texels_among_the_rays() {
        let rays: Vec<SampledRay> = (0..=100)
            .map(|i| SampledRay {
                key: i as f64 / 100.0,
                rate: 1.0,
                origin: 0.0,
                medium_entry: Some(0.0),
            })
            .collect();
        let (alone, ..) = frame_of_rays(&rays, |_, _| Vec::new()).expect("a frame");
        let mut texels: Vec<f64> = (0..1000).map(|i| 0.5 + i as f64 * 1e-4).collect();
        texels.extend([-5.0, 0.0, 1.0, 7.0]);
        texels.sort_unstable_by(|a, b| a.total_cmp(b));
        // The warps read only the texels strictly between the rays' keys, all that
        // `texel_keys` gives them.
        let (mixed, ..) = frame_of_rays(&rays, |lowest, highest| {
            assert_eq!((lowest, highest), (0.0, 1.0));
            texels
                .iter()
                .copied()
                .filter(|&key| key > lowest && key < highest)
                .collect()
        })
        .expect("a frame");
        let (unfiltered, ..) = frame_of_rays(&rays, |_, _| texels.clone()).expect("a frame");
        assert_eq!(mixed.warp.knots, unfiltered.warp.knots);
        assert_eq!(
            (mixed.warp.knots[0], mixed.warp.knots[KNOTS - 1]),
            (0.0, 1.0)
        );
        // Rays alone: knots at eighths. With the cluster in [0.5, 0.6], keys 0.5 and 0.6
        // are warped apart by about half the range rather than a tenth of it.
        assert!((alone.warp.knots[4] - 0.5).abs() < 0.011);
        let gap = |f: &SliceFrame| f.warp.warp(0.6) - f.warp.warp(0.5);
        assert!(gap(&alone) < 0.09, "{}", gap(&alone));
        assert!(gap(&mixed) > 0.35, "{}", gap(&mixed));
        let mut last = f64::NEG_INFINITY;
        for knot in mixed.warp.knots {
            assert!(knot > last);
            last = knot;
        }
    }

    /// Bands cover the slice's speeds in steps of 2^(1/n) from the fastest ray down, n
    /// an octave, up to `MAX_OCTAVES`, and every ray falls between two adjacent bands
    /// that bracket its speed.
    #[test]
    fn bands_bracket_every_ray() {
        for n in 1..=MAX_BANDS_PER_OCTAVE {
            let frame = SliceFrame {
                warp: Warp::from_knots(std::array::from_fn(|i| i as f64)),
                fastest: 300.0,
                slowest: 0.7,
                origin: 0.0,
                medium_start: Some(0.0),
                log2_fastest: 300.0f64.log2(),
                bands_per_octave: n,
            };
            let count = frame.band_count();
            let n = n as usize;
            assert_eq!(
                count,
                MAX_OCTAVES * n + 1,
                "300/0.7 needs ⌈{n}·log₂ 429⌉ + 1 bands, capped at {MAX_OCTAVES} octaves"
            );
            assert_eq!(frame.band_rate(0), 300.0);
            assert_eq!(frame.band_rate(n), 150.0, "an octave every {n} bands");
            for rate in [300.0, 150.0, 74.9, 20.0, 4.7, 2.4, 0.9] {
                let position = frame.band_position(f64::log2(rate), count);
                let lower = position.floor() as usize;
                assert!(frame.band_rate(lower) >= rate * (1.0 - 1e-9), "rate {rate}");
                if lower + 1 < count {
                    assert!(
                        frame.band_rate(lower + 1) <= rate * (1.0 + 1e-9),
                        "rate {rate}"
                    );
                    let share = position - lower as f64;
                    let expected = (frame.band_rate(lower) / rate).log2() * n as f64;
                    assert!((share - expected).abs() < 1e-9, "rate {rate}");
                }
            }
            let few = SliceFrame {
                slowest: 40.0,
                ..frame
            };
            let octaves = (300.0f64 / 40.0).log2();
            let needed = (octaves * n as f64).ceil() as usize + 1;
            assert_eq!(
                few.band_count(),
                needed,
                "300/40 needs ⌈{n}·log₂ 7.5⌉ + 1 bands"
            );
            let position = few.band_position(40.0f64.log2(), needed);
            assert!((position - octaves * n as f64).abs() < 1e-12);
            let single = SliceFrame {
                fastest: 10.0,
                slowest: 10.0,
                log2_fastest: 10.0f64.log2(),
                ..frame
            };
            assert_eq!(single.band_count(), 1);
            assert_eq!(single.band_position(10.0f64.log2(), 1), 0.0);
        }
    }

    /// A box's longest chord is its longest diagonal: a slab's, a sheared box's.
    #[test]
    fn a_box_is_crossed_along_its_longest_diagonal_at_most() {
        let slab = Mat4::from_scale(glam::Vec3::new(8.0, 8.0, 3.0));
        let expected = (16.0f64 * 16.0 + 16.0 * 16.0 + 6.0 * 6.0).sqrt();
        assert!((longest_chord(&slab) - expected).abs() < 1e-9);
        let moved = Mat4::from_translation(glam::Vec3::new(100.0, -50.0, 7.0)) * slab;
        assert!(
            (longest_chord(&moved) - expected).abs() < 1e-9,
            "not its place"
        );
        let sheared = Mat4::from_cols(
            glam::Vec4::new(1.0, 0.0, 0.0, 0.0),
            glam::Vec4::new(1.0, 1.0, 0.0, 0.0),
            glam::Vec4::new(0.0, 0.0, 1.0, 0.0),
            glam::Vec4::W,
        );
        // Corners (±1 ± 1, ±1, ±1): the diagonal from (−2, −1, −1) to (2, 1, 1).
        assert!((longest_chord(&sheared) - (16.0f64 + 4.0 + 4.0).sqrt()).abs() < 1e-9);
    }

    /// Octaves in thin media, more bands an octave as the optical depth of the tables'
    /// reach grows, up to the most.
    #[test]
    fn denser_media_take_more_bands_an_octave() {
        assert_eq!(bands_per_octave(0.05, 70.0), 1, "the built-in scenes' fog");
        assert_eq!(bands_per_octave(0.0, 70.0), 1, "no medium");
        assert_eq!(bands_per_octave(0.1, 50.0), 1);
        assert_eq!(bands_per_octave(0.1, 70.0), 2);
        assert_eq!(bands_per_octave(0.2, 70.0), 3);
        assert_eq!(bands_per_octave(1.5, 70.0), MAX_BANDS_PER_OCTAVE);
        assert_eq!(bands_per_octave(f64::NAN, 70.0), 1);
    }
}
