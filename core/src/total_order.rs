//! Floats as unsigned integers in [`f64::total_cmp`]'s (and [`f32::total_cmp`]'s) order:
//! sorting the integers sorts the floats, and an integer key leaves spare bits for a tie
//! breaker, at a fraction of the cost of sorting by a comparator.

/// `value`'s bits as an integer in [`f64::total_cmp`]'s order. Sorting by it gives the
/// same order as sorting by `total_cmp`, at a fraction of the cost: sorting colonnade's
/// 850k sampled rays by it, with their speeds alone, took 11 ms against 20 ms sorting
/// the whole rays by `total_cmp` (the sum over slices, one core each).
#[inline]
pub(crate) fn total_order_bits(value: f64) -> u64 {
    let bits = value.to_bits();
    if bits >> 63 == 1 {
        !bits
    } else {
        bits | 1 << 63
    }
}

/// The inverse of [`total_order_bits`].
#[inline]
pub(crate) fn from_total_order_bits(bits: u64) -> f64 {
    f64::from_bits(if bits >> 63 == 1 {
        bits & !(1 << 63)
    } else {
        !bits
    })
}

/// [`total_order_bits`] for `f32`, in [`f32::total_cmp`]'s order.
#[inline]
pub(crate) fn total_order_bits_f32(value: f32) -> u32 {
    let bits = value.to_bits();
    if bits >> 31 == 1 {
        !bits
    } else {
        bits | 1 << 31
    }
}
