//! Minima and maxima over sliding windows in O(1) per element, whatever the window
//! length (van Herk / Gil–Werman): the signal is cut into blocks of the window length,
//! so that a window spans at most two blocks and is covered by a suffix of one and a
//! prefix of the next. Shared by the 2D morphology and the epipolar (silhouette) filters.
//!
//! An element may be a whole row of `width` lanes (filtered lane by lane), which turns
//! the inner loops into contiguous ones that compile to vector min/max.
//!
//! The extrema are plain comparisons with no arithmetic, so infinities pass through
//! exactly and the result does not depend on evaluation order.

/// The scalar types the filters run on.
pub(crate) trait Scalar: Copy + PartialOrd + Send + Sync + 'static {
    const INFINITY: Self;
    const NEG_INFINITY: Self;
}

impl Scalar for f32 {
    const INFINITY: Self = f32::INFINITY;
    const NEG_INFINITY: Self = f32::NEG_INFINITY;
}

impl Scalar for f64 {
    const INFINITY: Self = f64::INFINITY;
    const NEG_INFINITY: Self = f64::NEG_INFINITY;
}

/// Which extremum a filter takes: [`Min`] or [`Max`]. Inputs are never NaN (callers
/// validate), so a single comparison is exact; written as a select it compiles to one
/// vector min/max instruction.
pub(crate) trait Pick: Copy + Send + Sync + 'static {
    /// The value that never wins, standing in for what lies outside the signal.
    fn neutral<T: Scalar>() -> T;
    fn pick<T: Scalar>(a: T, b: T) -> T;
}

#[derive(Clone, Copy, Debug)]
pub(crate) struct Min;

#[derive(Clone, Copy, Debug)]
pub(crate) struct Max;

impl Pick for Min {
    #[inline(always)]
    fn neutral<T: Scalar>() -> T {
        T::INFINITY
    }

    #[inline(always)]
    fn pick<T: Scalar>(a: T, b: T) -> T {
        if b < a {
            b
        } else {
            a
        }
    }
}

impl Pick for Max {
    #[inline(always)]
    fn neutral<T: Scalar>() -> T {
        T::NEG_INFINITY
    }

    #[inline(always)]
    fn pick<T: Scalar>(a: T, b: T) -> T {
        if b > a {
            b
        } else {
            a
        }
    }
}

/// `out[i] = pick(a[i], b[i])`.
#[inline(always)]
pub(crate) fn pick_into<T: Scalar, P: Pick>(a: &[T], b: &[T], out: &mut [T]) {
    for ((o, &x), &y) in out.iter_mut().zip(a).zip(b) {
        *o = P::pick(x, y);
    }
}

/// Per-block prefix and suffix extrema of a signal of rows, from which the extremum of
/// any window of at most `block` rows that is whole, or clipped by the signal's ends, is
/// read in O(1). Buffers are kept between signals to avoid reallocation.
#[derive(Debug, Default)]
pub(crate) struct BlockExtrema<T> {
    block: usize,
    width: usize,
    /// Extremum from the start of each row's block up to the row.
    prefix: Vec<T>,
    /// Extremum from the row to the end of its block (or of the signal).
    suffix: Vec<T>,
}

impl<T: Scalar> BlockExtrema<T> {
    pub(crate) fn new() -> Self {
        Self {
            block: 1,
            width: 1,
            prefix: Vec::new(),
            suffix: Vec::new(),
        }
    }

    /// Number of rows in the signal.
    pub(crate) fn len(&self) -> usize {
        self.prefix.len() / self.width
    }

    /// Prepares queries on `values`, rows of `width` lanes, for windows of up to `block`
    /// rows.
    pub(crate) fn build<P: Pick>(&mut self, values: &[T], width: usize, block: usize) {
        let (width, block) = (width.max(1), block.max(1));
        self.block = block;
        self.width = width;
        let len = values.len();
        self.prefix.resize(len, T::INFINITY);
        self.suffix.resize(len, T::INFINITY);
        if width == 1 {
            // One lane: plain running extrema, without per-row slices.
            let blocks = values
                .chunks(block)
                .zip(self.prefix.chunks_mut(block))
                .zip(self.suffix.chunks_mut(block));
            for ((values, prefix), suffix) in blocks {
                let mut acc = P::neutral();
                for (p, &v) in prefix.iter_mut().zip(values) {
                    acc = P::pick(acc, v);
                    *p = acc;
                }
                let mut acc = P::neutral();
                for (s, &v) in suffix.iter_mut().zip(values).rev() {
                    acc = P::pick(acc, v);
                    *s = acc;
                }
            }
            return;
        }
        let rows = len / width;
        for start in (0..rows).step_by(block) {
            let end = (start + block).min(rows);
            let row = |i: usize| i * width..(i + 1) * width;
            self.prefix[row(start)].copy_from_slice(&values[row(start)]);
            for i in start + 1..end {
                let (done, rest) = self.prefix.split_at_mut(i * width);
                let previous = &done[(i - 1) * width..];
                pick_into::<T, P>(previous, &values[row(i)], &mut rest[..width]);
            }
            self.suffix[row(end - 1)].copy_from_slice(&values[row(end - 1)]);
            for i in (start..end - 1).rev() {
                let (head, done) = self.suffix.split_at_mut((i + 1) * width);
                pick_into::<T, P>(&done[..width], &values[row(i)], &mut head[i * width..]);
            }
        }
    }

    #[inline]
    pub(crate) fn prefix(&self, i: usize) -> &[T] {
        &self.prefix[i * self.width..(i + 1) * self.width]
    }

    #[inline]
    pub(crate) fn suffix(&self, i: usize) -> &[T] {
        &self.suffix[i * self.width..(i + 1) * self.width]
    }

    /// Writes the extremum of rows `a..=b` to `out`. The window must hold exactly
    /// `block` rows, or start at row 0, or end at the last row (a window clipped by an
    /// end of the signal).
    pub(crate) fn window_into<P: Pick>(&self, a: usize, b: usize, out: &mut [T]) {
        let block = self.block;
        if a / block != b / block {
            pick_into::<T, P>(self.suffix(a), self.prefix(b), out);
        } else if a.is_multiple_of(block) {
            out.copy_from_slice(self.prefix(b));
        } else {
            // Same block, not starting at its start: by the precondition the window ends
            // where the suffix does (the signal's end).
            debug_assert_eq!(b + 1, self.len());
            out.copy_from_slice(self.suffix(a));
        }
    }

    /// The extremum of rows `a..=b` of a one-lane signal, under `window_into`'s
    /// precondition.
    #[inline]
    pub(crate) fn window<P: Pick>(&self, a: usize, b: usize) -> T {
        let mut out = [P::neutral()];
        self.window_into::<P>(a, b, &mut out);
        out[0]
    }
}

/// `out[x]` = extremum of `values[x − reach ..= x + reach]`, the part outside the signal
/// being absent.
pub(crate) fn centred<T: Scalar, P: Pick>(
    values: &[T],
    reach: usize,
    blocks: &mut BlockExtrema<T>,
    out: &mut [T],
) {
    let len = values.len();
    blocks.build::<P>(values, 1, 2 * reach + 1);
    let window = |x: usize| (x.saturating_sub(reach), (x + reach).min(len - 1));
    if len > 2 * reach {
        // Whole windows span two blocks, or fill one exactly: either way the suffix at
        // their start and the prefix at their end cover them.
        let inner = len - 2 * reach;
        pick_into::<T, P>(
            &blocks.suffix[..inner],
            &blocks.prefix[2 * reach..],
            &mut out[reach..reach + inner],
        );
        for x in (0..reach).chain(len - reach..len) {
            let (a, b) = window(x);
            out[x] = blocks.window::<P>(a, b);
        }
    } else {
        for (x, o) in out.iter_mut().enumerate().take(len) {
            let (a, b) = window(x);
            *o = blocks.window::<P>(a, b);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive<P: Pick>(values: &[f64], a: isize, b: isize) -> f64 {
        (a.max(0)..=b.min(values.len() as isize - 1))
            .map(|i| values[i as usize])
            .fold(P::neutral(), P::pick)
    }

    fn signal(len: usize) -> Vec<f64> {
        (0..len)
            .map(|i| match (i * 7919) % 13 {
                0 => f64::INFINITY,
                k => ((i * 31) % 17) as f64 - k as f64,
            })
            .collect()
    }

    #[test]
    fn centred_windows_match_a_direct_scan() {
        let mut blocks = BlockExtrema::new();
        for len in [1, 2, 5, 37] {
            let values = signal(len);
            let mut out = vec![0.0; len];
            for reach in [0, 1, 2, 3, 17, 18, 40] {
                centred::<f64, Min>(&values, reach, &mut blocks, &mut out);
                for (x, &o) in out.iter().enumerate() {
                    let (x, r) = (x as isize, reach as isize);
                    assert_eq!(o, naive::<Min>(&values, x - r, x + r), "{len} {reach} {x}");
                }
                centred::<f64, Max>(&values, reach, &mut blocks, &mut out);
                for (x, &o) in out.iter().enumerate() {
                    let (x, r) = (x as isize, reach as isize);
                    assert_eq!(o, naive::<Max>(&values, x - r, x + r), "{len} {reach} {x}");
                }
            }
        }
    }

    #[test]
    fn clipped_and_whole_windows_of_rows_match_a_direct_scan() {
        let (rows, width) = (23, 3);
        let values = signal(rows * width);
        let mut blocks = BlockExtrema::new();
        let mut out = [0.0; 3];
        for n in [1, 2, 5, 23, 30] {
            blocks.build::<Max>(&values, width, n);
            for end in 0..rows {
                // Trailing windows, clipped at the start.
                let start = (end + 1).saturating_sub(n);
                blocks.window_into::<Max>(start, end, &mut out);
                for (lane, &o) in out.iter().enumerate() {
                    let lane_values: Vec<f64> =
                        values.iter().skip(lane).step_by(width).copied().collect();
                    let expected = naive::<Max>(&lane_values, start as isize, end as isize);
                    assert_eq!(o, expected, "n {n} end {end} lane {lane}");
                }
                // Leading windows, clipped at the end.
                let last = (end + n - 1).min(rows - 1);
                blocks.window_into::<Max>(end, last, &mut out);
                for (lane, &o) in out.iter().enumerate() {
                    let lane_values: Vec<f64> =
                        values.iter().skip(lane).step_by(width).copied().collect();
                    let expected = naive::<Max>(&lane_values, end as isize, last as isize);
                    assert_eq!(o, expected, "n {n} start {end} lane {lane}");
                }
            }
        }
    }
}
