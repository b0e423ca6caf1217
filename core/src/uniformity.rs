//! Whether a view ray is lit, or shadowed, over a whole stretch of its slice of the
//! rectified map, in a handful of reads: prefiltering answers such stretches exactly
//! instead of from its series, whose residue (about 0.5% of a lit ray, 0.006 of visibility
//! in full shadow) is most of its error on views where many rays never cross a shadow.
//!
//! Per slice, the samples are grouped in blocks of [`BLOCK`]; a sparse table holds the
//! lowest and highest K over every run of 2^k blocks from each block. A stretch is its
//! partial blocks at either end, each uniform where its whole block is (one entry) or
//! else read sample by sample (one cache line), and the whole blocks between, covered by
//! two runs of the table.

use rayon::prelude::*;

use crate::epipolar::EpipolarMap;
use crate::error::{Result, Sizing};
use crate::spare::Spare;

/// Samples per block: one cache line of rectified values.
pub const BLOCK: usize = 16;

/// The sparse table of a rectified map's blocks.
#[derive(Debug)]
pub struct UniformityTable {
    blocks: usize,
    levels: usize,
    /// Per slice, per level k, per block b: [lowest, highest] K over blocks b..b + 2^k
    /// (entries that would run past the slice's end are unused).
    runs: Vec<[f32; 2]>,
}

// The last frame's table, kept for the next (see `crate::spare`).
static SPARE_RUNS: Spare<[f32; 2]> = Spare::on_huge_pages(Sizing::Rectified);

/// Lets go of the kept tables ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_RUNS.clear();
}

impl Drop for UniformityTable {
    fn drop(&mut self) {
        SPARE_RUNS.keep(std::mem::take(&mut self.runs));
    }
}

/// Blocks per slice, and levels of runs (1, 2, … up to the largest power of two of blocks
/// that fits), of the table over slices of `samples` samples.
pub fn table_shape(samples: usize) -> (usize, usize) {
    let blocks = samples.div_ceil(BLOCK);
    let levels = if blocks == 0 {
        0
    } else {
        blocks.ilog2() as usize + 1
    };
    (blocks, levels)
}

/// Bytes of the table over `slices` slices of `samples` samples.
pub fn table_bytes(slices: u32, samples: u32) -> usize {
    let (blocks, levels) = table_shape(samples as usize);
    slices as usize * levels * blocks * std::mem::size_of::<[f32; 2]>()
}

impl UniformityTable {
    /// The table of `map`, each slice's only over the samples before its `reaches`
    /// (queries there may read no farther), or over all of them.
    /// An error where its memory cannot be allocated.
    pub fn build(map: &EpipolarMap, reaches: Option<&[usize]>) -> Result<Self> {
        let samples = map.samples as usize;
        let (blocks, levels) = table_shape(samples);
        let stride = levels * blocks;
        // Every entry a query reads is set below, so a kept buffer's old values do not
        // matter.
        let mut runs = SPARE_RUNS.try_take(map.slices as usize * stride, || {
            format!("the uniformity table ({} slices)", map.slices)
        })?;
        if stride > 0 {
            runs.par_chunks_mut(stride)
                .enumerate()
                .for_each(|(slice, table)| {
                    let row = map.row(slice as u32);
                    let used = reaches.map_or(blocks, |reaches| {
                        reaches[slice].min(samples).div_ceil(BLOCK)
                    });
                    let (first, rest) = table.split_at_mut(blocks);
                    for (b, run) in first[..used].iter_mut().enumerate() {
                        *run = map.run_bounds(row, b * BLOCK..((b + 1) * BLOCK).min(samples));
                    }
                    let mut below: &[[f32; 2]] = first;
                    let mut rest = rest;
                    for k in 1..levels {
                        let (level, after) = rest.split_at_mut(blocks);
                        let half = 1 << (k - 1);
                        for b in 0..(used + 1).saturating_sub(1 << k) {
                            let (x, y) = (below[b], below[b + half]);
                            level[b] = [x[0].min(y[0]), x[1].max(y[1])];
                        }
                        below = level;
                        rest = after;
                    }
                });
        }
        Ok(Self {
            blocks,
            levels,
            runs,
        })
    }

    pub fn memory_bytes(&self) -> usize {
        self.runs.len() * std::mem::size_of::<[f32; 2]>()
    }

    /// Whether a ray with `threshold` is lit over all of samples `first..=last` of `slice`
    /// (`Some(true)`), shadowed over all of them (`Some(false)`), or neither (`None`).
    #[inline]
    pub fn uniformity(
        &self,
        map: &EpipolarMap,
        slice: u32,
        threshold: f32,
        first: usize,
        last: usize,
    ) -> Option<bool> {
        let row = map.row(slice);
        let (low, high) = map.sample_bounds(first, row[first]);
        let lit = if low >= threshold {
            true
        } else if high < threshold {
            false
        } else {
            return None;
        };
        let uniform = |[low, high]: [f32; 2]| {
            if lit {
                low >= threshold
            } else {
                high < threshold
            }
        };
        if last == first {
            return Some(lit);
        }
        // Rays change most often at their ends (a surface is nearly its own occluder), so
        // the last sample is tested before the rest.
        let (low, high) = map.sample_bounds(last, row[last]);
        if !uniform([low, high]) {
            return None;
        }
        let (first_block, last_block) = (first / BLOCK, last / BLOCK);
        let table = &self.runs[slice as usize * self.levels * self.blocks..];
        // A partial block is uniform where its whole block is, which one entry says;
        // only where that fails are its own samples read.
        let partial = |block: usize, samples: std::ops::Range<usize>| {
            uniform(table[block]) || uniform(map.run_bounds(row, samples))
        };
        if first_block == last_block {
            return partial(first_block, first + 1..last).then_some(lit);
        }
        if !partial(first_block, first + 1..(first_block + 1) * BLOCK)
            || !partial(last_block, last_block * BLOCK..last)
        {
            return None;
        }
        let whole = last_block - first_block - 1;
        if whole > 0 {
            let k = whole.ilog2() as usize;
            let level = &table[k * self.blocks..][..self.blocks];
            if !uniform(level[first_block + 1]) || !uniform(level[last_block - (1 << k)]) {
                return None;
            }
        }
        Some(lit)
    }
}

/// [`UniformityTable::uniformity`] the slow way, testing every sample's bounds: what the
/// tests hold the table and prefiltering's exact rays to.
#[cfg(test)]
pub(crate) fn uniformity_of_every_sample(
    map: &EpipolarMap,
    slice: u32,
    threshold: f32,
    first: usize,
    last: usize,
) -> Option<bool> {
    let row = map.row(slice);
    let bounds: Vec<(f32, f32)> = (first..=last)
        .map(|i| map.sample_bounds(i, row[i]))
        .collect();
    if bounds.iter().all(|&(low, _)| low >= threshold) {
        Some(true)
    } else if bounds.iter().all(|&(_, high)| high < threshold) {
        Some(false)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::builtin_scene;
    use crate::epipolar::test_support::rectified;
    use crate::epipolar::{MapLayout, RectifyDesc};
    use crate::scene::{Projection, Rectification};
    use rand::{RngExt, SeedableRng};

    /// Small frames of the built-in scenes in each of the map's layouts.
    fn maps() -> Vec<(&'static str, EpipolarMap)> {
        let small = |name: &str| {
            let mut scene = builtin_scene(name).unwrap();
            scene.camera.width = 96;
            scene.camera.height = 54;
            scene.render.shadow_map_size = 256;
            scene
        };
        let mut orthographic = small("plane");
        orthographic.camera.projection = Projection::orthographic(30.0);
        let desc = RectifyDesc::prefiltered(0);
        vec![
            (
                "tree, epipolar",
                rectified(&small("tree"), Rectification::Epipolar, &desc).2,
            ),
            (
                "torus, projective",
                rectified(&small("torus"), Rectification::Projective, &desc).2,
            ),
            (
                "plane, orthographic",
                rectified(&orthographic, Rectification::Epipolar, &desc).2,
            ),
        ]
    }

    #[test]
    fn the_maps_cover_every_layout() {
        let layouts: Vec<MapLayout> = maps().iter().map(|(_, m)| m.geometry().layout).collect();
        for layout in [
            MapLayout::Radial,
            MapLayout::Projective,
            MapLayout::Parallel,
        ] {
            assert!(layouts.contains(&layout), "{layout:?} missing: {layouts:?}");
        }
    }

    #[test]
    fn uniformity_equals_testing_every_sample() {
        for (name, map) in maps() {
            let samples = map.samples as usize;
            let mut rng = rand_pcg::Pcg64::seed_from_u64(17);
            // Each slice built to a random reach, half of them, and queried before it, in
            // a kept buffer (`Spare`) of NaN, which no stretch reads as uniform.
            let (blocks, levels) = table_shape(samples);
            let mut poisoned = SPARE_RUNS
                .try_take(map.slices as usize * blocks * levels, String::new)
                .unwrap();
            poisoned.fill([f32::NAN; 2]);
            SPARE_RUNS.keep(poisoned);
            let reaches: Vec<usize> = (0..map.slices)
                .map(|_| match rng.random_bool(0.5) {
                    true => rng.random_range(1..=samples),
                    false => samples,
                })
                .collect();
            let table = UniformityTable::build(&map, Some(&reaches)).expect("memory for the table");
            let (mut lit, mut shadowed, mut mixed) = (0, 0, 0);
            for _ in 0..4000 {
                let slice = rng.random_range(0..map.slices);
                let row = map.row(slice);
                let reach = reaches[slice as usize];
                let first = rng.random_range(0..reach);
                // Short and long stretches alike, within a block and across many.
                let length = 1usize << rng.random_range(0..12);
                let last = (first + rng.random_range(0..length)).min(reach - 1);
                // Thresholds at the stretch's own values, where the answer is closest.
                let at = rng.random_range(first..=last);
                let threshold = row[at] + rng.random_range(-0.02..0.02f32) * row[at].abs();
                let expected = uniformity_of_every_sample(&map, slice, threshold, first, last);
                match expected {
                    Some(true) => lit += 1,
                    Some(false) => shadowed += 1,
                    None => mixed += 1,
                }
                assert_eq!(
                    table.uniformity(&map, slice, threshold, first, last),
                    expected,
                    "{name}: slice {slice}, samples {first}..={last}, threshold {threshold}"
                );
            }
            assert!(
                lit > 100 && shadowed > 100 && mixed > 100,
                "{name}: {lit} lit, {shadowed} shadowed, {mixed} mixed"
            );
        }
    }

    #[test]
    fn the_table_has_one_run_per_block_and_level() {
        assert_eq!(table_shape(0), (0, 0));
        assert_eq!(table_shape(1), (1, 1));
        assert_eq!(table_shape(BLOCK), (1, 1));
        assert_eq!(table_shape(BLOCK + 1), (2, 2));
        assert_eq!(table_shape(100 * BLOCK), (100, 7));
        assert_eq!(table_bytes(3, 100 * BLOCK as u32), 3 * 100 * 7 * 8);
    }
}
