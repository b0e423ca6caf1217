//! Hole creation (papers 000/001 §4.1): opens random, animated holes in chosen occluders
//! of the scattering shadow map, so that more light shafts burst through foliage.
//!
//! A hole map H is a threshold of Perlin fBm N (Eq. 4–5). Where H says "hole" on a texel
//! whose occluder is one of the chosen objects, that occluder is removed from the map used
//! for scattering. Surface shadows are never changed: this works on a copy of the depth.
//! [`HolesDesc`] holds the settings, [`HoleNoise`] lays one frame's noise over one map
//! (and [`HoleNoise::apply`] opens the holes), [`holed_depth`] does both on a copy.
//!
//! How this departs from, or pins down, the papers:
//! - **Scene units.** The paper looks the noise up at texture coordinates t ∈ [0, 1]² of the
//!   map. Here t is the texel centre's position on the light plane in scene units (through
//!   the inverse of `texel_from_world`'s xy part, measured from [`HolesDesc::pivot`]), so the
//!   holes stay put in the world whatever the map's resolution or fitted footprint.
//! - **Octaves.** Eq. 5 as printed samples every octave at the same q, which would only
//!   rescale one noise; octave i is sampled at 2ⁱ·q as in Perlin's fBm, with the printed
//!   weight pⁱ / max(1, o − i − 1). N is divided by the sum of the weights so that it lies
//!   in [0, 1] for any p and o, and h keeps its meaning: the paper's h is ours times that sum.
//! - **Polarity.** H = 1 (hole) where N < h, as in Eq. 4; h is the "hole probability", so
//!   raising h opens more holes.
//! - **Removal.** The paper renders the chosen objects into their own map and
//!   max-composites it with the hole map (depth pushed to the far plane). This map keeps
//!   one layer, the nearest occluder, so an opened texel becomes +∞ ("no occluder"): an
//!   unchosen object behind a chosen one does not show through. Rendering the chosen
//!   objects into a separate map and compositing would remove that limit.
//! - **Animation.** The two-step lookup of paper 001: the sample point q is rotated by
//!   θ = speed·time about the pivot and the noise is looked up there; that value P ∈ [0, 1],
//!   as warp·(P − ½), is added to both coordinates of q, and N at the moved point is the
//!   result. The first lookup uses N's first octave only: its offset field stays smooth,
//!   so holes drift and reshape instead of flickering, at the cost of one octave rather
//!   than o. Points far from the pivot sweep faster, as with the paper's rotation about
//!   the texture origin. Nothing depends on earlier frames, and the map is continuous in
//!   time.

use glam::{DMat4, DVec2, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::raster::NO_OBJECT;
use crate::scene::{MAX_SHADOW_MAP_SIZE, MIN_SHADOW_MAP_SIZE};
use crate::shadow_map::ShadowMap;

/// Largest octave count: octave 15 is already 2¹⁵ times finer than the first.
pub const MAX_OCTAVES: u32 = 16;
/// Largest gradient grid: a block's lattice coordinates start within one period, which
/// keeps them far below 2²² (see `ROUNDER`).
pub const MAX_GRID_SIZE: u32 = 4096;
/// Largest frequency, in grid repeats per scene unit.
pub const MAX_FREQUENCY: f32 = 1.0e6;
/// Largest warp, in base-octave cells.
pub const MAX_WARP: f32 = 64.0;

/// Farthest a texel may lie from the pivot, in first-octave cells, before f64 loses
/// the finest octave's position within its cell.
const MAX_CELLS: f64 = 1e9;

/// Most cells one texel may span at the finest octave (far past aliasing), so that
/// lattice coordinates within a block stay below 2²² and round exactly in f32.
const MAX_CELLS_PER_TEXEL: f64 = 16384.0;

/// Prefix of the field names in errors.
const FIELD: &str = "style.holes";

/// Hole creation settings. Every value is a plain number so that a host can keyframe it.
///
/// The noise is N(q) with q = t·g·f (Eq. 4–5): t is a texel centre's position on the light
/// plane in scene units, relative to the pivot; the gradient grid holds g × g random
/// gradients and repeats; f is how often that grid repeats per scene unit. One cell of the
/// first octave is therefore 1 / (g·f) scene units wide, and the whole pattern repeats
/// every 1 / f scene units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HolesDesc {
    /// f: gradient-grid repeats per scene unit (≥ 0). Default 1/32: with the default grid,
    /// first-octave cells of 0.5 units and a pattern that repeats every 32 units.
    pub frequency: f32,
    /// p: weight ratio between successive octaves, in (0, 1]. Default 0.5.
    pub persistence: f32,
    /// o: number of octaves, 1 to 16; octave i is 2ⁱ times finer. Default 4.
    pub octaves: u32,
    /// h: hole probability in [0, 1]; a texel is a hole where N < h. Default 0.5.
    pub threshold: f32,
    /// g: side of the repeating gradient grid, in cells, 1 to 4096. Default 64.
    pub grid_size: u32,
    /// Picks the random gradients; another seed gives another, equally likely pattern.
    pub seed: u32,
    /// Animation time, in seconds (frame / fps). Default 0.
    pub time: f32,
    /// Rotation speed of the first lookup, in radians per second; its sign picks the
    /// direction. Motion grows with distance from the pivot. Default 0.02.
    pub speed: f32,
    /// Strength of the animation: the first lookup moves the second by up to ±warp/2
    /// first-octave cells (0 to 64). 0 gives the static map of Eq. 4–5. Larger values
    /// change the map more over time but streak it along the diagonal (above about 1 the
    /// warp folds the pattern). Default 0.5.
    pub warp: f32,
    /// World point the noise is anchored to and rotates about (projected along the light).
    /// Default the origin.
    pub pivot: [f32; 3],
    /// Object ids whose occluders get holes. Default none, which changes nothing.
    pub objects: Vec<u32>,
}

impl Default for HolesDesc {
    fn default() -> Self {
        Self {
            frequency: 1.0 / 32.0,
            persistence: 0.5,
            octaves: 4,
            threshold: 0.5,
            grid_size: 64,
            seed: 0,
            time: 0.0,
            speed: 0.02,
            warp: 0.5,
            pivot: [0.0; 3],
            objects: Vec::new(),
        }
    }
}

impl HolesDesc {
    /// Checks every value and names the first offending field (`style.holes.<field>`).
    pub fn validate(&self) -> Result<()> {
        let field = |name: &str| format!("{FIELD}.{name}");
        finite_in(&field("frequency"), self.frequency, 0.0, MAX_FREQUENCY)?;
        let persistence = self.persistence;
        if !(persistence > 0.0 && persistence <= 1.0) {
            return Err(Error::invalid(
                field("persistence"),
                format!("{persistence} is outside (0, 1]"),
            ));
        }
        if !(1..=MAX_OCTAVES).contains(&self.octaves) {
            return Err(Error::invalid(
                field("octaves"),
                format!("{} is outside 1..={MAX_OCTAVES}", self.octaves),
            ));
        }
        finite_in(&field("threshold"), self.threshold, 0.0, 1.0)?;
        if !(1..=MAX_GRID_SIZE).contains(&self.grid_size) {
            return Err(Error::invalid(
                field("grid_size"),
                format!("{} is outside 1..={MAX_GRID_SIZE}", self.grid_size),
            ));
        }
        if !self.time.is_finite() {
            return Err(Error::invalid(field("time"), "is not finite"));
        }
        if !self.speed.is_finite() {
            return Err(Error::invalid(field("speed"), "is not finite"));
        }
        finite_in(&field("warp"), self.warp, 0.0, MAX_WARP)?;
        if let Some(axis) = self.pivot.iter().position(|c| !c.is_finite()) {
            return Err(Error::invalid(
                format!("{FIELD}.pivot[{axis}]"),
                "is not finite",
            ));
        }
        if let Some(index) = self.objects.iter().position(|&id| id == NO_OBJECT) {
            return Err(Error::invalid(
                format!("{FIELD}.objects[{index}]"),
                format!("{NO_OBJECT} marks texels without an occluder, not an object"),
            ));
        }
        Ok(())
    }
}

fn finite_in(field: &str, value: f32, min: f32, max: f32) -> Result<()> {
    if !value.is_finite() {
        return Err(Error::invalid(field, format!("{value} is not finite")));
    }
    if value < min || value > max {
        return Err(Error::invalid(
            field,
            format!("{value} is outside [{min}, {max}]"),
        ));
    }
    Ok(())
}

/// Texels per evaluation block: rows are cut at fixed multiples of it, so results do not
/// depend on how rows are shared between threads, and a block without a chosen object
/// costs nothing.
const BLOCK: usize = 64;

/// [0, 1, …, BLOCK − 1] as floats, the lane offsets of a block.
const LANE: [f32; BLOCK] = {
    let mut lanes = [0.0; BLOCK];
    let mut i = 0;
    while i < BLOCK {
        lanes[i] = i as f32;
        i += 1;
    }
    lanes
};

/// One octave of Eq. 5.
#[derive(Clone, Copy, Debug)]
struct Octave {
    /// 2ⁱ: how much finer than the first octave.
    scale: f64,
    /// pⁱ / max(1, o − i − 1), divided by the sum over all octaves.
    weight: f32,
    /// Shift in this octave's cells, so that the octaves' lattice points (where Perlin
    /// noise is always zero) do not line up.
    shift: DVec2,
    seed: u32,
}

/// Where one octave's samples of one block lie: lane k (texel x0 + k) at
/// `base + k·step + scale·offset_k` on both axes, in that octave's cells.
#[derive(Clone, Copy, Default)]
struct OctaveBlock {
    base_x: f32,
    base_y: f32,
    step_x: f32,
    step_y: f32,
    scale: f32,
    weight: f32,
    seed: u32,
}

/// The animated noise field of one frame, laid over one shadow map's texels.
#[derive(Clone, Debug)]
pub struct HoleNoise {
    size: u32,
    threshold: f32,
    warp: f32,
    period: Period,
    octaves: Vec<Octave>,
    /// q at the centre of texel (0, 0), in first-octave cells, and its change per texel
    /// in x and in y.
    origin: DVec2,
    per_x: DVec2,
    per_y: DVec2,
    /// The rotation of the first lookup, as (cos θ, sin θ).
    rotation: DVec2,
    chosen: Chosen,
    kernels: Kernels,
}

impl HoleNoise {
    /// The noise of `desc` on a `size` × `size` map placed by `texel_from_world`.
    pub fn new(desc: &HolesDesc, texel_from_world: &DMat4, size: u32) -> Result<Self> {
        desc.validate()?;
        if !(MIN_SHADOW_MAP_SIZE..=MAX_SHADOW_MAP_SIZE).contains(&size) {
            return Err(Error::invalid(
                "shadow_map.size",
                format!("{size} is outside {MIN_SHADOW_MAP_SIZE}..={MAX_SHADOW_MAP_SIZE}"),
            ));
        }
        let plane = LightPlane::new(texel_from_world)?;
        let cells_per_unit = desc.grid_size as f64 * desc.frequency as f64;
        let pivot = plane.project(DVec3::from_array(desc.pivot.map(f64::from)));
        let at = |texel: DVec2| (plane.at_texel(texel) - pivot) * cells_per_unit;
        let origin = at(DVec2::splat(0.5));
        let per_x = at(DVec2::new(1.5, 0.5)) - origin;
        let per_y = at(DVec2::new(0.5, 1.5)) - origin;
        let reach = origin.abs() + (per_x.abs() + per_y.abs()) * size as f64;
        if !reach.is_finite() || reach.max_element() > MAX_CELLS {
            return Err(Error::invalid(
                format!("{FIELD}.frequency"),
                format!(
                    "the map reaches {:.3e} noise cells from the pivot, more than the noise \
                     resolves ({MAX_CELLS:e}); lower the frequency or grid size, or move the pivot",
                    reach.max_element()
                ),
            ));
        }

        let count = desc.octaves as usize;
        let finest = (1u64 << (count - 1)) as f64;
        let cells_per_texel = per_x.length().max(per_y.length()) * finest;
        if cells_per_texel > MAX_CELLS_PER_TEXEL {
            return Err(Error::invalid(
                format!("{FIELD}.frequency"),
                format!(
                    "the finest octave would have {cells_per_texel:.3e} noise cells per texel \
                     (at most {MAX_CELLS_PER_TEXEL}); lower the frequency, grid size or octaves"
                ),
            ));
        }
        let raw: Vec<f64> = (0..count)
            .map(|i| {
                let damping = (count as f64 - i as f64 - 1.0).max(1.0);
                (desc.persistence as f64).powi(i as i32) / damping
            })
            .collect();
        let total: f64 = raw.iter().sum();
        let octaves = raw
            .iter()
            .enumerate()
            .map(|(i, &weight)| Octave {
                scale: (1u64 << i) as f64,
                weight: (weight / total) as f32,
                // Additive recurrence on the plastic number: well spread, never on the lattice.
                shift: DVec2::new(
                    (i as f64 * 0.754_877_666_246_693).fract(),
                    (i as f64 * 0.569_840_290_998_053).fract(),
                ),
                seed: mix(desc.seed ^ mix(i as u32 ^ 0x9e37_79b9)),
            })
            .collect();

        let angle = (desc.speed as f64 * desc.time as f64) % std::f64::consts::TAU;
        let (sin, cos) = angle.sin_cos();
        Ok(Self {
            size,
            threshold: desc.threshold,
            warp: desc.warp,
            period: Period::new(desc.grid_size),
            octaves,
            origin,
            per_x,
            per_y,
            rotation: DVec2::new(cos, sin),
            chosen: Chosen::new(&desc.objects),
            kernels: Kernels::detect(),
        })
    }

    /// The noise of `desc` on `map`'s texels.
    pub fn for_map(desc: &HolesDesc, map: &ShadowMap) -> Result<Self> {
        Self::new(desc, &map.texel_from_world, map.size)
    }

    pub fn size(&self) -> u32 {
        self.size
    }

    /// Whether [`HoleNoise::apply`] opens nothing whatever the map: no object chosen, or
    /// a threshold no noise lies below.
    pub fn opens_nothing(&self) -> bool {
        self.chosen.is_empty() || self.threshold <= 0.0
    }

    /// This frame's noise as plain values, for a device that evaluates it texel by
    /// texel exactly as [`HoleNoise::apply`] does.
    pub fn params(&self) -> NoiseParams {
        NoiseParams {
            size: self.size,
            block: BLOCK as u32,
            threshold: self.threshold,
            warp: self.warp,
            origin: self.origin.to_array(),
            per_x: self.per_x.to_array(),
            per_y: self.per_y.to_array(),
            rotation: self.rotation.to_array(),
            period_whole: self.period.whole,
            period_mask: self.period.mask,
            period_cells: self.period.cells,
            period_inverse: self.period.inverse,
            perlin_scale: PERLIN_SCALE,
            octaves: self
                .octaves
                .iter()
                .map(|octave| OctaveParams {
                    scale: octave.scale,
                    shift: octave.shift.to_array(),
                    weight: octave.weight,
                    seed: octave.seed,
                })
                .collect(),
            objects: self.chosen.0.clone(),
        }
    }

    /// N at every texel of row `y` (`out` holds `size` values), in [0, 1].
    pub fn noise_row(&self, y: u32, out: &mut [f32]) -> Result<()> {
        if y >= self.size || out.len() != self.size as usize {
            return Err(Error::invalid(
                "holes.noise_row",
                format!(
                    "row {y} with {} values does not fit a {}² map",
                    out.len(),
                    self.size
                ),
            ));
        }
        self.row(y, out);
        Ok(())
    }

    /// N for the whole map, row-major, in [0, 1].
    pub fn noise_map(&self) -> Vec<f32> {
        let size = self.size as usize;
        let mut noise = vec![0.0; size * size];
        noise
            .par_chunks_mut(size)
            .enumerate()
            .for_each(|(y, row)| self.row(y as u32, row));
        noise
    }

    /// H of Eq. 4 for the whole map, row-major: true where a chosen occluder would open.
    pub fn hole_map(&self) -> Vec<bool> {
        let threshold = self.threshold;
        self.noise_map()
            .into_iter()
            .map(|n| n < threshold)
            .collect()
    }

    /// Removes the occluders of the chosen objects wherever H is a hole: their depth
    /// becomes +∞. Every other texel keeps its depth bit for bit; `ids` is only read.
    /// Returns how many texels were opened.
    pub fn apply(&self, depth: &mut [f32], ids: &[u32]) -> Result<usize> {
        let texels = self.size as usize * self.size as usize;
        if depth.len() != texels || ids.len() != texels {
            return Err(Error::invalid(
                "holes.depth",
                format!(
                    "{} depths and {} ids do not fill a {}² map",
                    depth.len(),
                    ids.len(),
                    self.size
                ),
            ));
        }
        let chosen = &self.chosen;
        if chosen.is_empty() || self.threshold <= 0.0 {
            return Ok(0);
        }
        let size = self.size as usize;
        let opened = depth
            .par_chunks_mut(size)
            .zip(ids.par_chunks(size))
            .enumerate()
            .map(|(y, (depth, ids))| {
                let mut lanes = [0.0; BLOCK];
                let mut marks = [false; BLOCK];
                let mut noise = [0.0; BLOCK];
                let mut opened = 0;
                for (index, (depth, ids)) in
                    depth.chunks_mut(BLOCK).zip(ids.chunks(BLOCK)).enumerate()
                {
                    // Only texels of chosen objects are evaluated, packed into lanes (in
                    // place where every texel of the block is chosen).
                    let marks = &mut marks[..ids.len()];
                    let count = chosen.mark(ids, marks);
                    if count == 0 {
                        continue;
                    }
                    let lanes: &[f32] = if count == ids.len() {
                        &LANE[..count]
                    } else {
                        let mut packed = 0;
                        for (lane, &marked) in marks.iter().enumerate() {
                            if marked {
                                lanes[packed] = LANE[lane];
                                packed += 1;
                            }
                        }
                        &lanes[..count]
                    };
                    self.block(index * BLOCK, y as u32, lanes, &mut noise[..count]);
                    let threshold = self.threshold;
                    if count == depth.len() {
                        // Every texel chosen, the lanes in place: opened without a branch
                        // on the noise, which would mispredict on every other texel.
                        for (depth, &noise) in depth.iter_mut().zip(&noise) {
                            let open = noise < threshold;
                            *depth = if open { f32::INFINITY } else { *depth };
                            opened += open as usize;
                        }
                        continue;
                    }
                    for (&lane, &noise) in lanes.iter().zip(&noise[..count]) {
                        if noise < threshold {
                            depth[lane as usize] = f32::INFINITY;
                            opened += 1;
                        }
                    }
                }
                opened
            })
            .sum();
        Ok(opened)
    }

    fn row(&self, y: u32, out: &mut [f32]) {
        for (index, out) in out.chunks_mut(BLOCK).enumerate() {
            self.block(index * BLOCK, y, &LANE[..out.len()], out);
        }
    }

    /// N at texels `x0 + lanes[k]` of row `y`. A texel's value depends only on its
    /// block and lane, not on which other lanes are evaluated with it.
    fn block(&self, x0: usize, y: u32, lanes: &[f32], out: &mut [f32]) {
        let at = self.origin + self.per_x * x0 as f64 + self.per_y * y as f64;
        let period = self.period.cells as f64;
        let lay = |octave: &Octave, at: DVec2, step: DVec2| {
            // Reduced to one period in f64 here, so lanes only add small f32 offsets.
            let base = at * octave.scale + octave.shift;
            let step = step * octave.scale;
            OctaveBlock {
                base_x: base.x.rem_euclid(period) as f32,
                base_y: base.y.rem_euclid(period) as f32,
                step_x: step.x as f32,
                step_y: step.y as f32,
                scale: octave.scale as f32,
                weight: octave.weight,
                seed: octave.seed,
            }
        };
        let mut straight = [OctaveBlock::default(); MAX_OCTAVES as usize];
        for (block, octave) in straight.iter_mut().zip(&self.octaves) {
            *block = lay(octave, at, self.per_x);
        }
        let rotated = lay(&self.octaves[0], self.rotate(at), self.rotate(self.per_x));
        let blocks = Blocks {
            rotated,
            straight: &straight[..self.octaves.len()],
            warp: self.warp,
            period: self.period,
        };
        self.kernels.two_step(&blocks, lanes, out);
    }

    fn rotate(&self, v: DVec2) -> DVec2 {
        let (cos, sin) = (self.rotation.x, self.rotation.y);
        DVec2::new(cos * v.x - sin * v.y, sin * v.x + cos * v.y)
    }
}

/// One frame's [`HoleNoise`] as plain values (see [`HoleNoise::params`]): per block of
/// `block` texels of a row, q is laid out in f64 from `origin`, `per_x` and `per_y` and
/// reduced to one period; each texel then adds its lane in f32.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseParams {
    pub size: u32,
    pub block: u32,
    pub threshold: f32,
    pub warp: f32,
    pub origin: [f64; 2],
    pub per_x: [f64; 2],
    pub per_y: [f64; 2],
    /// (cos θ, sin θ) of the first lookup.
    pub rotation: [f64; 2],
    /// The lattice period in cells; `period_mask` is period − 1 where that wraps it (a
    /// power of two above 1), else 0.
    pub period_whole: u32,
    pub period_mask: u32,
    pub period_cells: f32,
    pub period_inverse: f32,
    /// Scales Perlin noise into [−1, 1].
    pub perlin_scale: f32,
    pub octaves: Vec<OctaveParams>,
    /// The chosen object ids, sorted and without duplicates.
    pub objects: Vec<u32>,
}

/// One octave of Eq. 5 (see [`NoiseParams`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OctaveParams {
    /// 2ⁱ.
    pub scale: f64,
    /// Shift in this octave's cells.
    pub shift: [f64; 2],
    pub weight: f32,
    pub seed: u32,
}

/// A copy of `map`'s depth with holes opened in the occluders of `desc.objects`.
pub fn holed_depth(desc: &HolesDesc, map: &ShadowMap) -> Result<Vec<f32>> {
    let mut depth = map.depth.clone();
    if desc.objects.is_empty() {
        desc.validate()?;
        return Ok(depth);
    }
    HoleNoise::for_map(desc, map)?.apply(&mut depth, &map.ids)?;
    Ok(depth)
}

/// The set of chosen object ids.
#[derive(Clone, Debug)]
struct Chosen(Vec<u32>);

impl Chosen {
    fn new(objects: &[u32]) -> Self {
        let mut ids: Vec<u32> = objects
            .iter()
            .copied()
            .filter(|&id| id != NO_OBJECT)
            .collect();
        ids.sort_unstable();
        ids.dedup();
        Self(ids)
    }

    fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Marks which of `ids` are chosen in `marks` (as long as `ids`); returns how many.
    /// A few objects are compared with every id in turn, which vectorizes; more are
    /// searched for.
    #[inline]
    fn mark(&self, ids: &[u32], marks: &mut [bool]) -> usize {
        if self.0.len() <= 8 {
            marks.fill(false);
            for &object in &self.0 {
                for (mark, &id) in marks.iter_mut().zip(ids) {
                    *mark |= id == object;
                }
            }
        } else {
            for (mark, &id) in marks.iter_mut().zip(ids) {
                *mark = self.0.binary_search(&id).is_ok();
            }
        }
        marks.iter().map(|&mark| mark as usize).sum()
    }
}

/// Orthonormal coordinates in scene units on the plane the map's texel x and y span.
struct LightPlane {
    axes: [DVec3; 2],
    /// plane = `plane_from_texel` · (texel − `offset`); lower triangular.
    plane_from_texel: [[f64; 2]; 2],
    offset: DVec2,
}

impl LightPlane {
    fn new(texel_from_world: &DMat4) -> Result<Self> {
        let bad = |reason: &str| Error::invalid("shadow_map.texel_from_world", reason.to_owned());
        if !texel_from_world.is_finite() {
            return Err(bad("contains NaN or infinity"));
        }
        let row_x = texel_from_world.row(0);
        let row_y = texel_from_world.row(1);
        let (a, b) = (row_x.truncate(), row_y.truncate());
        let u = a
            .try_normalize()
            .ok_or_else(|| bad("has no texel x axis"))?;
        let v = (b - u * b.dot(u))
            .try_normalize()
            .ok_or_else(|| bad("has parallel texel x and y axes"))?;
        // In (u, v) coordinates texel x = (a·u)·u and texel y = (b·u)·u + (b·v)·v.
        let (m00, m10, m11) = (a.dot(u), b.dot(u), b.dot(v));
        let det = m00 * m11;
        if !det.is_finite() || det.abs() < 1e-300 {
            return Err(bad("is singular on the light plane"));
        }
        Ok(Self {
            axes: [u, v],
            plane_from_texel: [[1.0 / m00, 0.0], [-m10 / det, 1.0 / m11]],
            offset: DVec2::new(row_x.w, row_y.w),
        })
    }

    fn at_texel(&self, texel: DVec2) -> DVec2 {
        let t = texel - self.offset;
        let m = &self.plane_from_texel;
        DVec2::new(m[0][0] * t.x + m[0][1] * t.y, m[1][0] * t.x + m[1][1] * t.y)
    }

    fn project(&self, world: DVec3) -> DVec2 {
        DVec2::new(self.axes[0].dot(world), self.axes[1].dot(world))
    }
}

/// lowbias32 by Chris Wellons: a cheap integer hash with good avalanche.
#[inline(always)]
fn mix(mut h: u32) -> u32 {
    h ^= h >> 16;
    h = h.wrapping_mul(0x7feb_352d);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846c_a68b);
    h ^= h >> 16;
    h
}

/// A lattice point's hash, of which only the top bits are used: the xorshift brings the
/// first product's high bits down for the second multiply to spread up again. Half the
/// work of `mix`, which the hot loop feels.
#[inline(always)]
fn lattice_hash(point: u32) -> u32 {
    let h = point.wrapping_mul(0x7feb_352d);
    (h ^ (h >> 15)).wrapping_mul(0x846c_a68b)
}

/// The lattice's period in cells: a power of two wraps with a mask, any other size with
/// a float division.
#[derive(Clone, Copy, Debug)]
struct Period {
    whole: u32,
    cells: f32,
    inverse: f32,
    /// cells − 1 where cells is a power of two, else 0.
    mask: u32,
    /// log₂ cells where cells is a power of two.
    row_shift: u32,
}

impl Period {
    fn new(cells: u32) -> Self {
        Self {
            whole: cells,
            cells: cells as f32,
            inverse: 1.0 / cells as f32,
            mask: if cells.is_power_of_two() {
                cells - 1
            } else {
                0
            },
            row_shift: cells.trailing_zeros(),
        }
    }
}

/// The instruction set the block kernel runs with. Every variant runs the same scalar
/// code without fused multiply-adds, so all give bit-identical noise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kernels {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl Kernels {
    fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Kernels::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return Kernels::Avx2;
            }
        }
        Kernels::Portable
    }

    /// Every variant this CPU can run.
    #[cfg(test)]
    fn available() -> Vec<Self> {
        #[allow(unused_mut)]
        let mut kernels = vec![Kernels::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                kernels.push(Kernels::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                kernels.push(Kernels::Avx512);
            }
        }
        kernels
    }

    #[inline]
    fn two_step(self, blocks: &Blocks, lanes: &[f32], out: &mut [f32]) {
        let masked = blocks.period.mask != 0;
        match (self, masked) {
            (Kernels::Portable, true) => two_step::<true>(blocks, lanes, out),
            (Kernels::Portable, false) => two_step::<false>(blocks, lanes, out),
            // SAFETY: `detect` only chose this variant where the CPU has AVX-512.
            #[cfg(target_arch = "x86_64")]
            (Kernels::Avx512, true) => unsafe { two_step_avx512::<true>(blocks, lanes, out) },
            #[cfg(target_arch = "x86_64")]
            (Kernels::Avx512, false) => unsafe { two_step_avx512::<false>(blocks, lanes, out) },
            // SAFETY: `detect` only chose this variant where the CPU has AVX2.
            #[cfg(target_arch = "x86_64")]
            (Kernels::Avx2, true) => unsafe { two_step_avx2::<true>(blocks, lanes, out) },
            #[cfg(target_arch = "x86_64")]
            (Kernels::Avx2, false) => unsafe { two_step_avx2::<false>(blocks, lanes, out) },
        }
    }
}

/// Everything the kernel needs for one block.
struct Blocks<'a> {
    /// The first octave at the rotated points.
    rotated: OctaveBlock,
    /// Every octave at the straight points.
    straight: &'a [OctaveBlock],
    warp: f32,
    period: Period,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn two_step_avx2<const MASKED: bool>(blocks: &Blocks, lanes: &[f32], out: &mut [f32]) {
    two_step::<MASKED>(blocks, lanes, out)
}

/// [`two_step`] sixteen lanes at once in AVX-512 intrinsics, operation for operation
/// (no fused multiply-adds), but that each corner's gradient is picked from a table with
/// one permute per axis ([`avx512::gradients`]) rather than by masks, which took most of
/// the time.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn two_step_avx512<const MASKED: bool>(blocks: &Blocks, lanes: &[f32], out: &mut [f32]) {
    use std::arch::x86_64::*;
    let count = lanes.len().min(out.len()).min(BLOCK);
    let groups = count.div_ceil(WIDE_GROUP);
    let mut padded = [0.0f32; BLOCK];
    padded[..count].copy_from_slice(&lanes[..count]);
    let period = blocks.period;
    let load = |values: &[f32; BLOCK], group: usize| {
        // SAFETY: a group's sixteen values lie within the block's array.
        unsafe { _mm512_loadu_ps(values[group * WIDE_GROUP..].as_ptr()) }
    };
    let mut offset = [0.0f32; BLOCK];
    if blocks.warp != 0.0 {
        let half_warp = _mm512_set1_ps(0.5 * blocks.warp);
        let first = &blocks.rotated;
        for group in 0..groups {
            let lane = load(&padded, group);
            let x = _mm512_add_ps(
                _mm512_set1_ps(first.base_x),
                _mm512_mul_ps(lane, _mm512_set1_ps(first.step_x)),
            );
            let y = _mm512_add_ps(
                _mm512_set1_ps(first.base_y),
                _mm512_mul_ps(lane, _mm512_set1_ps(first.step_y)),
            );
            let noise = avx512::perlin::<MASKED>(x, y, first.seed, period);
            _mm512_storeu_ps(
                offset[group * WIDE_GROUP..].as_mut_ptr(),
                _mm512_mul_ps(half_warp, noise),
            );
        }
    }
    let mut sums = [_mm512_setzero_ps(); BLOCK / WIDE_GROUP];
    for octave in blocks.straight {
        for (group, sum) in sums.iter_mut().enumerate().take(groups) {
            let lane = load(&padded, group);
            let shift = _mm512_mul_ps(_mm512_set1_ps(octave.scale), load(&offset, group));
            let at = |base: f32, step: f32| {
                _mm512_add_ps(
                    _mm512_add_ps(
                        _mm512_set1_ps(base),
                        _mm512_mul_ps(lane, _mm512_set1_ps(step)),
                    ),
                    shift,
                )
            };
            let (x, y) = (
                at(octave.base_x, octave.step_x),
                at(octave.base_y, octave.step_y),
            );
            let noise = avx512::perlin::<MASKED>(x, y, octave.seed, period);
            *sum = _mm512_add_ps(*sum, _mm512_mul_ps(_mm512_set1_ps(octave.weight), noise));
        }
    }
    let mut sum = [0.0f32; BLOCK];
    for (group, lanes) in sums.iter().enumerate() {
        _mm512_storeu_ps(sum[group * WIDE_GROUP..].as_mut_ptr(), *lanes);
    }
    for (out, &sum) in out[..count].iter_mut().zip(&sum[..count]) {
        *out = (0.5 + 0.5 * sum).clamp(0.0, 1.0);
    }
}

/// [`perlin`] and its parts for sixteen lanes in AVX-512, operation for operation.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Period, PERLIN_SCALE, ROUNDER};
    use std::arch::x86_64::*;

    /// [`super::perlin`] of sixteen points.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub(super) fn perlin<const MASKED: bool>(
        x: __m512,
        y: __m512,
        seed: u32,
        period: Period,
    ) -> __m512 {
        let (dx, x0, x1) = cell::<MASKED>(x, period);
        let (dy, y0, y1) = cell::<MASKED>(y, period);
        let row = |y: __m512i| {
            if MASKED {
                _mm512_sllv_epi32(y, _mm512_set1_epi32(period.row_shift as i32))
            } else {
                _mm512_mullo_epi32(y, _mm512_set1_epi32(period.whole as i32))
            }
        };
        let (row0, row1) = (row(y0), row(y1));
        let seed = _mm512_set1_epi32(seed as i32);
        let hash = |row: __m512i, x: __m512i| {
            lattice_hash(_mm512_xor_si512(_mm512_add_epi32(row, x), seed))
        };
        let one = _mm512_set1_ps(1.0);
        let (dx1, dy1) = (_mm512_sub_ps(dx, one), _mm512_sub_ps(dy, one));
        let n00 = gradients(hash(row0, x0), dx, dy);
        let n10 = gradients(hash(row0, x1), dx1, dy);
        let n01 = gradients(hash(row1, x0), dx, dy1);
        let n11 = gradients(hash(row1, x1), dx1, dy1);
        let (u, v) = (fade(dx), fade(dy));
        let bottom = _mm512_add_ps(n00, _mm512_mul_ps(u, _mm512_sub_ps(n10, n00)));
        let top = _mm512_add_ps(n01, _mm512_mul_ps(u, _mm512_sub_ps(n11, n01)));
        let blend = _mm512_add_ps(bottom, _mm512_mul_ps(v, _mm512_sub_ps(top, bottom)));
        _mm512_mul_ps(_mm512_set1_ps(PERLIN_SCALE), blend)
    }

    /// [`super::cell`] of sixteen coordinates.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn cell<const MASKED: bool>(x: __m512, period: Period) -> (__m512, __m512i, __m512i) {
        let rounder = _mm512_set1_ps(ROUNDER);
        let one = _mm512_set1_ps(1.0);
        let shifted = _mm512_add_ps(x, rounder);
        let nearest = _mm512_sub_ps(shifted, rounder);
        let down = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(nearest, x);
        let floor = _mm512_mask_sub_ps(nearest, down, nearest, one);
        let fraction = _mm512_sub_ps(x, floor);
        if MASKED {
            let whole = _mm512_sub_epi32(
                _mm512_castps_si512(shifted),
                _mm512_set1_epi32(ROUNDER.to_bits() as i32),
            );
            let whole = _mm512_mask_sub_epi32(whole, down, whole, _mm512_set1_epi32(1));
            let mask = _mm512_set1_epi32(period.mask as i32);
            let next = _mm512_add_epi32(whole, _mm512_set1_epi32(1));
            (
                fraction,
                _mm512_and_si512(whole, mask),
                _mm512_and_si512(next, mask),
            )
        } else {
            let cells = _mm512_set1_ps(period.cells);
            let scaled = _mm512_mul_ps(floor, _mm512_set1_ps(period.inverse));
            let nearest = _mm512_sub_ps(_mm512_add_ps(scaled, rounder), rounder);
            let above = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(nearest, scaled);
            let turns = _mm512_mask_sub_ps(nearest, above, nearest, one);
            let low = _mm512_sub_ps(floor, _mm512_mul_ps(cells, turns));
            let low = _mm512_mask_sub_ps(
                low,
                _mm512_cmp_ps_mask::<_CMP_GE_OQ>(low, cells),
                low,
                cells,
            );
            let zero = _mm512_setzero_ps();
            let low =
                _mm512_mask_add_ps(low, _mm512_cmp_ps_mask::<_CMP_LT_OQ>(low, zero), low, cells);
            let next = _mm512_add_ps(low, one);
            let high =
                _mm512_mask_mov_ps(next, _mm512_cmp_ps_mask::<_CMP_GE_OQ>(next, cells), zero);
            (fraction, whole_to_u32(low), whole_to_u32(high))
        }
    }

    /// [`super::whole_to_u32`] of sixteen whole numbers.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn whole_to_u32(whole: __m512) -> __m512i {
        _mm512_sub_epi32(
            _mm512_castps_si512(_mm512_add_ps(whole, _mm512_set1_ps(8_388_608.0))),
            _mm512_set1_epi32(0x4b00_0000),
        )
    }

    /// [`super::lattice_hash`] of sixteen points.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn lattice_hash(point: __m512i) -> __m512i {
        let h = _mm512_mullo_epi32(point, _mm512_set1_epi32(0x7feb_352d));
        let h = _mm512_xor_si512(h, _mm512_srli_epi32::<15>(h));
        _mm512_mullo_epi32(h, _mm512_set1_epi32(0x846c_a68bu32 as i32))
    }

    /// [`super::gradient`] of sixteen hashes: the gradient (gx, gy) its top three bits
    /// pick, from a table, dotted with (dx, dy). gx·dx and gy·dy are exact (each factor
    /// is ±1 or ±½), and their sum is the scalar's major + ½·minor in the other order,
    /// which an addition does not see.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn gradients(hash: __m512i, dx: __m512, dy: __m512) -> __m512 {
        // Index bits: 29 swaps the axes, 30 negates the minor one, 31 the major one.
        const X: [f32; 16] = [
            1.0, 0.5, 1.0, -0.5, -1.0, 0.5, -1.0, -0.5, 1.0, 0.5, 1.0, -0.5, -1.0, 0.5, -1.0, -0.5,
        ];
        const Y: [f32; 16] = [
            0.5, 1.0, -0.5, 1.0, 0.5, -1.0, -0.5, -1.0, 0.5, 1.0, -0.5, 1.0, 0.5, -1.0, -0.5, -1.0,
        ];
        let index = _mm512_srli_epi32::<29>(hash);
        // SAFETY: each table holds sixteen values, all that the unaligned load reads.
        let (x, y) = unsafe { (_mm512_loadu_ps(X.as_ptr()), _mm512_loadu_ps(Y.as_ptr())) };
        let gx = _mm512_permutexvar_ps(index, x);
        let gy = _mm512_permutexvar_ps(index, y);
        _mm512_add_ps(_mm512_mul_ps(gx, dx), _mm512_mul_ps(gy, dy))
    }

    /// [`super::fade`] of sixteen values.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn fade(t: __m512) -> __m512 {
        let cube = _mm512_mul_ps(_mm512_mul_ps(t, t), t);
        let inner = _mm512_sub_ps(_mm512_mul_ps(t, _mm512_set1_ps(6.0)), _mm512_set1_ps(15.0));
        let inner = _mm512_add_ps(_mm512_mul_ps(t, inner), _mm512_set1_ps(10.0));
        _mm512_mul_ps(cube, inner)
    }
}

/// Lanes evaluated together; blocks are evaluated in whole groups.
const GROUP: usize = 8;
/// [`GROUP`] of the AVX-512 kernel.
#[cfg(target_arch = "x86_64")]
const WIDE_GROUP: usize = 16;

/// The two-step lookup for the lanes of one block: the first octave at the rotated
/// points gives P ∈ [0, 1]; N is then looked up at the straight points moved by
/// warp·(P − ½) along (1, 1). `MASKED`: the period is a power of two.
#[inline(always)]
fn two_step<const MASKED: bool>(blocks: &Blocks, lanes: &[f32], out: &mut [f32]) {
    let count = lanes.len().min(out.len()).min(BLOCK);
    // Whole groups of fixed size vectorize; lanes past `count` are computed and dropped.
    let groups = count.div_ceil(GROUP);
    let mut padded = [0.0; BLOCK];
    padded[..count].copy_from_slice(&lanes[..count]);
    let period = blocks.period;
    let mut offset = [0.0; BLOCK];
    if blocks.warp != 0.0 {
        let half_warp = 0.5 * blocks.warp;
        let first = &blocks.rotated;
        for (offset, lanes) in offset
            .chunks_exact_mut(GROUP)
            .zip(padded.chunks_exact(GROUP))
            .take(groups)
        {
            for k in 0..GROUP {
                let x = first.base_x + lanes[k] * first.step_x;
                let y = first.base_y + lanes[k] * first.step_y;
                offset[k] = half_warp * perlin::<MASKED>(x, y, first.seed, period);
            }
        }
    }
    let mut sum = [0.0f32; BLOCK];
    for octave in blocks.straight {
        for ((sum, lanes), offset) in sum
            .chunks_exact_mut(GROUP)
            .zip(padded.chunks_exact(GROUP))
            .zip(offset.chunks_exact(GROUP))
            .take(groups)
        {
            for k in 0..GROUP {
                let shift = octave.scale * offset[k];
                let x = octave.base_x + lanes[k] * octave.step_x + shift;
                let y = octave.base_y + lanes[k] * octave.step_y + shift;
                sum[k] += octave.weight * perlin::<MASKED>(x, y, octave.seed, period);
            }
        }
    }
    for (out, &sum) in out[..count].iter_mut().zip(&sum[..count]) {
        *out = (0.5 + 0.5 * sum).clamp(0.0, 1.0);
    }
}

/// Adding 1.5·2²³ rounds a float of magnitude below 2²² to an integer exactly. Lattice
/// coordinates stay below that: a block's base lies within one period (≤ 2¹²), its lanes
/// add at most 2²⁰ (`MAX_CELLS_PER_TEXEL`) and the warp at most 2²⁰ (2¹⁵ · 64 / 2).
const ROUNDER: f32 = 12_582_912.0;

/// The lattice cell of `x` along one axis: the fraction within it, and the wrapped
/// indices of its two ends. Float and integer operations only, so that it vectorizes (a
/// saturating float-to-int conversion or a libm floor would not).
#[inline(always)]
fn cell<const MASKED: bool>(x: f32, period: Period) -> (f32, u32, u32) {
    let shifted = x + ROUNDER;
    let nearest = shifted - ROUNDER;
    let down = nearest > x;
    let floor = if down { nearest - 1.0 } else { nearest };
    if MASKED {
        // In [2²³, 2²⁴) a float's bits count whole numbers: these are floor's, as i32.
        let whole = shifted
            .to_bits()
            .wrapping_sub(ROUNDER.to_bits())
            .wrapping_sub(down as u32);
        (
            x - floor,
            whole & period.mask,
            whole.wrapping_add(1) & period.mask,
        )
    } else {
        let mut low = floor - period.cells * round_down(floor * period.inverse);
        // The product above may round across a multiple of the period; one step fixes it.
        if low >= period.cells {
            low -= period.cells;
        }
        if low < 0.0 {
            low += period.cells;
        }
        let high = if low + 1.0 >= period.cells {
            0.0
        } else {
            low + 1.0
        };
        (x - floor, whole_to_u32(low), whole_to_u32(high))
    }
}

/// floor for |x| ≤ 2²².
#[inline(always)]
fn round_down(x: f32) -> f32 {
    let nearest = (x + ROUNDER) - ROUNDER;
    if nearest > x {
        nearest - 1.0
    } else {
        nearest
    }
}

/// A whole number in [0, 2²³) as an integer, read from its bits after adding 2²³.
#[inline(always)]
fn whole_to_u32(whole: f32) -> u32 {
    (whole + 8_388_608.0).to_bits() - 0x4b00_0000
}

/// One of the eight gradients (±1, ±½) and (±½, ±1), picked by the top three bits of
/// `hash`, dotted with (dx, dy). Eight directions roughly 45° apart avoid the diagonal
/// streaks of the four (±1, ±1) alone.
#[inline(always)]
fn gradient(hash: u32, dx: f32, dy: f32) -> f32 {
    let swap = hash & 0x2000_0000 != 0;
    let (major, minor) = if swap { (dy, dx) } else { (dx, dy) };
    let major = f32::from_bits(major.to_bits() ^ (hash & 0x8000_0000));
    // A select rather than a shift of bit 30: the compiler would fold a left shift into
    // the hash's last multiply and multiply again.
    let minor = if hash & 0x4000_0000 != 0 {
        -minor
    } else {
        minor
    };
    major + 0.5 * minor
}

/// The largest |value| of the noise below with these gradients and fade is 0.7556 (at
/// (½, 0.545) within a cell, found by exhaustive search); this scale takes it just
/// inside ±1.
const PERLIN_SCALE: f32 = 1.0 / 0.76;

/// Classical 2D Perlin gradient noise with a period of `period` cells and the quintic
/// fade, scaled into [−1, 1].
#[inline(always)]
fn perlin<const MASKED: bool>(x: f32, y: f32, seed: u32, period: Period) -> f32 {
    let (dx, x0, x1) = cell::<MASKED>(x, period);
    let (dy, y0, y1) = cell::<MASKED>(y, period);
    // Lattice points are numbered row by row, so distinct points hash distinct numbers;
    // a power-of-two row length is a shift, where a multiply takes twice the port time.
    let row = |y: u32| {
        if MASKED {
            y << period.row_shift
        } else {
            y.wrapping_mul(period.whole)
        }
    };
    let (row0, row1) = (row(y0), row(y1));
    let n00 = gradient(lattice_hash((row0 + x0) ^ seed), dx, dy);
    let n10 = gradient(lattice_hash((row0 + x1) ^ seed), dx - 1.0, dy);
    let n01 = gradient(lattice_hash((row1 + x0) ^ seed), dx, dy - 1.0);
    let n11 = gradient(lattice_hash((row1 + x1) ^ seed), dx - 1.0, dy - 1.0);
    let (u, v) = (fade(dx), fade(dy));
    let bottom = n00 + u * (n10 - n00);
    let top = n01 + u * (n11 - n01);
    PERLIN_SCALE * (bottom + v * (top - bottom))
}

/// 6t⁵ − 15t⁴ + 10t³: C² joins between cells.
#[inline(always)]
fn fade(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn random_points(count: usize, range: f32) -> Vec<(f32, f32)> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        (0..count)
            .map(|_| {
                (
                    rng.random_range(-range..range),
                    rng.random_range(-range..range),
                )
            })
            .collect()
    }

    #[test]
    fn floor_matches_libm_within_its_range() {
        for (x, _) in random_points(100_000, 4_000_000.0)
            .into_iter()
            .chain(random_points(100_000, 3.0))
        {
            assert_eq!(round_down(x), x.floor(), "{x}");
        }
        for x in [
            -2.0,
            -1.0,
            -0.5,
            -0.0,
            0.0,
            0.5,
            1.0,
            4_194_303.5,
            -4_194_303.5,
        ] {
            assert_eq!(round_down(x), x.floor(), "{x}");
        }
    }

    #[test]
    fn cells_wrap_into_the_period_with_or_without_the_mask() {
        for cells in [1, 2, 3, 7, 64, 100, 4096] {
            let period = Period::new(cells);
            for (x, _) in random_points(20_000, 3_000_000.0) {
                let (fraction, low, high) = cell::<false>(x, period);
                let floor = x.floor();
                assert_eq!(fraction, x - floor);
                assert_eq!(
                    low as i64,
                    (floor as i64).rem_euclid(cells as i64),
                    "{x} {cells}"
                );
                assert_eq!(high as i64, (floor as i64 + 1).rem_euclid(cells as i64));
                if cells.is_power_of_two() {
                    assert_eq!(cell::<true>(x, period), (fraction, low, high), "{x}");
                }
            }
        }
    }

    #[test]
    fn perlin_is_periodic_and_stays_within_one() {
        let period = Period::new(12);
        let (mut low, mut high) = (0.0f32, 0.0f32);
        for (x, y) in random_points(200_000, 1000.0) {
            let value = perlin::<false>(x, y, 99, period);
            assert!((-1.0..=1.0).contains(&value), "{value} at ({x}, {y})");
            (low, high) = (low.min(value), high.max(value));
            let (x, y) = (x.floor() + 0.25, y.floor() + 0.75);
            assert_eq!(
                perlin::<false>(x, y, 99, period),
                perlin::<false>(x + 12.0, y - 24.0, 99, period)
            );
        }
        // The scale uses most of the range, so the bound above is not met trivially.
        assert!(low < -0.8 && high > 0.8, "range [{low}, {high}]");
    }

    #[test]
    fn perlin_is_zero_on_the_lattice_and_continuous_across_cells() {
        let period = Period::new(64);
        for i in -5..5 {
            let x = i as f32;
            assert_eq!(perlin::<true>(x, 3.0, 1, period), 0.0);
            let below = perlin::<true>(x - 1e-4, 3.4, 1, period);
            let above = perlin::<true>(x + 1e-4, 3.4, 1, period);
            assert!(
                (below - above).abs() < 1e-3,
                "{below} vs {above} at x = {x}"
            );
        }
    }

    #[test]
    fn every_kernel_gives_the_same_bits() {
        let desc = HolesDesc {
            time: 3.0,
            warp: 2.0,
            ..HolesDesc::default()
        };
        let map = DMat4::from_scale(DVec3::new(20.0, 20.0, 1.0));
        for grid_size in [64, 60] {
            let desc = HolesDesc {
                grid_size,
                ..desc.clone()
            };
            let mut noise = HoleNoise::new(&desc, &map, 128).unwrap();
            noise.kernels = Kernels::Portable;
            let portable = noise.noise_map();
            for kernels in Kernels::available() {
                noise.kernels = kernels;
                let noise = noise.noise_map();
                assert!(
                    portable
                        .iter()
                        .zip(&noise)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{kernels:?}"
                );
            }
        }
    }

    #[test]
    fn a_texel_does_not_depend_on_which_lanes_are_evaluated_with_it() {
        let desc = HolesDesc {
            time: 2.0,
            ..HolesDesc::default()
        };
        let noise = HoleNoise::new(&desc, &DMat4::from_scale(DVec3::splat(30.0)), 256).unwrap();
        let mut all = [0.0; BLOCK];
        noise.block(128, 17, &LANE, &mut all);
        let lanes = [3.0, 9.0, 10.0, 63.0];
        let mut some = [0.0; 4];
        noise.block(128, 17, &lanes, &mut some);
        for (lane, value) in lanes.iter().zip(some) {
            assert_eq!(all[*lane as usize].to_bits(), value.to_bits());
        }
    }

    #[test]
    fn the_light_plane_inverts_the_maps_xy() {
        let world_to_texel = DMat4::from_cols_array(&[
            3.0, 0.5, 0.2, 0.0, //
            -1.0, 2.0, 0.7, 0.0, //
            0.4, -0.3, 1.0, 0.0, //
            5.0, -7.0, 2.0, 1.0,
        ]);
        let plane = LightPlane::new(&world_to_texel).unwrap();
        let world = DVec3::new(1.3, -2.1, 0.6);
        let texel = world_to_texel.transform_point3(world).truncate();
        assert!((plane.at_texel(texel) - plane.project(world)).length() < 1e-12);
        // Both axes are unit length, so plane coordinates are in scene units.
        let [u, v] = plane.axes;
        assert!((u.length() - 1.0).abs() < 1e-12 && (v.length() - 1.0).abs() < 1e-12);
        assert!(u.dot(v).abs() < 1e-12);
    }
}
