//! The inner loops of prefiltering: accumulating basis rows into prefix sums, and
//! blending filtered rows into one dot product per pixel. Each is written once over
//! lanes of [`LANES`] and compiled twice, portable and with AVX2 + FMA; [`Kernels`]
//! picks one per frame, so a build runs everywhere and uses what the CPU has.

/// Rows are padded to a multiple of this many values, with zeros.
pub const LANES: usize = 8;

/// A filtered-basis value as stored: normalized means lie in [−1, 1], so a 16-bit
/// signed normalized integer keeps them to 1.5·10⁻⁵ at half the memory of f32.
pub trait BasisValue: Copy + Default + Send + Sync {
    /// What the stored value times `SCALE` is worth.
    const SCALE: f32;
    fn store(value: f32) -> Self;
    fn load(self) -> f32;
    /// [`BasisValue::load`] of eight values at once, for the AVX2 kernels.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    unsafe fn load_lanes(values: &[Self; LANES]) -> std::arch::x86_64::__m256;
    /// [`BasisValue::store`] of eight values at once, bit for bit.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    unsafe fn store_lanes(values: std::arch::x86_64::__m256, out: &mut [Self; LANES]);
}

impl BasisValue for f32 {
    const SCALE: f32 = 1.0;
    #[inline(always)]
    fn store(value: f32) -> Self {
        value
    }
    #[inline(always)]
    fn load(self) -> f32 {
        self
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load_lanes(values: &[Self; LANES]) -> std::arch::x86_64::__m256 {
        std::arch::x86_64::_mm256_loadu_ps(values.as_ptr())
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn store_lanes(values: std::arch::x86_64::__m256, out: &mut [Self; LANES]) {
        std::arch::x86_64::_mm256_storeu_ps(out.as_mut_ptr(), values)
    }
}

impl BasisValue for i16 {
    const SCALE: f32 = 1.0 / i16::MAX as f32;
    #[inline(always)]
    fn store(value: f32) -> Self {
        // Round half away from zero without a libm call; the clamp keeps ±1 in range, and
        // NaN (never expected) stores 0 as a saturating cast would. Saturating casts do not
        // vectorize, and storing was most of the prefix sums' instructions.
        let scaled = value * i16::MAX as f32;
        let scaled = if scaled.is_nan() {
            0.0
        } else {
            scaled.clamp(-(i16::MAX as f32), i16::MAX as f32)
        };
        let rounded = scaled + 0.5f32.copysign(scaled);
        // SAFETY: `rounded` is finite and within ±32767.5, so its truncation fits an i32.
        unsafe { rounded.to_int_unchecked::<i32>() as i16 }
    }
    #[inline(always)]
    fn load(self) -> f32 {
        self as f32
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load_lanes(values: &[Self; LANES]) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        let packed = _mm_loadu_si128(values.as_ptr().cast());
        _mm256_cvtepi32_ps(_mm256_cvtepi16_epi32(packed))
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn store_lanes(values: std::arch::x86_64::__m256, out: &mut [Self; LANES]) {
        use std::arch::x86_64::*;
        let limit = _mm256_set1_ps(i16::MAX as f32);
        let scaled = _mm256_mul_ps(values, limit);
        let clamped = _mm256_min_ps(
            _mm256_max_ps(scaled, _mm256_sub_ps(_mm256_setzero_ps(), limit)),
            limit,
        );
        // NaN lanes store 0, as `store` does.
        let scaled = _mm256_and_ps(clamped, _mm256_cmp_ps::<_CMP_ORD_Q>(scaled, scaled));
        let sign = _mm256_and_ps(scaled, _mm256_set1_ps(-0.0));
        let rounded = _mm256_add_ps(scaled, _mm256_or_ps(sign, _mm256_set1_ps(0.5)));
        let integers = _mm256_cvttps_epi32(rounded);
        // Packed per 128-bit half; the permute brings both halves' four values together.
        let packed = _mm256_permute4x64_epi64::<0b1000>(_mm256_packs_epi32(integers, integers));
        _mm_storeu_si128(out.as_mut_ptr().cast(), _mm256_castsi256_si128(packed));
    }
}

/// The length a row of `values` takes once padded to whole lanes.
pub fn padded(values: usize) -> usize {
    values.div_ceil(LANES) * LANES
}

/// The instruction set the kernels run with, detected once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernels {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2Fma,
}

impl Kernels {
    pub fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            return Kernels::Avx2Fma;
        }
        Kernels::Portable
    }

    /// Σ over `reads` of Σ_r factor_r · ⟨stored row index_r, the read's coefficients⟩,
    /// over padded rows of `stored`: one call and one horizontal sum for all the bands a
    /// pixel reads in one slice.
    #[inline]
    pub fn blend_dots<T: BasisValue>(self, stored: &[T], reads: &[BandRead<'_>]) -> f32 {
        match self {
            Kernels::Portable => blend_dots(stored, reads),
            // SAFETY: `detect` only chose this variant where the CPU has AVX2 and FMA.
            #[cfg(target_arch = "x86_64")]
            Kernels::Avx2Fma => unsafe { blend_dots_avx2(stored, reads) },
        }
    }

    /// [`Kernels::blend_dots`] of `reads`, and of the same reads with `others[i]` in place of
    /// read i's coefficients (one per read), each read's rows blended once for both: the
    /// first bit for bit what `blend_dots` gives.
    #[inline]
    pub fn blend_dots_twice<T: BasisValue>(
        self,
        stored: &[T],
        reads: &[BandRead<'_>],
        others: &[&[f32]],
    ) -> [f32; 2] {
        match self {
            Kernels::Portable => blend_dots_twice(stored, reads, others),
            // SAFETY: as in `blend_dots`.
            #[cfg(target_arch = "x86_64")]
            Kernels::Avx2Fma => unsafe { blend_dots_twice_avx2(stored, reads, others) },
        }
    }

    /// For each of `boundaries` (a row and the factors of it and the next), those two
    /// rows blended and dotted with `coefficients`, into `out` (as many as both hold):
    /// bit for bit [`Kernels::blend_dots`] of each as a read of its own, in one call for
    /// the many boundaries a ray in a box reads per band.
    #[inline]
    pub fn boundary_dots<T: BasisValue>(
        self,
        stored: &[T],
        coefficients: &[f32],
        boundaries: &[(u32, [f32; 2])],
        out: &mut [f32],
    ) {
        match self {
            Kernels::Portable => {
                for (&boundary, out) in boundaries.iter().zip(out) {
                    *out = blend_dots(stored, &[BandRead::of_boundary(boundary, coefficients)]);
                }
            }
            // SAFETY: as in `blend_dots`.
            #[cfg(target_arch = "x86_64")]
            Kernels::Avx2Fma => unsafe {
                boundary_dots_avx2(stored, coefficients, boundaries, out)
            },
        }
    }

    /// Running prefix sums of weighted basis rows: for each sample i, in order,
    /// `sums += weights[i] · table row entries[i]`; after every k-th sample (k =
    /// `entries.len() / scales.len()`, the samples per output row) output row r becomes
    /// `sums · scales[r]`. Rows are padded; `out` holds one row per scale.
    #[inline]
    pub fn prefix_sums<T: BasisValue>(
        self,
        table: &[f32],
        entries: &[u32],
        weights: &[f32],
        scales: &[f32],
        out: &mut [T],
    ) {
        match self {
            Kernels::Portable => prefix_sums(table, entries, weights, scales, out),
            // SAFETY: as in `blend_dots`.
            #[cfg(target_arch = "x86_64")]
            Kernels::Avx2Fma => unsafe { prefix_sums_avx2(table, entries, weights, scales, out) },
        }
    }
}

/// What a pixel reads from one band: up to four weighted rows of the filtered basis,
/// dotted with the coefficients of the ray's key.
#[derive(Clone, Copy, Debug)]
pub struct BandRead<'c> {
    pub rows: [(u32, f32); 4],
    pub count: usize,
    pub coefficients: &'c [f32],
}

impl<'c> BandRead<'c> {
    /// The read of one boundary: `row` and the next, weighted by `factors`.
    #[inline]
    pub fn of_boundary((row, factors): (u32, [f32; 2]), coefficients: &'c [f32]) -> Self {
        Self {
            rows: [(row, factors[0]), (row + 1, factors[1]), (0, 0.0), (0, 0.0)],
            count: 2,
            coefficients,
        }
    }
}

/// Dispatches to [`blend_dots_fixed`] for every padded stride of M = 4…64 (a constant
/// stride unrolls the lanes and keeps the blended row in registers: the general loop
/// spent more instructions on indices than on arithmetic).
#[inline(always)]
fn blend_dots<T: BasisValue>(stored: &[T], reads: &[BandRead<'_>]) -> f32 {
    match reads.first().map_or(0, |read| read.coefficients.len()) {
        8 => blend_dots_fixed::<T, 8>(stored, reads),
        16 => blend_dots_fixed::<T, 16>(stored, reads),
        24 => blend_dots_fixed::<T, 24>(stored, reads),
        32 => blend_dots_fixed::<T, 32>(stored, reads),
        40 => blend_dots_fixed::<T, 40>(stored, reads),
        48 => blend_dots_fixed::<T, 48>(stored, reads),
        56 => blend_dots_fixed::<T, 56>(stored, reads),
        64 => blend_dots_fixed::<T, 64>(stored, reads),
        _ => blend_dots_any(stored, reads),
    }
}

/// [`blend_dots_any`] for reads whose coefficient rows all hold `STRIDE` values, in the
/// same order of operations, so the result is identical.
#[inline(always)]
fn blend_dots_fixed<T: BasisValue, const STRIDE: usize>(
    stored: &[T],
    reads: &[BandRead<'_>],
) -> f32 {
    let mut total = [0.0f32; LANES];
    for read in reads {
        let Ok(coefficients) = <&[f32; STRIDE]>::try_from(read.coefficients) else {
            return blend_dots_any(stored, reads);
        };
        let mut blended = [0.0f32; STRIDE];
        for &(index, factor) in &read.rows[..read.count] {
            let Some(values) = stored[index as usize * STRIDE..].first_chunk::<STRIDE>() else {
                return blend_dots_any(stored, reads);
            };
            let factor = factor * T::SCALE;
            for (blended, value) in blended.iter_mut().zip(values) {
                *blended += factor * value.load();
            }
        }
        for (blended, coefficients) in blended
            .chunks_exact(LANES)
            .zip(coefficients.chunks_exact(LANES))
        {
            for lane in 0..LANES {
                total[lane] += blended[lane] * coefficients[lane];
            }
        }
    }
    total.iter().sum()
}

/// [`Kernels::blend_dots_twice`] as two calls of [`blend_dots`]: the second read by read,
/// as no kernel holds two reads' other rows at once.
fn blend_dots_twice<T: BasisValue>(
    stored: &[T],
    reads: &[BandRead<'_>],
    others: &[&[f32]],
) -> [f32; 2] {
    let second = reads
        .iter()
        .zip(others)
        .map(|(read, &coefficients)| {
            blend_dots(
                stored,
                &[BandRead {
                    coefficients,
                    ..*read
                }],
            )
        })
        .sum();
    [blend_dots(stored, reads), second]
}

#[inline(always)]
fn blend_dots_any<T: BasisValue>(stored: &[T], reads: &[BandRead<'_>]) -> f32 {
    let mut total = [0.0f32; LANES];
    for read in reads {
        let stride = read.coefficients.len();
        let rows = &read.rows[..read.count];
        for (lane_start, coefficients) in (0..stride)
            .step_by(LANES)
            .zip(read.coefficients.chunks_exact(LANES))
        {
            let mut blended = [0.0f32; LANES];
            for &(index, factor) in rows {
                let start = index as usize * stride + lane_start;
                let values = &stored[start..start + LANES];
                let factor = factor * T::SCALE;
                for lane in 0..LANES {
                    blended[lane] += factor * values[lane].load();
                }
            }
            for lane in 0..LANES {
                total[lane] += blended[lane] * coefficients[lane];
            }
        }
    }
    total.iter().sum()
}

/// [`blend_dots`] in AVX2 + FMA: the same sum, with fused multiply-adds. Written in
/// intrinsics because the compiler vectorized the portable loop or not depending on
/// how its total was summed, and never fuses on its own.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn blend_dots_avx2<T: BasisValue>(stored: &[T], reads: &[BandRead<'_>]) -> f32 {
    match reads.first().map_or(0, |read| read.coefficients.len()) {
        8 => blend_dots_fixed_avx2::<T, 8, 1>(stored, reads),
        16 => blend_dots_fixed_avx2::<T, 16, 2>(stored, reads),
        24 => blend_dots_fixed_avx2::<T, 24, 3>(stored, reads),
        32 => blend_dots_fixed_avx2::<T, 32, 4>(stored, reads),
        40 => blend_dots_fixed_avx2::<T, 40, 5>(stored, reads),
        48 => blend_dots_fixed_avx2::<T, 48, 6>(stored, reads),
        56 => blend_dots_fixed_avx2::<T, 56, 7>(stored, reads),
        64 => blend_dots_fixed_avx2::<T, 64, 8>(stored, reads),
        _ => blend_dots_any(stored, reads),
    }
}

/// [`Kernels::blend_dots_twice`] in AVX2 + FMA, dispatched on the stride as
/// [`blend_dots_avx2`] is.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn blend_dots_twice_avx2<T: BasisValue>(
    stored: &[T],
    reads: &[BandRead<'_>],
    others: &[&[f32]],
) -> [f32; 2] {
    match reads.first().map_or(0, |read| read.coefficients.len()) {
        8 => blend_dots_twice_fixed_avx2::<T, 8, 1>(stored, reads, others),
        16 => blend_dots_twice_fixed_avx2::<T, 16, 2>(stored, reads, others),
        24 => blend_dots_twice_fixed_avx2::<T, 24, 3>(stored, reads, others),
        32 => blend_dots_twice_fixed_avx2::<T, 32, 4>(stored, reads, others),
        40 => blend_dots_twice_fixed_avx2::<T, 40, 5>(stored, reads, others),
        48 => blend_dots_twice_fixed_avx2::<T, 48, 6>(stored, reads, others),
        56 => blend_dots_twice_fixed_avx2::<T, 56, 7>(stored, reads, others),
        64 => blend_dots_twice_fixed_avx2::<T, 64, 8>(stored, reads, others),
        _ => blend_dots_twice(stored, reads, others),
    }
}

/// [`blend_dots_twice_avx2`] with `STRIDE` = 8·`VECTORS` values per row: each read's rows
/// blended once, as [`blend_dots_fixed_avx2`] blends them, and dotted into two sets of
/// accumulators, the first operation for operation as there.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn blend_dots_twice_fixed_avx2<T: BasisValue, const STRIDE: usize, const VECTORS: usize>(
    stored: &[T],
    reads: &[BandRead<'_>],
    others: &[&[f32]],
) -> [f32; 2] {
    use std::arch::x86_64::*;
    const { assert!(STRIDE == VECTORS * LANES) };
    let mut totals = [[_mm256_setzero_ps(); VECTORS]; 2];
    if others.len() < reads.len() {
        return blend_dots_twice(stored, reads, others);
    }
    for (read, &other) in reads.iter().zip(others) {
        let (Ok(first), Ok(second)) = (
            <&[f32; STRIDE]>::try_from(read.coefficients),
            <&[f32; STRIDE]>::try_from(other),
        ) else {
            return blend_dots_twice(stored, reads, others);
        };
        let Some(blended) = blended_avx2::<T, STRIDE, VECTORS>(stored, read) else {
            return blend_dots_twice(stored, reads, others);
        };
        for (totals, coefficients) in totals.iter_mut().zip([first, second]) {
            accumulate_dot_avx2(totals, &blended, coefficients);
        }
    }
    totals.map(|totals| total_of_avx2(&totals))
}

/// [`Kernels::boundary_dots`] in AVX2 + FMA, dispatched on the stride as
/// [`blend_dots_avx2`] is.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn boundary_dots_avx2<T: BasisValue>(
    stored: &[T],
    coefficients: &[f32],
    boundaries: &[(u32, [f32; 2])],
    out: &mut [f32],
) {
    match coefficients.len() {
        8 => boundary_dots_fixed_avx2::<T, 8, 1>(stored, coefficients, boundaries, out),
        16 => boundary_dots_fixed_avx2::<T, 16, 2>(stored, coefficients, boundaries, out),
        24 => boundary_dots_fixed_avx2::<T, 24, 3>(stored, coefficients, boundaries, out),
        32 => boundary_dots_fixed_avx2::<T, 32, 4>(stored, coefficients, boundaries, out),
        40 => boundary_dots_fixed_avx2::<T, 40, 5>(stored, coefficients, boundaries, out),
        48 => boundary_dots_fixed_avx2::<T, 48, 6>(stored, coefficients, boundaries, out),
        56 => boundary_dots_fixed_avx2::<T, 56, 7>(stored, coefficients, boundaries, out),
        64 => boundary_dots_fixed_avx2::<T, 64, 8>(stored, coefficients, boundaries, out),
        _ => boundary_dots_any(stored, coefficients, boundaries, out),
    }
}

/// [`Kernels::boundary_dots`] through [`blend_dots_any`], for strides without a kernel
/// of their own.
fn boundary_dots_any<T: BasisValue>(
    stored: &[T],
    coefficients: &[f32],
    boundaries: &[(u32, [f32; 2])],
    out: &mut [f32],
) {
    for (&boundary, out) in boundaries.iter().zip(out) {
        *out = blend_dots_any(stored, &[BandRead::of_boundary(boundary, coefficients)]);
    }
}

/// [`boundary_dots_avx2`] with `STRIDE` = 8·`VECTORS` values per row: the coefficients
/// loaded once, and each boundary's rows blended and dotted as
/// [`blend_dots_fixed_avx2`] does for a single read, operation for operation.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn boundary_dots_fixed_avx2<T: BasisValue, const STRIDE: usize, const VECTORS: usize>(
    stored: &[T],
    coefficients: &[f32],
    boundaries: &[(u32, [f32; 2])],
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    const { assert!(STRIDE == VECTORS * LANES) };
    let Ok(row_of_coefficients) = <&[f32; STRIDE]>::try_from(coefficients) else {
        return boundary_dots_any(stored, coefficients, boundaries, out);
    };
    let loaded: [__m256; VECTORS] = std::array::from_fn(|v| {
        // The chunk holds exactly LANES values, all that the unaligned load reads.
        _mm256_loadu_ps(row_of_coefficients[v * LANES..].as_ptr())
    });
    for (&(row, factors), out) in boundaries.iter().zip(out) {
        let rows = (
            stored[row as usize * STRIDE..].first_chunk::<STRIDE>(),
            stored[(row as usize + 1) * STRIDE..].first_chunk::<STRIDE>(),
        );
        let (Some(lower), Some(upper)) = rows else {
            *out = blend_dots_any(
                stored,
                &[BandRead::of_boundary((row, factors), coefficients)],
            );
            continue;
        };
        let mut blended = [_mm256_setzero_ps(); VECTORS];
        for (values, factor) in [lower, upper].into_iter().zip(factors) {
            let factor = _mm256_set1_ps(factor * T::SCALE);
            for (blended, lanes) in blended.iter_mut().zip(values.chunks_exact(LANES)) {
                let lanes = T::load_lanes(lanes.try_into().unwrap_or(&[T::default(); LANES]));
                *blended = _mm256_fmadd_ps(factor, lanes, *blended);
            }
        }
        let mut sum = _mm256_setzero_ps();
        for (blended, coefficients) in blended.into_iter().zip(loaded) {
            sum = _mm256_add_ps(
                sum,
                _mm256_fmadd_ps(blended, coefficients, _mm256_setzero_ps()),
            );
        }
        *out = horizontal_sum(sum);
    }
}

/// One pixel's reads with `STRIDE` = 8·`VECTORS` values per row: each read's rows are
/// blended in `VECTORS` registers and dotted with its coefficients into as many
/// accumulators, summed once at the end.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn blend_dots_fixed_avx2<T: BasisValue, const STRIDE: usize, const VECTORS: usize>(
    stored: &[T],
    reads: &[BandRead<'_>],
) -> f32 {
    use std::arch::x86_64::*;
    const { assert!(STRIDE == VECTORS * LANES) };
    let mut totals = [_mm256_setzero_ps(); VECTORS];
    for read in reads {
        let Ok(coefficients) = <&[f32; STRIDE]>::try_from(read.coefficients) else {
            return blend_dots_any(stored, reads);
        };
        let Some(blended) = blended_avx2::<T, STRIDE, VECTORS>(stored, read) else {
            return blend_dots_any(stored, reads);
        };
        accumulate_dot_avx2(&mut totals, &blended, coefficients);
    }
    total_of_avx2(&totals)
}

/// `totals` += `blended` × `coefficients`, lane by lane, one fused multiply-add a register.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn accumulate_dot_avx2<const STRIDE: usize, const VECTORS: usize>(
    totals: &mut [std::arch::x86_64::__m256; VECTORS],
    blended: &[std::arch::x86_64::__m256; VECTORS],
    coefficients: &[f32; STRIDE],
) {
    use std::arch::x86_64::*;
    for ((total, blended), coefficients) in totals
        .iter_mut()
        .zip(blended)
        .zip(coefficients.chunks_exact(LANES))
    {
        // The chunk holds exactly LANES values, all that the unaligned load reads.
        let coefficients = _mm256_loadu_ps(coefficients.as_ptr());
        *total = _mm256_fmadd_ps(*blended, coefficients, *total);
    }
}

/// The sum of all of `totals`' lanes: the registers in order, then [`horizontal_sum`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn total_of_avx2<const VECTORS: usize>(
    totals: &[std::arch::x86_64::__m256; VECTORS],
) -> f32 {
    use std::arch::x86_64::*;
    let mut sum = _mm256_setzero_ps();
    for &total in totals {
        sum = _mm256_add_ps(sum, total);
    }
    horizontal_sum(sum)
}

/// `read`'s rows of `stored` blended by their factors, in `VECTORS` registers; `None`
/// where a row lies past the end of `stored`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn blended_avx2<T: BasisValue, const STRIDE: usize, const VECTORS: usize>(
    stored: &[T],
    read: &BandRead<'_>,
) -> Option<[std::arch::x86_64::__m256; VECTORS]> {
    use std::arch::x86_64::*;
    let mut blended = [_mm256_setzero_ps(); VECTORS];
    for &(index, factor) in &read.rows[..read.count] {
        let values = stored[index as usize * STRIDE..].first_chunk::<STRIDE>()?;
        let factor = _mm256_set1_ps(factor * T::SCALE);
        for (blended, lanes) in blended.iter_mut().zip(values.chunks_exact(LANES)) {
            let lanes = T::load_lanes(lanes.try_into().unwrap_or(&[T::default(); LANES]));
            *blended = _mm256_fmadd_ps(factor, lanes, *blended);
        }
    }
    Some(blended)
}

/// The sum of `sum`'s eight lanes, halves first: the one order both dot kernels use, so
/// that a boundary dotted by [`boundary_dots_fixed_avx2`] is a read's sum to the bit.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn horizontal_sum(sum: std::arch::x86_64::__m256) -> f32 {
    use std::arch::x86_64::*;
    let half = _mm_add_ps(_mm256_castps256_ps128(sum), _mm256_extractf128_ps::<1>(sum));
    let pair = _mm_add_ps(half, _mm_movehl_ps(half, half));
    _mm_cvtss_f32(_mm_add_ss(pair, _mm_movehdup_ps(pair)))
}

/// Dispatches to [`prefix_sums_fixed`] for every padded stride of M = 4…64, as
/// [`blend_dots`] does.
#[inline(always)]
fn prefix_sums<T: BasisValue>(
    table: &[f32],
    entries: &[u32],
    weights: &[f32],
    scales: &[f32],
    out: &mut [T],
) {
    match out.len() / scales.len().max(1) {
        8 => prefix_sums_fixed::<T, 8>(table, entries, weights, scales, out),
        16 => prefix_sums_fixed::<T, 16>(table, entries, weights, scales, out),
        24 => prefix_sums_fixed::<T, 24>(table, entries, weights, scales, out),
        32 => prefix_sums_fixed::<T, 32>(table, entries, weights, scales, out),
        40 => prefix_sums_fixed::<T, 40>(table, entries, weights, scales, out),
        48 => prefix_sums_fixed::<T, 48>(table, entries, weights, scales, out),
        56 => prefix_sums_fixed::<T, 56>(table, entries, weights, scales, out),
        64 => prefix_sums_fixed::<T, 64>(table, entries, weights, scales, out),
        _ => prefix_sums_any(table, entries, weights, scales, out),
    }
}

/// [`prefix_sums_any`] with a constant stride: the running sums stay in registers. Same
/// arithmetic in the same order, so the same result.
#[inline(always)]
fn prefix_sums_fixed<T: BasisValue, const STRIDE: usize>(
    table: &[f32],
    entries: &[u32],
    weights: &[f32],
    scales: &[f32],
    out: &mut [T],
) {
    let per_row = samples_per_row(entries, scales);
    let mut sums = [0.0f32; STRIDE];
    let row_of = |entry: u32| table[entry as usize * STRIDE..].first_chunk::<STRIDE>();
    for (((row_entries, row_weights), &scale), row_out) in entries
        .chunks_exact(per_row.max(1))
        .zip(weights.chunks_exact(per_row.max(1)))
        .zip(scales)
        .zip(out.chunks_exact_mut(STRIDE))
    {
        for (&entry, &weight) in row_entries.iter().zip(row_weights) {
            let Some(values) = row_of(entry) else {
                return prefix_sums_any(table, entries, weights, scales, out);
            };
            for (sum, &value) in sums.iter_mut().zip(values) {
                *sum += weight * value;
            }
        }
        for (sum, out) in sums.iter().zip(row_out.iter_mut()) {
            *out = T::store(*sum * scale);
        }
    }
}

/// For the prefix sums: the samples summed into each output row. The fixed-stride
/// kernels hand an entry past the table to the general loop, which reports it; checking
/// every entry before summing took 2.5% of colonnade's preparation.
#[inline(always)]
fn samples_per_row(entries: &[u32], scales: &[f32]) -> usize {
    let per_row = entries.len() / scales.len().max(1);
    debug_assert_eq!(entries.len(), per_row * scales.len());
    per_row
}

#[inline(always)]
fn prefix_sums_any<T: BasisValue>(
    table: &[f32],
    entries: &[u32],
    weights: &[f32],
    scales: &[f32],
    out: &mut [T],
) {
    let stride = out.len() / scales.len().max(1);
    let per_row = samples_per_row(entries, scales);
    let mut sums = [0.0f32; crate::prefiltered::MAX_BASES as usize];
    let sums = &mut sums[..stride];
    for (((entries, weights), &scale), out) in entries
        .chunks_exact(per_row.max(1))
        .zip(weights.chunks_exact(per_row.max(1)))
        .zip(scales)
        .zip(out.chunks_exact_mut(stride))
    {
        // Chunks are never empty: the row's last sample is added and stored in one pass.
        let last = entries.len() - 1;
        for (&entry, &weight) in entries[..last].iter().zip(weights) {
            let values = &table[entry as usize * stride..][..stride];
            for (sum, &value) in sums.iter_mut().zip(values) {
                *sum += weight * value;
            }
        }
        let weight = weights[last];
        let values = &table[entries[last] as usize * stride..][..stride];
        for ((sum, &value), out) in sums.iter_mut().zip(values).zip(out.iter_mut()) {
            *sum += weight * value;
            *out = T::store(*sum * scale);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn prefix_sums_avx2<T: BasisValue>(
    table: &[f32],
    entries: &[u32],
    weights: &[f32],
    scales: &[f32],
    out: &mut [T],
) {
    match out.len() / scales.len().max(1) {
        8 => prefix_sums_fixed_avx2::<T, 8, 1>(table, entries, weights, scales, out),
        16 => prefix_sums_fixed_avx2::<T, 16, 2>(table, entries, weights, scales, out),
        24 => prefix_sums_fixed_avx2::<T, 24, 3>(table, entries, weights, scales, out),
        32 => prefix_sums_fixed_avx2::<T, 32, 4>(table, entries, weights, scales, out),
        40 => prefix_sums_fixed_avx2::<T, 40, 5>(table, entries, weights, scales, out),
        48 => prefix_sums_fixed_avx2::<T, 48, 6>(table, entries, weights, scales, out),
        56 => prefix_sums_fixed_avx2::<T, 56, 7>(table, entries, weights, scales, out),
        64 => prefix_sums_fixed_avx2::<T, 64, 8>(table, entries, weights, scales, out),
        _ => prefix_sums_any(table, entries, weights, scales, out),
    }
}

/// [`prefix_sums_fixed`] in AVX2 with the running sums in `VECTORS` registers, and the
/// same arithmetic in the same order (a multiply, then an add: no fusing), so the same
/// result. Left to the compiler, the sums were spilled to the stack and reloaded at
/// other offsets than they were stored, which stalled store forwarding on every sample
/// and doubled the kernel's time, or not, depending on unrelated code in the crate.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn prefix_sums_fixed_avx2<T: BasisValue, const STRIDE: usize, const VECTORS: usize>(
    table: &[f32],
    entries: &[u32],
    weights: &[f32],
    scales: &[f32],
    out: &mut [T],
) {
    use std::arch::x86_64::*;
    const { assert!(STRIDE == VECTORS * LANES) };
    let per_row = samples_per_row(entries, scales);
    let row_of = |entry: u32| table[entry as usize * STRIDE..].first_chunk::<STRIDE>();
    let mut sums = [_mm256_setzero_ps(); VECTORS];
    for (((row_entries, row_weights), &scale), row_out) in entries
        .chunks_exact(per_row.max(1))
        .zip(weights.chunks_exact(per_row.max(1)))
        .zip(scales)
        .zip(out.chunks_exact_mut(STRIDE))
    {
        for (&entry, &weight) in row_entries.iter().zip(row_weights) {
            let Some(values) = row_of(entry) else {
                return prefix_sums_any(table, entries, weights, scales, out);
            };
            let weight = _mm256_set1_ps(weight);
            for (sum, lanes) in sums.iter_mut().zip(values.chunks_exact(LANES)) {
                // The chunk holds exactly LANES values, all that the unaligned load reads.
                let lanes = _mm256_loadu_ps(lanes.as_ptr());
                *sum = _mm256_add_ps(*sum, _mm256_mul_ps(weight, lanes));
            }
        }
        let scale = _mm256_set1_ps(scale);
        for (sum, out) in sums.iter().zip(row_out.chunks_exact_mut(LANES)) {
            if let Ok(out) = <&mut [T; LANES]>::try_from(out) {
                T::store_lanes(_mm256_mul_ps(*sum, scale), out);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all_kernels() -> Vec<Kernels> {
        let mut kernels = vec![Kernels::Portable];
        if Kernels::detect() != Kernels::Portable {
            kernels.push(Kernels::detect());
        }
        kernels
    }

    #[test]
    fn snorm16_storage_keeps_unit_values_to_its_step() {
        for v in (0..64).map(|i| ((i as f32) * 0.7).sin()) {
            let loaded = i16::store(v).load() * i16::SCALE;
            assert!(
                (v - loaded).abs() <= 0.5 / i16::MAX as f32 + 1e-7,
                "{v} → {loaded}"
            );
        }
        assert_eq!(
            (i16::store(1.0), i16::store(-1.0), i16::store(2.0)),
            (i16::MAX, -i16::MAX, i16::MAX)
        );
        // Halves round away from zero; out-of-range values saturate, NaN stores 0.
        let half = 0.5 / i16::MAX as f32;
        assert_eq!((i16::store(half), i16::store(-half)), (1, -1));
        assert_eq!(
            (
                i16::store(f32::INFINITY),
                i16::store(f32::NEG_INFINITY),
                i16::store(f32::NAN)
            ),
            (i16::MAX, -i16::MAX, 0)
        );
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn storing_eight_lanes_matches_storing_each() {
        if Kernels::detect() == Kernels::Portable {
            return;
        }
        let special = [
            0.0,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1.0,
            -1.0,
            2.5,
            -7.0,
            0.5 / i16::MAX as f32,
            -0.5 / i16::MAX as f32,
            1.5 / i16::MAX as f32,
            f32::MIN_POSITIVE,
            1e-30,
        ];
        let ramp = (0..4000).map(|i| (i as f32 - 2000.0) * 0.000_613);
        let values: Vec<f32> = special.into_iter().chain(ramp).collect();
        for chunk in values.chunks(LANES) {
            let mut lanes = [0.0f32; LANES];
            lanes[..chunk.len()].copy_from_slice(chunk);
            let mut stored = [0i16; LANES];
            // SAFETY: the CPU has AVX2 (checked above).
            unsafe {
                let loaded = std::arch::x86_64::_mm256_loadu_ps(lanes.as_ptr());
                i16::store_lanes(loaded, &mut stored);
            }
            assert_eq!(stored, lanes.map(i16::store), "{lanes:?}");
        }
    }

    #[test]
    fn blend_dots_match_the_direct_sum() {
        // Every padded stride of M = 4…64, each with a padded tail of zeros.
        for values in (4..=64).step_by(6) {
            let stride = padded(values);
            let rows = 5;
            let stored: Vec<f32> = (0..rows * stride)
                .map(|i| ((i * 37 % 23) as f32 - 11.0) / 11.0)
                .collect();
            let coefficients = |phase: f32| -> Vec<f32> {
                (0..stride)
                    .map(|k| {
                        if k < values {
                            (k as f32 + phase).sin()
                        } else {
                            0.0
                        }
                    })
                    .collect()
            };
            let (first, second) = (coefficients(0.0), coefficients(0.7));
            let picked = [
                (&[(4u32, 0.25f32), (1, -1.5), (3, 2.0)][..], &first),
                (&[(0, 0.5), (2, -0.75)][..], &second),
            ];
            let mut expected = 0.0f64;
            let mut reads = Vec::new();
            for (rows, coefficients) in picked {
                for &(index, factor) in rows {
                    for k in 0..stride {
                        expected += factor as f64
                            * stored[index as usize * stride + k] as f64
                            * coefficients[k] as f64;
                    }
                }
                let mut read = BandRead {
                    rows: [(0, 0.0); 4],
                    count: rows.len(),
                    coefficients,
                };
                read.rows[..rows.len()].copy_from_slice(rows);
                reads.push(read);
            }
            // The same values stored as snorm16, which the AVX2 kernels widen themselves.
            let snorm: Vec<i16> = stored.iter().map(|&v| i16::store(v)).collect();
            let snorm_expected: f64 = reads
                .iter()
                .flat_map(|read| read.rows[..read.count].iter().map(move |row| (read, row)))
                .map(|(read, &(index, factor))| {
                    (0..stride)
                        .map(|k| {
                            let value = snorm[index as usize * stride + k].load() * i16::SCALE;
                            factor as f64 * value as f64 * read.coefficients[k] as f64
                        })
                        .sum::<f64>()
                })
                .sum();
            for kernels in all_kernels() {
                let got = kernels.blend_dots(&stored, &reads);
                assert!(
                    (got as f64 - expected).abs() < 1e-5,
                    "{kernels:?}, stride {stride}: {got} vs {expected}"
                );
                let got = kernels.blend_dots(&snorm, &reads);
                assert!(
                    (got as f64 - snorm_expected).abs() < 1e-5,
                    "{kernels:?}, snorm16, stride {stride}: {got} vs {snorm_expected}"
                );
            }
            // The fixed-stride kernels do the general loop's arithmetic in its order.
            assert_eq!(
                blend_dots(&stored, &reads).to_bits(),
                blend_dots_any(&stored, &reads).to_bits(),
                "stride {stride}"
            );
        }
    }

    #[test]
    fn dotting_twice_gives_each_dot_of_its_own() {
        // Every padded stride of M = 4…64, and one (20) that no fixed kernel takes.
        let strides = (4..=64).step_by(6).map(padded).chain([20]);
        for stride in strides {
            let rows = 6;
            let stored: Vec<f32> = (0..rows * stride)
                .map(|i| ((i * 41 % 29) as f32 - 14.0) / 14.0)
                .collect();
            let snorm: Vec<i16> = stored.iter().map(|&v| i16::store(v)).collect();
            let row = |phase: f32| -> Vec<f32> {
                (0..stride)
                    .map(|k| (k as f32 * 0.6 + phase).sin())
                    .collect()
            };
            let (first, second, third, fourth) = (row(0.0), row(0.4), row(1.1), row(2.3));
            let reads = [
                BandRead {
                    rows: [(4, 0.5), (1, -1.25), (0, 0.0), (0, 0.0)],
                    count: 2,
                    coefficients: &first,
                },
                BandRead {
                    rows: [(2, 0.75), (3, 2.0), (5, -0.5), (1, 0.25)],
                    count: 4,
                    coefficients: &second,
                },
            ];
            let others = [&third[..], &fourth[..]];
            for kernels in all_kernels() {
                for (stored, snorm) in [(Some(&stored), None), (None, Some(&snorm))] {
                    let dots = |reads: &[BandRead<'_>]| match (stored, snorm) {
                        (Some(stored), _) => kernels.blend_dots(stored, reads),
                        (_, Some(snorm)) => kernels.blend_dots(snorm, reads),
                        _ => unreachable!(),
                    };
                    let [dot, other] = match (stored, snorm) {
                        (Some(stored), _) => kernels.blend_dots_twice(stored, &reads, &others),
                        (_, Some(snorm)) => kernels.blend_dots_twice(snorm, &reads, &others),
                        _ => unreachable!(),
                    };
                    // The first as `blend_dots` gives it, bit for bit.
                    assert_eq!(
                        dot.to_bits(),
                        dots(&reads).to_bits(),
                        "{kernels:?} {stride}"
                    );
                    let alone: f32 = reads
                        .iter()
                        .zip(others)
                        .map(|(read, coefficients)| {
                            dots(&[BandRead {
                                coefficients,
                                ..*read
                            }])
                        })
                        .sum();
                    assert!(
                        (other - alone).abs() <= 1e-5 * alone.abs().max(1.0),
                        "{kernels:?}, stride {stride}: {other} against {alone}"
                    );
                }
            }
        }
    }

    #[test]
    fn boundary_dots_are_each_boundary_dotted_alone_bit_for_bit() {
        // Every padded stride of M = 4…64, and one (20) that no fixed kernel takes.
        let strides = (4..=64).step_by(6).map(padded).chain([20]);
        for stride in strides {
            let rows = 9;
            let stored: Vec<f32> = (0..rows * stride)
                .map(|i| ((i * 29 % 31) as f32 - 15.0) / 15.0)
                .collect();
            let snorm: Vec<i16> = stored.iter().map(|&v| i16::store(v)).collect();
            let coefficients: Vec<f32> = (0..stride).map(|k| (k as f32 * 0.9).cos()).collect();
            // The last boundary reads the last two rows; factors of either sign and zero.
            let boundaries = [
                (0, [0.0, 0.375]),
                (3, [1.25, -0.5]),
                (7, [0.75, 2.0]),
                (2, [-1.0, 0.0]),
            ];
            for kernels in all_kernels() {
                let mut got = [f32::NAN; 4];
                kernels.boundary_dots(&stored, &coefficients, &boundaries, &mut got);
                let mut got_snorm = [f32::NAN; 4];
                kernels.boundary_dots(&snorm, &coefficients, &boundaries, &mut got_snorm);
                for (k, &boundary) in boundaries.iter().enumerate() {
                    let read = [BandRead::of_boundary(boundary, &coefficients)];
                    let alone = kernels.blend_dots(&stored, &read);
                    assert_eq!(
                        got[k].to_bits(),
                        alone.to_bits(),
                        "{kernels:?}, stride {stride}"
                    );
                    let alone = kernels.blend_dots(&snorm, &read);
                    assert_eq!(
                        got_snorm[k].to_bits(),
                        alone.to_bits(),
                        "{kernels:?}, snorm16, stride {stride}"
                    );
                }
            }
        }
    }

    #[test]
    fn prefix_sums_accumulate_and_scale_every_row() {
        // Every padded stride of M = 4…64.
        for values in (4..=64).step_by(6) {
            let stride = padded(values);
            let table: Vec<f32> = (0..4 * stride)
                .map(|i| ((i % 7) as f32 - 3.0) / 3.0)
                .collect();
            let entries = [2u32, 0, 3, 3, 1, 2];
            let weights = [0.5f32, 0.25, 1.0, 0.125, 2.0, 0.75];
            for per_row in [1, 2, 3] {
                let rows = entries.len() / per_row;
                let scales: Vec<f32> = (0..rows).map(|r| 1.0 / (r as f32 + 1.5)).collect();
                for kernels in all_kernels() {
                    let mut out = vec![0i16; rows * stride];
                    kernels.prefix_sums(&table, &entries, &weights, &scales, &mut out);
                    let mut sums = vec![0.0f64; stride];
                    for (i, &entry) in entries.iter().enumerate() {
                        for (k, sum) in sums.iter_mut().enumerate() {
                            *sum += weights[i] as f64 * table[entry as usize * stride + k] as f64;
                        }
                        if (i + 1) % per_row != 0 {
                            continue;
                        }
                        let r = i / per_row;
                        for (k, sum) in sums.iter().enumerate() {
                            let want = (sum * scales[r] as f64).clamp(-1.0, 1.0);
                            let got = out[r * stride + k].load() * i16::SCALE;
                            assert!(
                                (got as f64 - want).abs() <= 0.6 / i16::MAX as f64,
                                "{kernels:?}, stride {stride}, {per_row} per row: row {r} lane {k}"
                            );
                        }
                    }
                }
                // The fixed-stride kernels, and the AVX2 ones, do the general loop's
                // arithmetic in its order.
                let mut fixed = vec![0.0f32; rows * stride];
                let mut any = vec![0.0f32; rows * stride];
                prefix_sums(&table, &entries, &weights, &scales, &mut fixed);
                prefix_sums_any(&table, &entries, &weights, &scales, &mut any);
                assert_eq!(fixed, any, "stride {stride}, {per_row} per row");
                let mut snorm16_any = vec![0i16; rows * stride];
                prefix_sums_any(&table, &entries, &weights, &scales, &mut snorm16_any);
                for kernels in all_kernels() {
                    let mut f32s = vec![0.0f32; rows * stride];
                    kernels.prefix_sums(&table, &entries, &weights, &scales, &mut f32s);
                    let bits =
                        |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&f32s), bits(&any), "{kernels:?}, stride {stride}");
                    let mut snorm16 = vec![0i16; rows * stride];
                    kernels.prefix_sums(&table, &entries, &weights, &scales, &mut snorm16);
                    assert_eq!(snorm16, snorm16_any, "{kernels:?}, stride {stride}");
                }
            }
        }
    }

    #[test]
    fn an_entry_past_the_table_is_reported_by_every_kernel() {
        let stride = padded(32);
        let table = vec![0.5f32; 2 * stride];
        // The bad entry comes after good ones, so a kernel has stored rows before it.
        let (entries, weights, scales) = ([0u32, 1, 2], [1.0f32; 3], [1.0f32; 3]);
        for kernels in all_kernels() {
            let summed = std::panic::catch_unwind(|| {
                let mut out = vec![0i16; scales.len() * stride];
                kernels.prefix_sums(&table, &entries, &weights, &scales, &mut out);
            });
            assert!(summed.is_err(), "{kernels:?} summed past the table");
        }
    }
}
