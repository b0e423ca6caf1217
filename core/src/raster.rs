//! A tiled, watertight depth rasterizer for shadow maps and camera depth.
//!
//! Triangles are clipped in homogeneous space (near plane and a guard band), snapped to a
//! fixed-point grid and filled with integer edge functions and a top-left rule, so that
//! every sample on a shared edge belongs to exactly one of the two triangles. Tiles are
//! filled in parallel, each in triangle order with a strict depth test, which makes the
//! output independent of the thread count.

use std::cmp::Ordering;

use glam::{DMat4, DVec4};
use rayon::prelude::*;

use crate::cutout::{AlphaMask, TexturedTriangle, OPAQUE};
use crate::error::{Result, Sizing};
use crate::render::Geometry;
use crate::spare::Spare;
use crate::total_order::total_order_bits_f32;

mod runs;

use runs::{DepthTest, Run, RunDepth, RunKernels};

// Camera depth targets kept from one frame for the next (see `crate::spare`); their
// holders hand them back with `keep_camera_depth`. Faulting in a fresh 8 MB target each
// 1080p frame took about 0.5 ms of plane's 9.5 ms camera depth.
static SPARE_CAMERA_DEPTH: Spare<f32> = Spare::new(Sizing::Image);
// The same for shadow maps' depth and id targets (`keep_map_targets`): fresh pages for
// a 1024² map's two 4 MB targets took about 1 ms of plane's 3.5–4 ms shadow-map stage.
static SPARE_MAP_DEPTH: Spare<f32> = Spare::new(Sizing::Rectified);
static SPARE_MAP_IDS: Spare<u32> = Spare::new(Sizing::Rectified);

/// Keeps a buffer that [`rasterize_depth`] returned, for a later frame's.
pub(crate) fn keep_camera_depth(buffer: Vec<f32>) {
    SPARE_CAMERA_DEPTH.keep(buffer);
}

/// Keeps the depth and id targets of a map that [`rasterize`] drew, for a later frame's.
pub(crate) fn keep_map_targets(depth: Vec<f32>, ids: Vec<u32>) {
    SPARE_MAP_DEPTH.keep(depth);
    SPARE_MAP_IDS.keep(ids);
}

/// Lets go of the kept targets ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_CAMERA_DEPTH.clear();
    SPARE_MAP_DEPTH.clear();
    SPARE_MAP_IDS.clear();
}

/// Id written where no triangle covers a sample.
pub const NO_OBJECT: u32 = u32::MAX;

const SUBPIXEL_BITS: u32 = 8;
const SUBPIXEL: f64 = (1u32 << SUBPIXEL_BITS) as f64;
const TILE: u32 = 64;
/// Rows of the bands that rasterizers fill in parallel: half a tile.
const BAND: u32 = TILE / 2;

/// What to rasterize into.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterDesc {
    pub width: u32,
    pub height: u32,
    /// True when the projection divides by w (a pinhole camera); depth is then w itself.
    pub perspective: bool,
    /// With `perspective`, store z/w instead of w: affine in the image, so interpolated
    /// linearly (a projective shadow map's depth).
    pub projected_depth: bool,
    /// Smallest w kept by the near-plane clip (perspective only).
    pub near_w: f64,
    /// Samples whose depth falls outside this range are left empty (clip planes).
    pub depth_range: (f64, f64),
}

impl RasterDesc {
    pub fn orthographic(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            perspective: false,
            projected_depth: false,
            near_w: 0.0,
            depth_range: (f64::NEG_INFINITY, f64::INFINITY),
        }
    }

    pub fn perspective(width: u32, height: u32, near: f64, far: f64) -> Self {
        Self {
            width,
            height,
            perspective: true,
            projected_depth: false,
            near_w: near,
            depth_range: (near, far),
        }
    }

    /// Divides by w, clips at `near_w`, and stores z/w with no depth clipping: geometry
    /// at any depth is kept (the rasterizer's equivalent of depth clamping).
    pub fn projective(width: u32, height: u32, near_w: f64) -> Self {
        Self {
            width,
            height,
            perspective: true,
            projected_depth: true,
            near_w,
            depth_range: (f64::NEG_INFINITY, f64::INFINITY),
        }
    }

    /// Whether depth is recovered as the reciprocal of an interpolated 1/w.
    fn interpolates_reciprocal(&self) -> bool {
        self.perspective && !self.projected_depth
    }
}

/// Nearest depth and its object id per sample, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthTarget {
    pub width: u32,
    pub height: u32,
    /// +∞ where nothing was drawn.
    pub depth: Vec<f32>,
    /// [`NO_OBJECT`] where nothing was drawn; empty from a rasterizer asked for depth
    /// alone (the GPU's camera-depth pass).
    pub ids: Vec<u32>,
}

/// Fills depth targets on a GPU's graphics pipeline, to [`rasterize`]'s contract (the CPU
/// paths call [`rasterize`] itself).
pub trait Rasterizer {
    /// [`rasterize`]'s contract: world triangles through `pixel_from_world` into `desc`.
    fn rasterize(
        &self,
        geometry: &Geometry,
        pixel_from_world: &DMat4,
        desc: &RasterDesc,
    ) -> Result<DepthTarget>;
}

/// A triangle after clipping and snapping, ready for edge-function traversal.
#[derive(Clone, Copy, Debug)]
struct ScreenTriangle {
    /// Fixed-point vertex positions, counter-clockwise in the sense of positive area.
    vertices: [[i64; 2]; 3],
    /// Per-vertex depth: z, 1/w for perspective projections, or z/w for projected depth.
    attributes: [f64; 3],
    object_id: u32,
    /// Inclusive pixel bounds, already clamped to the target.
    bounds: [u32; 4],
    /// [`nearest_depth`] of its attributes, for depth-only rasters: found once here rather
    /// than in each band-tile that draws it.
    nearest: f32,
}

/// The alpha-cut triangles of a raster ([`crate::cutout`]): per screen triangle, its
/// [`TexturedTriangle`]'s index or [`OPAQUE`] (empty where nothing is cut: a field of
/// [`ScreenTriangle`] made it 104 bytes rather than 96, and colonnade's shadow map 15%
/// slower), those set-ups, and the masks.
struct CutTriangles<'a> {
    of_screen: Vec<u32>,
    triangles: Vec<TexturedTriangle>,
    masks: &'a [AlphaMask<'a>],
}

impl CutTriangles<'_> {
    #[inline(always)]
    fn of(&self, screen_index: u32) -> u32 {
        self.of_screen
            .get(screen_index as usize)
            .copied()
            .unwrap_or(OPAQUE)
    }
}

/// Rasterizes world-space triangles through `pixel_from_world`, which maps a point to
/// (pixel x · w, pixel y · w, depth, w).
pub fn rasterize(
    geometry: &Geometry,
    pixel_from_world: &DMat4,
    desc: &RasterDesc,
) -> Result<DepthTarget> {
    rasterize_targets(geometry, pixel_from_world, desc, true)
}

/// [`rasterize`] without object ids (`ids` left empty), as the GPU's camera-depth pass: a
/// camera's depth needs none, and filling them took a second full-size target each frame.
pub fn rasterize_depth(
    geometry: &Geometry,
    pixel_from_world: &DMat4,
    desc: &RasterDesc,
) -> Result<DepthTarget> {
    rasterize_targets(geometry, pixel_from_world, desc, false)
}

/// [`rasterize`], with object ids or without.
fn rasterize_targets(
    geometry: &Geometry,
    pixel_from_world: &DMat4,
    desc: &RasterDesc,
    with_ids: bool,
) -> Result<DepthTarget> {
    let (triangles, cut) = setup_triangles(geometry, pixel_from_world, desc);
    let tiles_x = desc.width.div_ceil(TILE);
    let tiles_y = desc.height.div_ceil(TILE);
    let mut bins = bin_triangles(&triangles, tiles_x, tiles_y);
    if !with_ids {
        front_to_back(&triangles, &mut bins);
    }

    let width = desc.width as usize;
    let samples = width * desc.height as usize;
    // Both filled band by band below, in parallel.
    let what = |target: &'static str| {
        let (width, height) = (desc.width, desc.height);
        move || format!("the {target} ({width}×{height})")
    };
    let (mut depth, mut ids) = if with_ids {
        (
            SPARE_MAP_DEPTH.try_take(samples, what("light's depth map"))?,
            SPARE_MAP_IDS.try_take(samples, what("light's object-id map"))?,
        )
    } else {
        (
            SPARE_CAMERA_DEPTH.try_take(samples, what("camera depth"))?,
            Vec::new(),
        )
    };
    // Each band of half a tile's rows filled in place, its tiles in turn: tiles of their
    // own took fresh memory each frame and were then copied (page faults, zeroing and the
    // copy were a tenth of a camera raster), and bands a whole tile high left a core idle
    // behind the densest band.
    let rows = BAND as usize * width.max(1);
    let id_bands: Vec<Option<&mut [u32]>> = if with_ids {
        ids.chunks_mut(rows).map(Some).collect()
    } else {
        depth.chunks(rows).map(|_| None).collect()
    };
    depth
        .par_chunks_mut(rows)
        .zip(id_bands)
        .enumerate()
        .for_each(|(band, (depth_band, mut id_band))| {
            depth_band.fill(f32::INFINITY);
            if let Some(ids) = id_band.as_deref_mut() {
                ids.fill(NO_OBJECT);
            }
            let y0 = band as u32 * BAND;
            let tile_y = y0 / TILE;
            for tile_x in 0..tiles_x {
                let index = tile_y * tiles_x + tile_x;
                let [x0, _, x1, _] = tile_rect(index, tiles_x, desc);
                let rect = [x0, y0, x1, (y0 + BAND).min(desc.height)];
                let bin = &bins[index as usize];
                let ids = id_band.as_deref_mut();
                fill_tile(&triangles, &cut, bin, rect, desc, width, depth_band, ids);
            }
        });
    Ok(DepthTarget {
        width: desc.width,
        height: desc.height,
        depth,
        ids,
    })
}

/// [x0, y0, x1, y1) of a tile, clamped to the target.
fn tile_rect(index: u32, tiles_x: u32, desc: &RasterDesc) -> [u32; 4] {
    let x0 = (index % tiles_x) * TILE;
    let y0 = (index / tiles_x) * TILE;
    [
        x0,
        y0,
        (x0 + TILE).min(desc.width),
        (y0 + TILE).min(desc.height),
    ]
}

fn bin_triangles(triangles: &[ScreenTriangle], tiles_x: u32, tiles_y: u32) -> Vec<Vec<u32>> {
    let mut bins = vec![Vec::new(); (tiles_x * tiles_y) as usize];
    for (index, triangle) in triangles.iter().enumerate() {
        let [x0, y0, x1, y1] = triangle.bounds;
        for ty in y0 / TILE..=y1 / TILE {
            for tx in x0 / TILE..=x1 / TILE {
                bins[(ty * tiles_x + tx) as usize].push(index as u32);
            }
        }
    }
    bins
}

/// Orders each bin by its triangles' [`nearest_depth`], for depth alone, which is the
/// nearest over all of them whatever their order: front to back, a tile's farthest depth
/// falls early, and the first triangle wholly behind it ends the tile ([`fill_tile`]).
/// A NaN bound sorts first, so that it is drawn.
fn front_to_back(triangles: &[ScreenTriangle], bins: &mut [Vec<u32>]) {
    // Each bound as its bits in total order, so that a bin sorts integers, each entry its
    // triangle's key above its index: ties by index, and each key looked up once per entry
    // rather than at every comparison.
    let keys: Vec<u32> = triangles
        .par_iter()
        .map(|triangle| {
            let nearest = triangle.nearest;
            total_order_bits_f32(if nearest.is_nan() {
                f32::NEG_INFINITY
            } else {
                nearest
            })
        })
        .collect();
    bins.par_iter_mut()
        .for_each_init(Vec::new, |keyed: &mut Vec<u64>, bin| {
            keyed.clear();
            keyed.extend(
                bin.iter()
                    .map(|&index| (keys[index as usize] as u64) << 32 | index as u64),
            );
            keyed.sort_unstable();
            for (index, entry) in bin.iter_mut().zip(keyed.iter()) {
                *index = *entry as u32;
            }
        });
}

/// Fills `rect` of `depth` and `ids` (if any), the rows from its first on, `width` wide.
/// Without ids, `bin` must be in [`front_to_back`] order.
#[allow(clippy::too_many_arguments)]
fn fill_tile(
    triangles: &[ScreenTriangle],
    cut: &CutTriangles,
    bin: &[u32],
    rect: [u32; 4],
    desc: &RasterDesc,
    width: usize,
    depth: &mut [f32],
    mut ids: Option<&mut [u32]>,
) {
    let (near, far) = desc.depth_range;
    let perspective = desc.interpolates_reciprocal();
    let kernels = RunKernels::for_target(desc.width, desc.height);
    // Without ids, a triangle wholly behind the farthest depth in the rect changes nothing,
    // and neither do those after it, front to back; one behind some of the rect's blocks
    // is drawn over the others alone. The farthest depths are refreshed every few
    // triangles; depths only fall, so stale ones are safe. Skipping would be exact with
    // ids too (the depth test is strict), but shadow maps, in the meshes' order, skip too
    // little to pay for the blocks' upkeep: tree's 1024² map took 12.8–14.2 ms with it,
    // 11.2–11.4 without.
    let mut farthest = FarthestBlocks::UNKNOWN;
    for (n, &index) in bin.iter().enumerate() {
        // A bin's triangles lie anywhere in the mesh's order (and in depth order for depth
        // alone), and a 96-byte triangle spans two or three cache lines: the first thing
        // read of each, its bound, waited on memory (14% of tree's camera raster).
        #[cfg(target_arch = "x86_64")]
        if let Some(&ahead) = bin.get(n + PREFETCH_AHEAD) {
            let start = (&triangles[ahead as usize] as *const ScreenTriangle).cast::<i8>();
            let size = std::mem::size_of::<ScreenTriangle>();
            for line in [
                start,
                start.wrapping_add(size / 2),
                start.wrapping_add(size - 1),
            ] {
                // SAFETY: SSE is part of x86-64; a prefetch reads nothing.
                unsafe {
                    std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(line)
                };
            }
        }
        let triangle = &triangles[index as usize];
        let mut drawn = rect;
        if ids.is_none() {
            if n % FARTHEST_REFRESH == FARTHEST_REFRESH - 1 {
                farthest = FarthestBlocks::of(depth, rect, width);
            }
            if triangle.nearest >= farthest.overall {
                break;
            }
            let Some(part) = farthest.changeable(rect, triangle.bounds, triangle.nearest) else {
                continue;
            };
            drawn = part;
        }
        let run_depth = RunDepth::of(triangle, perspective);
        let test = DepthTest {
            depth: &run_depth,
            range: (near, far),
            object_id: triangle.object_id,
        };
        let mut test_run = |run: &Run| {
            let start = (run.y - rect[1]) as usize * width + run.x as usize;
            let samples = start..start + run.len;
            let ids = ids.as_deref_mut().map(|ids| &mut ids[samples.clone()]);
            kernels.test(&test, run, &mut depth[samples], ids);
        };
        let cutout = cut.of(index);
        if cutout == OPAQUE {
            for_each_covered_run(triangle, drawn, |run| test_run(&run));
            continue;
        }
        // Cut by a mask: each run's samples the mask covers, as runs of their own.
        let textured = &cut.triangles[cutout as usize];
        let mask = &cut.masks[textured.mask as usize];
        for_each_covered_run(triangle, drawn, |run| {
            let covers = |k: usize| {
                let (x, y) = ((run.x as usize + k) as f64 + 0.5, run.y as f64 + 0.5);
                mask.covers(textured.uv_at(x, y))
            };
            // Each sample's mask is read once; a covered stretch is tested when it ends.
            let mut first = None;
            for k in 0..=run.len {
                match (first, k < run.len && covers(k)) {
                    (None, true) => first = Some(k),
                    (Some(start), false) => {
                        test_run(&Run {
                            x: run.x + start as u32,
                            y: run.y,
                            len: k - start,
                            values: run.values_at(start),
                            step: run.step,
                        });
                        first = None;
                    }
                    _ => {}
                }
            }
        });
    }
}

/// How many triangles ahead in a bin [`fill_tile`] asks for a triangle's set-up (8 did
/// no better).
const PREFETCH_AHEAD: usize = 4;

/// How many triangles a depth-only tile draws between refreshes of its farthest depths
/// ([`FarthestBlocks`]): every 8 cost more than the skipping saved on tree; every 16 took
/// colonnade's 1080p camera raster from about 9.5 ms to 8 but tree's from 14.4 to 15.8.
const FARTHEST_REFRESH: usize = 32;

/// Width and height of the blocks of a band-tile whose farthest depths [`fill_tile`]
/// keeps apart: against the rect's farthest depth alone, 16 by 4 took tree's 1080p camera
/// raster from about 18 ms to 14.5 (strips of 8, 4 or 2 whole rows: 16, 15.5, 16.5).
const BLOCK: [u32; 2] = [16, 4];
const BLOCKS_ACROSS: usize = (TILE / BLOCK[0]) as usize;
const BLOCKS_DOWN: usize = (BAND / BLOCK[1]) as usize;

/// The farthest depth of each block of a band-tile's rect, and of the whole rect.
struct FarthestBlocks {
    blocks: [[f32; BLOCKS_ACROSS]; BLOCKS_DOWN],
    overall: f32,
}

impl FarthestBlocks {
    /// Before any depth is known.
    const UNKNOWN: Self = Self {
        blocks: [[f32::INFINITY; BLOCKS_ACROSS]; BLOCKS_DOWN],
        overall: f32::INFINITY,
    };

    /// Of `rect` of `depth` (rows from the rect's first, `width` wide); blocks past the
    /// rect hold −∞.
    fn of(depth: &[f32], rect: [u32; 4], width: usize) -> Self {
        let mut blocks = [[f32::NEG_INFINITY; BLOCKS_ACROSS]; BLOCKS_DOWN];
        for row in 0..(rect[3] - rect[1]) as usize {
            let line = &depth[row * width + rect[0] as usize..row * width + rect[2] as usize];
            let across = &mut blocks[row / BLOCK[1] as usize];
            for (block, values) in across.iter_mut().zip(line.chunks(BLOCK[0] as usize)) {
                *block = values.iter().copied().fold(*block, f32::max);
            }
        }
        let overall = blocks
            .iter()
            .flatten()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        Self { blocks, overall }
    }

    /// The smallest rectangle of `rect`'s blocks that holds every block under `bounds`
    /// (inclusive) whose farthest depth lies beyond `nearest` (every one where `nearest`
    /// is NaN); `None` if there is none.
    fn changeable(&self, rect: [u32; 4], bounds: [u32; 4], nearest: f32) -> Option<[u32; 4]> {
        let [left, top, right, bottom] = bounds;
        if right < rect[0] || bottom < rect[1] || left >= rect[2] || top >= rect[3] {
            return None;
        }
        let block_of = |at: u32, axis: usize| ((at - rect[axis]) / BLOCK[axis]) as usize;
        let (first_column, last_column) = (
            block_of(left.max(rect[0]), 0),
            block_of(right.min(rect[2] - 1), 0),
        );
        let (first_row, last_row) = (
            block_of(top.max(rect[1]), 1),
            block_of(bottom.min(rect[3] - 1), 1),
        );
        // [first column, first row, last column, last row] of the blocks found.
        let mut found: Option<[usize; 4]> = None;
        for row in first_row..=last_row {
            for column in first_column..=last_column {
                if nearest < self.blocks[row][column] || nearest.is_nan() {
                    let [c0, r0, c1, r1] = found.unwrap_or([column, row, column, row]);
                    found = Some([c0.min(column), r0.min(row), c1.max(column), r1.max(row)]);
                }
            }
        }
        let [c0, r0, c1, r1] = found?;
        Some([
            rect[0] + c0 as u32 * BLOCK[0],
            rect[1] + r0 as u32 * BLOCK[1],
            (rect[0] + (c1 as u32 + 1) * BLOCK[0]).min(rect[2]),
            (rect[1] + (r1 as u32 + 1) * BLOCK[1]).min(rect[3]),
        ])
    }
}

/// A lower bound on the stored depth of any sample of a triangle with vertex `attributes`:
/// its samples interpolate them with weights that are at least 0 and sum to 1, so their
/// depths lie within the vertices' (within a few roundings, which the margin covers).
fn nearest_depth([a, b, c]: [f64; 3], perspective: bool) -> f32 {
    const MARGIN: f64 = 1e-9;
    let nearest = if perspective {
        // Attributes are 1/w, all positive past the near plane.
        1.0 / a.max(b).max(c)
    } else {
        a.min(b).min(c)
    };
    (nearest - nearest.abs() * MARGIN) as f32
}

/// Calls `visit(x, y, depth)` for every pixel centre of `rect` the triangle covers.
#[cfg(test)]
fn for_each_covered_sample(
    triangle: &ScreenTriangle,
    rect: [u32; 4],
    perspective: bool,
    mut visit: impl FnMut(u32, u32, f64),
) {
    let depth = RunDepth::of(triangle, perspective);
    for_each_covered_run(triangle, rect, |run| {
        for k in 0..run.len {
            visit(run.x + k as u32, run.y, depth.at(run.values_at(k)));
        }
    });
}

/// Calls `visit(run)` for every row's run of pixel centres of `rect` the triangle covers.
fn for_each_covered_run(triangle: &ScreenTriangle, rect: [u32; 4], mut visit: impl FnMut(Run)) {
    let [bx0, by0, bx1, by1] = triangle.bounds;
    let (x0, y0) = (bx0.max(rect[0]), by0.max(rect[1]));
    let (x1, y1) = ((bx1 + 1).min(rect[2]), (by1 + 1).min(rect[3]));
    if x0 >= x1 || y0 >= y1 {
        return;
    }
    let v = triangle.vertices;
    // Edge i runs opposite vertex i, so its function is that vertex's barycentric weight.
    let edges = [(v[1], v[2]), (v[2], v[0]), (v[0], v[1])];
    let half = (SUBPIXEL as i64) / 2;
    let px0 = x0 as i64 * SUBPIXEL as i64 + half;
    let py0 = y0 as i64 * SUBPIXEL as i64 + half;
    let mut row_values = [0i64; 3];
    let mut step_x = [0i64; 3];
    let mut step_y = [0i64; 3];
    let mut bias = [0i64; 3];
    for (i, &(a, b)) in edges.iter().enumerate() {
        let ea = -(b[1] - a[1]);
        let eb = b[0] - a[0];
        row_values[i] = ea * (px0 - a[0]) + eb * (py0 - a[1]);
        step_x[i] = ea * SUBPIXEL as i64;
        step_y[i] = eb * SUBPIXEL as i64;
        // Top-left rule: of the two triangles sharing an edge, exactly one owns samples
        // lying on it, because reversing the edge negates both coefficients.
        let owned = ea > 0 || (ea == 0 && eb < 0);
        bias[i] = if owned { 0 } else { -1 };
    }
    let count = (x1 - x0) as i64;
    for y in y0..y1 {
        // Only the run of the row inside all three edges is visited: a thin or sloping
        // triangle's box is mostly outside it (a 1080p camera tested 3–15 box samples per
        // covered one), and testing each sample mispredicted at every run's ends.
        let (mut first, mut end) = (0, count);
        for i in 0..3 {
            let (edge_first, edge_end) = inside_run(row_values[i] + bias[i], step_x[i], count);
            first = first.max(edge_first);
            end = end.min(edge_end);
        }
        if first < end {
            visit(Run {
                x: x0 + first as u32,
                y,
                len: (end - first) as usize,
                values: std::array::from_fn(|i| row_values[i] + first * step_x[i]),
                step: step_x,
            });
        }
        for i in 0..3 {
            row_values[i] += step_y[i];
        }
    }
}

/// The samples k of `0..count` where an edge function, `value` at the first and changing
/// by `step` per sample, is at least 0: one run, `first..end` (empty where `first >= end`).
fn inside_run(value: i64, step: i64, count: i64) -> (i64, i64) {
    match step.cmp(&0) {
        Ordering::Equal | Ordering::Greater if value >= 0 => (0, count),
        Ordering::Equal => (0, 0),
        // The first k with value + k·step ≥ 0.
        Ordering::Greater => ((-value + step - 1) / step, count),
        Ordering::Less if value < 0 => (0, 0),
        // Past the last k with value + k·step ≥ 0.
        Ordering::Less => (0, value / -step + 1),
    }
}

/// Transforms, clips and snaps all triangles, in input order, and sets up the texture
/// coordinates of those cut by masks.
fn setup_triangles<'g>(
    geometry: &Geometry<'g>,
    pixel_from_world: &DMat4,
    desc: &RasterDesc,
) -> (Vec<ScreenTriangle>, CutTriangles<'g>) {
    let pixel_from_local = geometry.pixel_from_local(pixel_from_world);
    let clip_positions: Vec<DVec4> = geometry
        .positions
        .par_iter()
        .map(|p| pixel_from_local * DVec4::new(p[0] as f64, p[1] as f64, p[2] as f64, 1.0))
        .collect();
    let planes = clip_planes(desc);
    let corners_of = |triangle: &[u32; 3]| triangle.map(|v| clip_positions[v as usize]);
    // Per triangle, its index among the cut ones (OPAQUE where it is not cut), and theirs
    // set up in that order; `None` for one seen edge on, which covers nothing.
    let (cut_index, textured): (Vec<u32>, Vec<Option<TexturedTriangle>>) = match geometry
        .cutouts
        .as_ref()
        .filter(|cutouts| cutouts.cuts_any())
    {
        None => (Vec::new(), Vec::new()),
        Some(cutouts) => {
            let mut count = 0u32;
            let index = cutouts
                .triangle_masks
                .iter()
                .map(|&mask| match mask {
                    OPAQUE => OPAQUE,
                    _ => {
                        count += 1;
                        count - 1
                    }
                })
                .collect();
            let cut: Vec<usize> = (0..geometry.triangles.len())
                .filter(|&t| cutouts.triangle_masks[t] != OPAQUE)
                .collect();
            let textured = cut
                .par_iter()
                .map(|&t| {
                    let triangle = &geometry.triangles[t];
                    let uvs = triangle.map(|v| cutouts.uvs[v as usize]);
                    TexturedTriangle::new(corners_of(triangle), uvs, cutouts.triangle_masks[t])
                })
                .collect();
            (index, textured)
        }
    };
    let clip_and_snap = |triangle: &[u32; 3], object_id: u32| {
        let polygon = clip_polygon(&corners_of(triangle), &planes);
        (1..polygon.len().saturating_sub(1)).filter_map(move |i| {
            snap_triangle([polygon[0], polygon[i], polygon[i + 1]], object_id, desc)
        })
    };
    let masks = geometry.cutouts.as_ref().map_or(&[][..], |c| c.masks);
    let triangles_and_ids = geometry
        .triangles
        .par_iter()
        .zip(geometry.object_ids.par_iter());
    if cut_index.is_empty() {
        let screen = triangles_and_ids
            .flat_map_iter(|(triangle, &object_id)| clip_and_snap(triangle, object_id))
            .collect();
        let none = CutTriangles {
            of_screen: Vec::new(),
            triangles: Vec::new(),
            masks,
        };
        return (screen, none);
    }
    let (screen, of_screen): (Vec<ScreenTriangle>, Vec<u32>) = triangles_and_ids
        .enumerate()
        .flat_map_iter(|(t, (triangle, &object_id))| {
            let cutout = cut_index[t];
            // A cut triangle seen edge on covers nothing.
            let edge_on = cutout != OPAQUE && textured[cutout as usize].is_none();
            let pieces: Vec<ScreenTriangle> = match edge_on {
                true => Vec::new(),
                false => clip_and_snap(triangle, object_id).collect(),
            };
            pieces.into_iter().map(move |piece| (piece, cutout))
        })
        .unzip();
    // Edge-on entries are never indexed; a placeholder keeps the others' indices.
    let triangles = textured
        .into_iter()
        .map(|t| t.unwrap_or(TexturedTriangle::EDGE_ON))
        .collect();
    let cut = CutTriangles {
        of_screen,
        triangles,
        masks,
    };
    (screen, cut)
}

/// An affine half-space n·v + c ≥ 0 in clip coordinates. The constant term works because
/// every clipped vertex is an affine combination of world points of weight one.
#[derive(Clone, Copy, Debug)]
struct Plane {
    normal: DVec4,
    offset: f64,
}

impl Plane {
    fn distance(&self, v: DVec4) -> f64 {
        self.normal.dot(v) + self.offset
    }
}

/// Keeps w positive (perspective) and the snapped coordinates within the fixed-point range.
fn clip_planes(desc: &RasterDesc) -> Vec<Plane> {
    let guard = 2.0 * desc.width.max(desc.height) as f64 + 64.0;
    let (w, h) = (desc.width as f64, desc.height as f64);
    let homogeneous = |x, y, w| Plane {
        normal: DVec4::new(x, y, 0.0, w),
        offset: 0.0,
    };
    let mut planes = vec![
        homogeneous(1.0, 0.0, guard),
        homogeneous(-1.0, 0.0, w + guard),
        homogeneous(0.0, 1.0, guard),
        homogeneous(0.0, -1.0, h + guard),
    ];
    if desc.perspective {
        planes.push(Plane {
            normal: DVec4::W,
            offset: -desc.near_w,
        });
    }
    planes
}

/// Sutherland–Hodgman clipping. Edge intersections are computed from the endpoints in
/// a canonical order, so an edge shared by two triangles is cut at the identical point.
fn clip_polygon(corners: &[DVec4; 3], planes: &[Plane]) -> Vec<DVec4> {
    let inside_all = |v: &DVec4| planes.iter().all(|p| p.distance(*v) >= 0.0);
    if corners.iter().all(inside_all) {
        return corners.to_vec();
    }
    let mut polygon: Vec<DVec4> = corners.to_vec();
    for plane in planes {
        if polygon.is_empty() {
            break;
        }
        let mut clipped = Vec::with_capacity(polygon.len() + 1);
        for i in 0..polygon.len() {
            let a = polygon[i];
            let b = polygon[(i + 1) % polygon.len()];
            let (da, db) = (plane.distance(a), plane.distance(b));
            if da >= 0.0 {
                clipped.push(a);
            }
            if (da >= 0.0) != (db >= 0.0) {
                clipped.push(intersect(a, b, plane));
            }
        }
        polygon = clipped;
    }
    polygon
}

fn intersect(a: DVec4, b: DVec4, plane: &Plane) -> DVec4 {
    let (first, second) = if a.to_array() <= b.to_array() {
        (a, b)
    } else {
        (b, a)
    };
    let (d0, d1) = (plane.distance(first), plane.distance(second));
    first + (second - first) * (d0 / (d0 - d1))
}

/// Twice the signed area of the triangle `vertices` (positive counter-clockwise in the
/// sense [`ScreenTriangle`] keeps): the constant sum of its three edge functions.
fn twice_area(vertices: &[[i64; 2]; 3]) -> i64 {
    (vertices[1][0] - vertices[0][0]) * (vertices[2][1] - vertices[0][1])
        - (vertices[1][1] - vertices[0][1]) * (vertices[2][0] - vertices[0][0])
}

/// `x.round() as i64` (halves away from zero, NaN to 0, saturating), inline: on baseline
/// x86-64 `f64::round` is a call into libm, which took 2% of a 1080p raster of `tree`.
#[inline]
fn round_to_i64(x: f64) -> i64 {
    // From 2^52 on every f64 is a whole number.
    const WHOLE_FROM: f64 = (1u64 << 52) as f64;
    if x.abs() < WHOLE_FROM {
        let whole = x as i64;
        // Exact: a float's fraction is itself a float.
        let fraction = x - whole as f64;
        whole + i64::from(fraction >= 0.5) - i64::from(fraction <= -0.5)
    } else {
        x as i64
    }
}

fn snap_triangle(corners: [DVec4; 3], object_id: u32, desc: &RasterDesc) -> Option<ScreenTriangle> {
    let mut vertices = [[0i64; 2]; 3];
    let mut attributes = [0f64; 3];
    for (i, c) in corners.iter().enumerate() {
        let (x, y) = (c.x / c.w, c.y / c.w);
        vertices[i] = [round_to_i64(x * SUBPIXEL), round_to_i64(y * SUBPIXEL)];
        attributes[i] = if desc.projected_depth {
            c.z / c.w
        } else if desc.perspective {
            1.0 / c.w
        } else {
            c.z
        };
    }
    let area = twice_area(&vertices);
    if area == 0 || !attributes.iter().all(|a| a.is_finite()) {
        return None;
    }
    if area < 0 {
        vertices.swap(1, 2);
        attributes.swap(1, 2);
    }
    // Pixel x is covered when its centre x + ½ lies inside; bound by the centres.
    let to_pixel = |v: i64, up: bool| -> i64 {
        let shifted = v - (SUBPIXEL as i64) / 2;
        if up {
            shifted.div_euclid(SUBPIXEL as i64) + 1
        } else {
            shifted.div_euclid(SUBPIXEL as i64)
        }
    };
    let min_x = vertices.iter().map(|v| v[0]).min()?;
    let max_x = vertices.iter().map(|v| v[0]).max()?;
    let min_y = vertices.iter().map(|v| v[1]).min()?;
    let max_y = vertices.iter().map(|v| v[1]).max()?;
    let x0 = to_pixel(min_x, false).max(0);
    let y0 = to_pixel(min_y, false).max(0);
    let x1 = to_pixel(max_x, true).min(desc.width as i64 - 1);
    let y1 = to_pixel(max_y, true).min(desc.height as i64 - 1);
    if x0 > x1 || y0 > y1 {
        return None;
    }
    Some(ScreenTriangle {
        vertices,
        attributes,
        object_id,
        bounds: [x0 as u32, y0 as u32, x1 as u32, y1 as u32],
        nearest: nearest_depth(attributes, desc.interpolates_reciprocal()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A tilted plane z = 0.25 x + 0.5 y + 3 over [x0, x1]², split into `n`² quads whose
    /// interior vertices are jittered (little enough that no triangle folds over), so that
    /// edges run at arbitrary angles.
    fn jittered_grid(n: usize, x0: f32, x1: f32, seed: u64) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let step = (x1 - x0) / n as f32;
        let mut positions = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let interior = i > 0 && i < n && j > 0 && j < n;
                let jitter = |rng: &mut rand_pcg::Pcg64| {
                    if interior {
                        rng.random_range(-0.15..0.15) * step
                    } else {
                        0.0
                    }
                };
                let x = x0 + i as f32 * step + jitter(&mut rng);
                let y = x0 + j as f32 * step + jitter(&mut rng);
                positions.push([x, y, 0.25 * x + 0.5 * y + 3.0]);
            }
        }
        let mut triangles = Vec::new();
        let index = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        for j in 0..n {
            for i in 0..n {
                let (a, b, c, d) = (
                    index(i, j),
                    index(i + 1, j),
                    index(i, j + 1),
                    index(i + 1, j + 1),
                );
                if (i + j) % 2 == 0 {
                    triangles.push([a, b, d]);
                    triangles.push([a, d, c]);
                } else {
                    triangles.push([a, b, c]);
                    triangles.push([b, d, c]);
                }
            }
        }
        (positions, triangles)
    }

    /// Pixels equal world x/y, depth = world z.
    fn identity_projection() -> DMat4 {
        DMat4::IDENTITY
    }

    #[test]
    fn rounding_to_integers_matches_f64_round() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            -2.5,
            0.49999999999999994,
            -0.49999999999999994,
            4503599627370495.5,
            -4503599627370495.5,
            4503599627370496.0,
            1e19,
            -1e19,
            f64::MAX,
            f64::MIN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for _ in 0..100_000 {
            let magnitude = 2f64.powi(rng.random_range(-4..66));
            let value = rng.random_range(-1.0..1.0) * magnitude;
            // Halves too, where a fraction of exactly one half must round away from zero.
            values.extend([value, (value * 2.0).round() * 0.5]);
        }
        for value in values {
            assert_eq!(round_to_i64(value), value.round() as i64, "{value:e}");
        }
    }

    #[test]
    fn inside_runs_are_the_samples_an_edge_function_keeps() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        for _ in 0..20_000 {
            let count = rng.random_range(0..70);
            let step = if rng.random_bool(0.1) {
                0
            } else {
                rng.random_range(-300..=300)
            };
            let value = rng.random_range(-20_000..=20_000);
            let kept: Vec<i64> = (0..count).filter(|k| value + k * step >= 0).collect();
            let (first, end) = inside_run(value, step, count);
            let run: Vec<i64> = (first.max(0)..end.min(count)).collect();
            assert_eq!(run, kept, "value {value}, step {step}, count {count}");
            assert!(first < end || kept.is_empty());
        }
    }

    #[test]
    fn shared_edges_cover_each_sample_exactly_once() {
        let (positions, triangles) = jittered_grid(40, 0.0, 200.0, 7);
        let ids = vec![5; triangles.len()];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let desc = RasterDesc::orthographic(256, 256);
        let (screen, _) = setup_triangles(&geometry, &identity_projection(), &desc);
        let mut counts = vec![0u32; 256 * 256];
        for triangle in &screen {
            for_each_covered_sample(triangle, [0, 0, 256, 256], false, |x, y, _| {
                counts[(y * 256 + x) as usize] += 1;
            });
        }
        for y in 0..256u32 {
            for x in 0..256u32 {
                let expected = u32::from(x < 200 && y < 200);
                assert_eq!(counts[(y * 256 + x) as usize], expected, "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn depth_matches_the_analytic_plane() {
        let (positions, triangles) = jittered_grid(33, 0.0, 120.0, 11);
        let ids = vec![9; triangles.len()];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let target = rasterize(
            &geometry,
            &identity_projection(),
            &RasterDesc::orthographic(128, 100),
        )
        .unwrap();
        for y in 0..100 {
            for x in 0..128 {
                let i = y * 128 + x;
                let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
                if x < 120 {
                    let expected = 0.25 * cx + 0.5 * cy + 3.0;
                    // Vertices snap by up to 1/512 pixel; the plane's slope is 0.75 per pixel.
                    let error = (target.depth[i] as f64 - expected).abs();
                    assert!(error < 0.75 / 256.0, "({x}, {y}) off by {error}");
                    assert_eq!(target.ids[i], 9);
                } else {
                    assert_eq!(target.depth[i], f32::INFINITY);
                    assert_eq!(target.ids[i], NO_OBJECT);
                }
            }
        }
    }

    /// The full targets and the depth alone of the triangles, orthographically onto a
    /// target larger than a tile either way, so that bands and tiles split it.
    fn full_and_depth_alone(
        positions: &[[f32; 3]],
        triangles: &[[u32; 3]],
        ids: &[u32],
    ) -> (DepthTarget, DepthTarget) {
        let geometry = Geometry {
            positions,
            triangles,
            object_ids: ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let desc = RasterDesc::orthographic(157, 101);
        (
            rasterize(&geometry, &identity_projection(), &desc).unwrap(),
            rasterize_depth(&geometry, &identity_projection(), &desc).unwrap(),
        )
    }

    #[test]
    fn depth_alone_is_the_depth_of_the_full_targets() {
        let (positions, triangles) = jittered_grid(33, 0.0, 150.0, 11);
        let ids: Vec<u32> = (0..triangles.len() as u32).map(|i| i % 5 + 1).collect();
        let (full, depth_alone) = full_and_depth_alone(&positions, &triangles, &ids);
        assert!(depth_alone.ids.is_empty());
        assert_eq!(full.ids.len(), full.depth.len());
        assert!(full.depth.iter().any(|d| d.is_finite()));
        assert_eq!(depth_alone.depth, full.depth);
    }

    /// A plane drawn first, then layers behind it, crossing it and in front of it, then
    /// the last again, each of `n`² cells of two triangles, and each layer's id.
    fn layers_over_a_plane(n: usize) -> (Vec<[f32; 3]>, Vec<[u32; 3]>, Vec<u32>) {
        let mut positions = Vec::new();
        let mut triangles = Vec::new();
        let mut ids = Vec::new();
        for (id, (seed, depth_of)) in [
            (11, (|z| z) as fn(f32) -> f32),
            (12, |z| z + 40.0),
            (13, |z| 2.0 * z - 30.0),
            (14, |z| z - 1.0),
            (14, |z| z - 1.0),
        ]
        .into_iter()
        .enumerate()
        {
            let (layer, layer_triangles) = jittered_grid(n, 0.0, 150.0, seed);
            let first = positions.len() as u32;
            positions.extend(layer.iter().map(|&[x, y, z]| [x, y, depth_of(z)]));
            triangles.extend(layer_triangles.iter().map(|t| t.map(|v| v + first)));
            ids.extend(std::iter::repeat_n(id as u32 + 1, layer_triangles.len()));
        }
        (positions, triangles, ids)
    }

    #[test]
    fn depth_alone_skips_only_what_lies_behind() {
        // Many triangles per tile, so that tiles skip whole triangles behind their
        // farthest depths: the depth must be that of the full targets.
        let (positions, triangles, ids) = layers_over_a_plane(33);
        let (full, depth_alone) = full_and_depth_alone(&positions, &triangles, &ids);
        assert!(full.depth.iter().any(|d| d.is_finite()));
        assert_eq!(depth_alone.depth, full.depth);
    }

    #[test]
    fn full_targets_skip_only_what_changes_nothing() {
        // The full targets against each triangle rasterized alone (where nothing can be
        // skipped), composed in order with the same strict depth test: ties, such as the
        // last layer's with the one before, keep the first drawn triangle's id.
        let (positions, triangles, ids) = layers_over_a_plane(12);
        let desc = RasterDesc::orthographic(157, 101);
        let full = rasterize(
            &Geometry {
                positions: &positions,
                triangles: &triangles,
                object_ids: &ids,
                origin: glam::DVec3::ZERO,
                cutouts: None,
            },
            &identity_projection(),
            &desc,
        )
        .unwrap();
        let mut depth = vec![f32::INFINITY; full.depth.len()];
        let mut composed_ids = vec![NO_OBJECT; full.depth.len()];
        for (triangle, id) in triangles.iter().zip(&ids) {
            let alone = rasterize(
                &Geometry {
                    positions: &positions,
                    triangles: std::slice::from_ref(triangle),
                    object_ids: std::slice::from_ref(id),
                    origin: glam::DVec3::ZERO,
                    cutouts: None,
                },
                &identity_projection(),
                &desc,
            )
            .unwrap();
            for (i, &z) in alone.depth.iter().enumerate() {
                if z < depth[i] {
                    depth[i] = z;
                    composed_ids[i] = alone.ids[i];
                }
            }
        }
        assert!(composed_ids.contains(&3) && composed_ids.contains(&4));
        assert!(!composed_ids.contains(&5), "ties keep the first drawn id");
        assert_eq!(full.depth, depth);
        assert_eq!(full.ids, composed_ids);
    }

    #[test]
    fn triangles_are_drawn_over_the_blocks_they_may_change() {
        // A band-tile's rect at (64, 32), 64 wide and 20 high (its last band, cut short):
        // depth 5 everywhere but 9 in the block of columns 96..112, rows 36..40, and +∞
        // (not yet drawn) in the block of columns 64..80, rows 48..52.
        let (width, rect) = (200usize, [64u32, 32, 128, 52]);
        let mut depth = vec![5.0f32; 20 * width];
        for row in 0..20usize {
            for x in 64..128usize {
                let y = 32 + row;
                if (96..112).contains(&x) && (36..40).contains(&y) {
                    depth[row * width + x] = 9.0;
                }
                if (64..80).contains(&x) && (48..52).contains(&y) {
                    depth[row * width + x] = f32::INFINITY;
                }
            }
        }
        let farthest = FarthestBlocks::of(&depth, rect, width);
        assert_eq!(farthest.overall, f32::INFINITY);
        // Nearer than everything: the blocks under its bounds, whole.
        assert_eq!(
            farthest.changeable(rect, [70, 30, 100, 41], 1.0),
            Some([64, 32, 112, 44])
        );
        // Behind the depth-5 blocks: only the block at 9 under its bounds.
        assert_eq!(
            farthest.changeable(rect, [70, 30, 100, 41], 6.0),
            Some([96, 36, 112, 40])
        );
        // Behind every block it lies over, though not behind the rect's farthest.
        assert_eq!(farthest.changeable(rect, [70, 30, 90, 41], 6.0), None);
        // Two blocks apart: the rectangle holding both; the last row band cut at the rect.
        assert_eq!(
            farthest.changeable(rect, [0, 0, 300, 300], 9.5),
            Some([64, 48, 80, 52])
        );
        assert_eq!(
            farthest.changeable(rect, [0, 0, 300, 300], 6.0),
            Some([64, 36, 112, 52])
        );
        // No bound: every block under its bounds.
        assert_eq!(
            farthest.changeable(rect, [70, 30, 100, 41], f32::NAN),
            Some([64, 32, 112, 44])
        );
        // Outside the rect.
        assert_eq!(farthest.changeable(rect, [0, 0, 63, 300], 1.0), None);
        assert_eq!(farthest.changeable(rect, [64, 52, 300, 300], 1.0), None);
    }

    #[test]
    fn depth_alone_draws_each_tile_front_to_back() {
        // Three triangles over the first tile, at depths 5, 2 and 8 (the second tilted
        // from 2 to 9), and one over the second tile only.
        let positions = [
            [0.0, 0.0, 5.0],
            [60.0, 0.0, 5.0],
            [0.0, 60.0, 5.0],
            [0.0, 0.0, 2.0],
            [60.0, 0.0, 9.0],
            [0.0, 60.0, 9.0],
            [0.0, 0.0, 8.0],
            [60.0, 0.0, 8.0],
            [0.0, 60.0, 8.0],
            [70.0, 0.0, 1.0],
            [120.0, 0.0, 1.0],
            [70.0, 60.0, 1.0],
        ];
        let triangles = [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]];
        let ids = [1; 4];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let desc = RasterDesc::orthographic(128, 64);
        let (screen, _) = setup_triangles(&geometry, &identity_projection(), &desc);
        let mut bins = bin_triangles(&screen, 2, 1);
        front_to_back(&screen, &mut bins);
        assert_eq!(bins, [vec![1, 0, 2], vec![3]]);
    }

    #[test]
    fn nearer_triangle_wins_and_ties_keep_the_first() {
        let positions = [
            [0.0, 0.0, 5.0],
            [64.0, 0.0, 5.0],
            [0.0, 64.0, 5.0],
            [0.0, 0.0, 2.0],
            [64.0, 0.0, 2.0],
            [0.0, 64.0, 2.0],
        ];
        let triangles = [[0, 1, 2], [3, 4, 5], [0, 1, 2]];
        let ids = [1, 2, 3];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let target = rasterize(
            &geometry,
            &identity_projection(),
            &RasterDesc::orthographic(64, 64),
        )
        .unwrap();
        assert_eq!(target.ids[0], 2);
        assert_eq!(target.depth[0], 2.0);
    }

    /// A perspective projection looking down −Z with a 90° field of view on 64×64.
    fn looking_down_minus_z() -> DMat4 {
        DMat4::from_cols(
            DVec4::new(32.0, 0.0, 0.0, 0.0),
            DVec4::new(0.0, -32.0, 0.0, 0.0),
            DVec4::new(-32.0, -32.0, -1.0, -1.0),
            DVec4::ZERO,
        )
    }

    /// A floor at y = −1 running from behind that camera to far away, as two triangles.
    const FLOOR: [[f32; 3]; 4] = [
        [-50.0, -1.0, 10.0],
        [50.0, -1.0, 10.0],
        [50.0, -1.0, -500.0],
        [-50.0, -1.0, -500.0],
    ];
    const FLOOR_TRIANGLES: [[u32; 3]; 2] = [[0, 1, 2], [0, 2, 3]];

    #[test]
    fn triangles_crossing_the_near_plane_are_clipped() {
        let m = looking_down_minus_z();
        let (positions, triangles) = (FLOOR, FLOOR_TRIANGLES);
        let ids = [4, 4];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let target =
            rasterize(&geometry, &m, &RasterDesc::perspective(64, 64, 0.1, 1000.0)).unwrap();
        for y in 33..64 {
            for x in 0..64 {
                let i = y * 64 + x;
                // Planar depth of the floor seen at row centre y: 1 / tan = 32 / (y + ½ − 32).
                let offset = y as f64 + 0.5 - 32.0;
                let expected = 32.0 / offset;
                // Snapping vertices to 1/256 pixel moves the grazing floor's depth by up to
                // |∂depth/∂y| / 256.
                let tolerance = 1e-5 * expected + 2.0 * expected / offset / 256.0;
                if expected < 500.0 {
                    let got = target.depth[i] as f64;
                    assert!(
                        (got - expected).abs() < tolerance,
                        "({x}, {y}) {got} vs {expected}"
                    );
                }
            }
        }
        for i in 0..64 * 32 {
            assert_eq!(target.depth[i], f32::INFINITY);
        }
    }

    /// The perspective floor of the test above, checkered by a mask every 2 units: where
    /// the mask at a pixel's own point of the floor (found by casting its ray) is clearly
    /// solid, the floor is drawn; where clearly empty, nothing is. The two triangles are
    /// clipped at the near plane, which the coordinates' set-up must not notice.
    #[test]
    fn alpha_cut_triangles_draw_where_their_mask_is_solid() {
        use crate::cutout::{AlphaMask, Cutouts};
        let m = looking_down_minus_z();
        let (positions, triangles) = (FLOOR, FLOOR_TRIANGLES);
        let uvs = positions.map(|[x, _, z]| [x / 2.0, z / 2.0]);
        let ids = [4, 4];
        let checker: Vec<f32> = (0..16).map(|k| ((k % 4 + k / 4) % 2) as f32).collect();
        let masks = [AlphaMask::repeating(
            4,
            4,
            std::borrow::Cow::Borrowed(&checker),
            0.5,
        )];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: Some(Cutouts {
                uvs: &uvs,
                triangle_masks: &[0, 0],
                masks: &masks,
            }),
        };
        let target =
            rasterize(&geometry, &m, &RasterDesc::perspective(64, 64, 0.1, 1000.0)).unwrap();
        let (mut solid, mut empty) = (0, 0);
        for y in 33..64 {
            for x in 0..64 {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let z = -32.0 / (py - 32.0);
                if z < -500.0 {
                    continue;
                }
                let alpha = masks[0].alpha_at([(px - 32.0) / (py - 32.0) / 2.0, z / 2.0]);
                let drawn = target.depth[y * 64 + x].is_finite();
                if alpha > 0.55 {
                    assert!(drawn, "({x}, {y}) alpha {alpha}");
                    solid += 1;
                } else if alpha < 0.45 {
                    assert!(!drawn, "({x}, {y}) alpha {alpha}");
                    empty += 1;
                }
            }
        }
        assert!(solid > 300 && empty > 300, "{solid} solid, {empty} empty");
        // Without its mask the floor is drawn everywhere in view.
        let opaque = Geometry {
            cutouts: None,
            ..geometry
        };
        let whole = rasterize(&opaque, &m, &RasterDesc::perspective(64, 64, 0.1, 1000.0)).unwrap();
        let drawn = |t: &DepthTarget| t.depth.iter().filter(|d| d.is_finite()).count();
        assert!(drawn(&whole) > drawn(&target) + empty);
    }
}
