//! Hole filling (papers 000/001 §4.1): flat 2D grey-scale morphology on the shadow
//! map's depth, with a disk or a box kernel.
//!
//! Depth is that of the nearest occluder, so *dilation* — occluders grow — is the minimum
//! over the kernel, and *erosion* the maximum. A closing (dilation, then erosion) fills
//! holes narrower than the kernel and removes the light shafts through them; an opening
//! removes occluders narrower than it. Texels outside the map take no part: a kernel
//! that overhangs the border covers only its part inside the map.
//!
//! The kernels, defined once and used by the fast and the naive filter alike:
//! - disk of radius r: the texel offsets (dx, dy) with dx² + dy² ≤ r² ([`in_disk`]);
//! - box of radius r: the offsets with |dx|, |dy| ≤ ⌊r⌋, a (2⌊r⌋+1)² square.
//!
//! Cost does not grow with the kernel's area. The box is separable: a running extremum
//! along rows, then along columns, O(1) per texel (`running`). The disk is the
//! union of one horizontal chord per row offset dy, of half-width w(dy); every chord is
//! read in O(1) from a sparse table of power-of-two extrema along its row, so a texel
//! costs O(r), in loops over contiguous x that compile to vector min/max.
//!
//! Only the scattering's copy of the map is filtered; object ids and surface shadows
//! keep the original (papers §4.1).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::running::{centred, pick_into, BlockExtrema, Max, Min, Pick};

/// The structuring element.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KernelShape {
    #[default]
    Disk,
    Box,
}

/// The morphological operation, named for what it does to occluders.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MorphologyOp {
    /// Minimum over the kernel: occluders grow.
    Dilate,
    /// Maximum over the kernel: occluders shrink.
    Erode,
    /// Dilation, then erosion: fills holes (the papers' hole filling).
    #[default]
    Close,
    /// Erosion, then dilation: removes thin occluders.
    Open,
}

/// One morphological filter. A radius of 0 leaves the map unchanged.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MorphologyDesc {
    pub op: MorphologyOp,
    pub shape: KernelShape,
    /// Kernel radius in texels; need not be an integer (see [`in_disk`]).
    pub radius_texels: f32,
}

impl MorphologyDesc {
    pub fn new(op: MorphologyOp, shape: KernelShape, radius_texels: f32) -> Self {
        Self {
            op,
            shape,
            radius_texels,
        }
    }

    pub fn dilate(shape: KernelShape, radius_texels: f32) -> Self {
        Self::new(MorphologyOp::Dilate, shape, radius_texels)
    }

    pub fn erode(shape: KernelShape, radius_texels: f32) -> Self {
        Self::new(MorphologyOp::Erode, shape, radius_texels)
    }

    pub fn close(shape: KernelShape, radius_texels: f32) -> Self {
        Self::new(MorphologyOp::Close, shape, radius_texels)
    }

    pub fn open(shape: KernelShape, radius_texels: f32) -> Self {
        Self::new(MorphologyOp::Open, shape, radius_texels)
    }

    /// Where the radius lives in the style description, for error messages.
    pub fn radius_field(&self) -> &'static str {
        match self.op {
            MorphologyOp::Dilate => "style.dilation.radius",
            MorphologyOp::Erode => "style.erosion.radius",
            MorphologyOp::Close => "style.closing.radius",
            MorphologyOp::Open => "style.opening.radius",
        }
    }

    pub(crate) fn validate(&self) -> Result<()> {
        let radius = self.radius_texels;
        if !radius.is_finite() || radius < 0.0 {
            return Err(Error::invalid(
                self.radius_field(),
                format!("{radius} must be a finite number of texels, zero or more"),
            ));
        }
        Ok(())
    }
}

/// Whether texel offset (dx, dy) lies in the disk of radius `radius`: dx² + dy² ≤ r².
/// The squares are exact integers and r² of an `f32` is exact in `f64`.
pub fn in_disk(dx: i64, dy: i64, radius: f32) -> bool {
    let r = radius as f64;
    ((dx as i128 * dx as i128 + dy as i128 * dy as i128) as f64) <= r * r
}

/// Filters the depth of a `size`×`size` map (row-major) as `desc` says.
pub fn apply(depth: &[f32], size: u32, desc: &MorphologyDesc) -> Result<Vec<f32>> {
    desc.validate()?;
    let n = check_depth(depth, size)?;
    let (shape, radius) = (desc.shape, desc.radius_texels);
    let mut map = depth.to_vec();
    let mut scratch = Vec::new();
    let mut pass = |occluders_grow: bool| {
        if occluders_grow {
            filter::<Min>(&mut map, n, shape, radius, &mut scratch);
        } else {
            filter::<Max>(&mut map, n, shape, radius, &mut scratch);
        }
    };
    match desc.op {
        MorphologyOp::Dilate => pass(true),
        MorphologyOp::Erode => pass(false),
        MorphologyOp::Close => {
            pass(true);
            pass(false);
        }
        MorphologyOp::Open => {
            pass(false);
            pass(true);
        }
    }
    Ok(map)
}

/// The same filter evaluated by brute force, O(r²) per texel: the definition the fast
/// [`apply`] is tested against.
pub fn apply_naive(depth: &[f32], size: u32, desc: &MorphologyDesc) -> Result<Vec<f32>> {
    desc.validate()?;
    let n = check_depth(depth, size)?;
    let (shape, radius) = (desc.shape, desc.radius_texels);
    Ok(match desc.op {
        MorphologyOp::Dilate => naive::<Min>(depth, n, shape, radius),
        MorphologyOp::Erode => naive::<Max>(depth, n, shape, radius),
        MorphologyOp::Close => {
            naive::<Max>(&naive::<Min>(depth, n, shape, radius), n, shape, radius)
        }
        MorphologyOp::Open => {
            naive::<Min>(&naive::<Max>(depth, n, shape, radius), n, shape, radius)
        }
    })
}

/// Checks that `depth` is a `size`×`size` map of usable depths (a number or +∞, never
/// NaN or −∞) and returns `size` as an index.
pub(crate) fn check_depth(depth: &[f32], size: u32) -> Result<usize> {
    const FIELD: &str = "shadow_map.depth";
    let n = size as usize;
    if n.checked_mul(n) != Some(depth.len()) {
        return Err(Error::invalid(
            FIELD,
            format!(
                "holds {} values, but a {size}×{size} map needs {}",
                depth.len(),
                n as u128 * n as u128
            ),
        ));
    }
    let unusable = |v: &f32| v.is_nan() || *v == f32::NEG_INFINITY;
    if depth.par_iter().any(unusable) {
        if let Some(i) = depth.iter().position(unusable) {
            return Err(Error::invalid(
                FIELD,
                format!(
                    "texel ({}, {}) is {} (depths are numbers, or +inf where nothing occludes)",
                    i % n,
                    i / n,
                    depth[i]
                ),
            ));
        }
    }
    Ok(n)
}

/// Largest offset that can still reach into a map of `size` texels.
fn reach(radius: f32, size: usize) -> usize {
    (radius.floor() as f64).min(size.saturating_sub(1) as f64) as usize
}

/// Half-width w(|dy|) of the disk's chord at each row offset, for |dy| up to the reach.
fn disk_half_widths(radius: f32, size: usize) -> Vec<usize> {
    let reach = reach(radius, size);
    let mut widths = Vec::with_capacity(reach + 1);
    let mut w = reach;
    for dy in 0..=reach {
        while w > 0 && !in_disk(w as i64, dy as i64, radius) {
            w -= 1;
        }
        widths.push(w);
    }
    widths
}

fn naive<P: Pick>(src: &[f32], n: usize, shape: KernelShape, radius: f32) -> Vec<f32> {
    let reach = reach(radius, n) as i64;
    let n_i = n as i64;
    let mut out = vec![0.0; n * n];
    out.par_chunks_mut(n.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let mut acc = P::neutral();
                for dy in -reach..=reach {
                    for dx in -reach..=reach {
                        let inside = match shape {
                            KernelShape::Disk => in_disk(dx, dy, radius),
                            KernelShape::Box => true,
                        };
                        let (sx, sy) = (x as i64 + dx, y as i64 + dy);
                        if inside && (0..n_i).contains(&sx) && (0..n_i).contains(&sy) {
                            acc = P::pick(acc, src[(sy * n_i + sx) as usize]);
                        }
                    }
                }
                *o = acc;
            }
        });
    out
}

/// Resizes `buffer` to `len` values; their content is left for the caller to overwrite.
fn sized(buffer: &mut Vec<f32>, len: usize) -> &mut [f32] {
    buffer.resize(len, 0.0);
    &mut buffer[..len]
}

/// Filters `map` in place; `scratch` is one more map's worth of memory, kept between
/// passes.
fn filter<P: Pick>(
    map: &mut [f32],
    n: usize,
    shape: KernelShape,
    radius: f32,
    scratch: &mut Vec<f32>,
) {
    let reach = reach(radius, n);
    if reach == 0 {
        return;
    }
    match shape {
        KernelShape::Disk => disk::<P>(map, n, radius, scratch),
        KernelShape::Box => square::<P>(map, n, reach, scratch),
    }
}

/// Output texels accumulated together, in registers, while the chords stream past.
const CHUNK: usize = 32;

/// The disk as chords. Rows are padded with the neutral value by the widest half-width,
/// so every chord query is the same two loads; the sparse table is built one level at a
/// time in place, and each level serves the chords whose length it spans, so memory
/// stays one padded copy of the map whatever the radius.
fn disk<P: Pick>(map: &mut [f32], n: usize, radius: f32, scratch: &mut Vec<f32>) {
    let widths = disk_half_widths(radius, n);
    let pad = widths[0];
    let padded = n + 2 * pad;
    // Chords grouped by the sparse-table level that covers them: level k holds extrema
    // of 2^k consecutive texels, and two of them cover a chord of 2w+1 < 2^(k+1).
    let level_of = |w: usize| (usize::BITS - 1 - (2 * w + 1).leading_zeros()) as usize;
    let top = level_of(pad);
    let mut chords: Vec<Vec<(isize, usize)>> = vec![Vec::new(); top + 1];
    for (dy, &w) in widths.iter().enumerate() {
        chords[level_of(w)].push((dy as isize, w));
        if dy > 0 {
            chords[level_of(w)].push((-(dy as isize), w));
        }
    }

    let table = sized(scratch, n * padded);
    table
        .par_chunks_mut(padded)
        .zip(map.par_chunks(n))
        .for_each(|(row, src_row)| {
            row[..pad].fill(P::neutral());
            row[pad..pad + n].copy_from_slice(src_row);
            row[pad + n..].fill(P::neutral());
        });
    let out = map;
    out.fill(P::neutral());
    for (level, level_chords) in chords.iter().enumerate() {
        let span = 1usize << level;
        if level > 0 {
            let half = span / 2;
            table.par_chunks_mut(padded).for_each_init(
                || vec![0.0f32; padded],
                |previous, row| {
                    previous.copy_from_slice(row);
                    pick_into::<f32, P>(&previous[..padded - half], &previous[half..], row);
                },
            );
        }
        if level_chords.is_empty() {
            continue;
        }
        let table = &*table;
        out.par_chunks_mut(n).enumerate().for_each_init(
            Vec::new,
            |spans: &mut Vec<(&[f32], &[f32])>, (y, out_row)| {
                // Padded index of x is x + pad; the chord [x − w, x + w] is covered by the
                // spans of 2^level texels starting at its two ends.
                spans.clear();
                for &(dy, w) in level_chords {
                    if let Some(sy) = y.checked_add_signed(dy).filter(|&sy| sy < n) {
                        let row = &table[sy * padded..(sy + 1) * padded];
                        let right = pad + w + 1 - span;
                        spans.push((&row[pad - w..pad - w + n], &row[right..right + n]));
                    }
                }
                accumulate_chords::<P>(out_row, spans);
            },
        );
    }
}

/// `out[x] = pick(out[x], left[x], right[x])` over all `(left, right)` spans, a chunk of
/// x at a time so that the accumulator stays in registers.
fn accumulate_chords<P: Pick>(out: &mut [f32], spans: &[(&[f32], &[f32])]) {
    let n = out.len();
    let whole = n - n % CHUNK;
    for x0 in (0..whole).step_by(CHUNK) {
        let mut acc = [0.0f32; CHUNK];
        acc.copy_from_slice(&out[x0..x0 + CHUNK]);
        for (left, right) in spans {
            let (left, right) = (&left[x0..x0 + CHUNK], &right[x0..x0 + CHUNK]);
            for i in 0..CHUNK {
                acc[i] = P::pick(acc[i], P::pick(left[i], right[i]));
            }
        }
        out[x0..x0 + CHUNK].copy_from_slice(&acc);
    }
    for (left, right) in spans {
        for x in whole..n {
            out[x] = P::pick(out[x], P::pick(left[x], right[x]));
        }
    }
}

/// The (2·reach+1)² box: running extrema along rows, then along columns.
fn square<P: Pick>(map: &mut [f32], n: usize, reach: usize, scratch: &mut Vec<f32>) {
    let block = 2 * reach + 1;
    let window = |i: usize| (i.saturating_sub(reach), (i + reach).min(n - 1));

    let suffix = sized(scratch, n * n);
    suffix
        .par_chunks_mut(n)
        .zip(map.par_chunks(n))
        .for_each_init(BlockExtrema::new, |blocks, (out_row, src_row)| {
            centred::<f32, P>(src_row, reach, blocks, out_row)
        });

    // Columns: the same block scheme with whole rows as the elements, so the inner loops
    // run over contiguous x. The row pass's result becomes the per-block prefixes in
    // `map` and the suffixes in `scratch`.
    let prefix = map;
    prefix.copy_from_slice(suffix);
    prefix
        .par_chunks_mut(block * n)
        .zip(suffix.par_chunks_mut(block * n))
        .for_each(|(prefix, suffix)| {
            let count = prefix.len() / n;
            for i in 1..count {
                let (done, rest) = prefix.split_at_mut(i * n);
                let previous = &done[(i - 1) * n..];
                for (p, &q) in rest[..n].iter_mut().zip(previous) {
                    *p = P::pick(q, *p);
                }
            }
            for i in (0..count.saturating_sub(1)).rev() {
                let (head, done) = suffix.split_at_mut((i + 1) * n);
                let next = &done[..n];
                for (s, &q) in head[i * n..].iter_mut().zip(next) {
                    *s = P::pick(q, *s);
                }
            }
        });

    // Row y's window is read from the prefixes at its last row b ≥ y, so the result can
    // overwrite the prefixes in increasing y, in strips of columns that run in parallel.
    let suffix = &*suffix;
    let mut strips: Vec<Vec<&mut [f32]>> = Vec::new();
    for row in prefix.chunks_mut(n) {
        for (s, piece) in row.chunks_mut(STRIP).enumerate() {
            if s == strips.len() {
                strips.push(Vec::with_capacity(n));
            }
            strips[s].push(piece);
        }
    }
    strips
        .into_par_iter()
        .enumerate()
        .for_each(|(s, mut rows)| {
            let x0 = s * STRIP;
            for y in 0..n {
                let (a, b) = window(y);
                let suffix_row = &suffix[a * n + x0..a * n + x0 + rows[y].len()];
                if a / block != b / block {
                    if b == y {
                        for (o, &t) in rows[y].iter_mut().zip(suffix_row) {
                            *o = P::pick(t, *o);
                        }
                    } else {
                        let (head, tail) = rows.split_at_mut(b);
                        pick_into::<f32, P>(suffix_row, tail[0], head[y]);
                    }
                } else if a % block == 0 {
                    if b != y {
                        let (head, tail) = rows.split_at_mut(b);
                        head[y].copy_from_slice(tail[0]);
                    }
                } else {
                    rows[y].copy_from_slice(suffix_row);
                }
            }
        });
}

/// Width of the column strips of the box's last pass (256 bytes).
const STRIP: usize = 64;
