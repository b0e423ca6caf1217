//! Adaptive shading for the fast methods: shade a sparse grid of pixels, then only the
//! pixels between them whose shaded neighbours disagree or end on another surface; the
//! rest take their neighbours' mean. In-scattering varies smoothly across the image
//! except at depth edges and shadow boundaries, which is what the test looks for
//! (epipolar sampling refines at the same places: Engelhardt and Dachsbacher 2010, Chen
//! et al. 2011).
//!
//! Shadow boundaries run along the epipolar lines, the images of the planes through the
//! camera and the light: in such a plane, the free space a view ray crosses is lit or
//! shadowed in strips parallel to the light, and turning the ray within the plane moves
//! where it crosses each strip smoothly. So along an epipolar line the samples can lie
//! farther apart than across it. Every other pixel of every other row (the finer grid)
//! is found in two steps. In each square of the finer grid, the points on its lines
//! along a short lattice vector close to the square's epipolar lines are shaded every
//! few points (a lattice); each other point lies between two of those on its own line
//! and is interpolated from them where that line runs along the epipolar line through
//! it, closely enough to resolve shafts no worse than the finer grid would. The pixels
//! between the finer grid's are then interpolated from it in any direction.
//!
//! A feature narrower than two pixels across the epipolar lines that no shaded pixel
//! touches, such as a shaft one pixel wide, can be missed; a tolerance of 0 shades every
//! pixel.

use std::sync::atomic::{AtomicUsize, Ordering};

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::CameraModel;
use crate::control::RenderControl;
use crate::layers::{Layers, Pixel};
use crate::render::{layer_depth, Stopwatch, EDGE_DEPTH_SPREAD, SHADING_TILE as TILE};
use crate::spare::Spare;

/// The default tolerance: neighbours whose radiance spreads by at most 1% of its mean
/// (or, in regions darker than a quarter of the image's mean, of that quarter) are
/// interpolated. On the built-in scenes' default views at 1920×1080 this shades 8–20%
/// of the pixels (min-max 9–22%) and moves the layers from shading every pixel by at
/// most 0.029% of the mean radiance (prefiltering; 0.066% for min-max).
pub const DEFAULT_TOLERANCE: f32 = 0.01;

/// The share of the image's mean radiance (per channel) under which neighbours may
/// spread by the tolerance of that share rather than of their own blend: in regions that
/// dark, the fast methods' own error (prefiltering's ringing is about 1% of the unshadowed
/// light) is larger than such a spread, and refining them found that error rather than
/// any feature: a fifth of plane's and a quarter of colonnade's shaded pixels.
const DARK_SHARE: f64 = 0.25;

/// How far apart across the epipolar line through a pixel, in pixels, the two pixels it
/// is interpolated from on the finer grid may lie: as far as the finer grid's own
/// neighbours, two pixels apart.
const MAX_ACROSS: f64 = 2.0;

/// The span along an epipolar line, in pixels, over which a pair may differ by the
/// tolerance; pairs farther apart may differ in proportion. In-scattering varies smoothly
/// along the lines, so what the test bounds there is its gradient, as the same tolerance
/// over pairs four pixels apart did before the lattices grew sparser.
const TOLERANCE_SPAN: f64 = 4.0;

/// What of a ray's reach is affine across the image on a plane, so that a pixel whose
/// reach matches its neighbours' interpolated in it sees the surface they see, however
/// steeply that surface recedes (a ground plane towards the horizon).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SurfaceCoordinate {
    /// The reciprocal of the distance: a pinhole camera (exactly for the planar depth;
    /// the distance along a ray differs from it by a factor that varies slowly across
    /// the image).
    InverseDistance,
    /// The distance itself: a parallel projection.
    Distance,
}

impl SurfaceCoordinate {
    pub fn of_camera(camera: &CameraModel) -> Self {
        if camera.is_perspective() {
            Self::InverseDistance
        } else {
            Self::Distance
        }
    }

    #[inline(always)]
    fn of(self, reach: f32) -> f32 {
        match self {
            Self::InverseDistance => 1.0 / reach,
            Self::Distance => reach,
        }
    }

    /// The reach whose coordinate is `coordinate`.
    #[cfg(test)]
    fn reach(self, coordinate: f32) -> f32 {
        match self {
            Self::InverseDistance => 1.0 / coordinate,
            Self::Distance => coordinate,
        }
    }

    /// Whether a ray ending at `reach` ends on the surface whose coordinate at its pixel
    /// is `expected` ([`blend_if_agreeing`]): within [`EDGE_DEPTH_SPREAD`] of it. Without
    /// a division for the inverse distance e, |1/e − reach| ≤ spread·reach being
    /// |1 − e·reach| ≤ spread·e·reach for the e > 0 of reaches up to the max distance.
    #[inline(always)]
    fn holds(self, expected: f32, reach: f32) -> bool {
        let spread = EDGE_DEPTH_SPREAD as f32;
        match self {
            Self::InverseDistance => {
                let product = expected * reach;
                (1.0 - product).abs() <= spread * product
            }
            Self::Distance => (expected - reach).abs() <= spread * reach,
        }
    }
}

/// The image's epipolar lines: they all pass through the epipole, the image of the
/// light's direction, or run parallel to its image when that lies at infinity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpipolarLines {
    /// Homogeneous (x·w, y·w, w) in the shaded image's pixel indices; w = 0 for
    /// parallel lines along (x, y).
    epipole: [f64; 3],
}

impl EpipolarLines {
    /// Lines through the homogeneous point `epipole`, in pixel indices.
    pub fn through(epipole: [f64; 3]) -> Self {
        Self { epipole }
    }

    /// The lines of `camera`'s image lit along `light_travel`, for an image whose pixel
    /// (x, y) is `camera`'s pixel (`stride`·x + `stride`/2, `stride`·y + `stride`/2), as
    /// with downsampling ([`crate::upsample::sample_pixel`]).
    pub fn of_view(camera: &CameraModel, light_travel: DVec3, stride: u32) -> Self {
        let image = camera.pixel_from_world() * light_travel.extend(0.0);
        // The pixel's centre lies half a pixel past its index.
        let offset = (stride / 2) as f64 + 0.5;
        let scale = 1.0 / stride as f64;
        Self::through([
            (image.x - offset * image.w) * scale,
            (image.y - offset * image.w) * scale,
            image.w,
        ])
    }

    /// The direction of the epipolar line through pixel (`x`, `y`), not normalized:
    /// zero at the epipole, where it has none.
    #[inline]
    fn direction(&self, x: usize, y: usize) -> [f64; 2] {
        let [ex, ey, ew] = self.epipole;
        [ex - x as f64 * ew, ey - y as f64 * ew]
    }

    /// Whether a pair of pixels `span` apart (from one to the other), either side of pixel
    /// (`x`, `y`), lies at most [`MAX_ACROSS`] across the epipolar line through it: never
    /// at the epipole, where no line has a direction.
    #[inline]
    fn pairs_along(&self, x: usize, y: usize, span: [f64; 2]) -> bool {
        let [dx, dy] = self.direction(x, y);
        // The pair's distance across the line, times the direction's length.
        let cross = dx * span[1] - dy * span[0];
        let length_squared = dx * dx + dy * dy;
        length_squared > 1e-24 && cross * cross <= MAX_ACROSS * MAX_ACROSS * length_squared
    }

    /// For pixel (`x`, `y`) interpolated from the pixels at ±`offset` from it: how far
    /// apart they lie across the epipolar line through it, in pixels (∞ at the epipole).
    #[cfg(test)]
    fn across(&self, x: usize, y: usize, offset: [f64; 2]) -> f64 {
        let [dx, dy] = self.direction(x, y);
        let length = (dx * dx + dy * dy).sqrt();
        if length.is_nan() || length <= 1e-12 {
            return f64::INFINITY;
        }
        2.0 * (dx * offset[1] - dy * offset[0]).abs() / length
    }
}

/// Interpolation from shaded neighbours, where they agree and the pixel sees the same
/// surface.
struct Interpolation<'s, S> {
    tolerance: f32,
    /// Per channel of RGBA, the value below which spreads are held to the tolerance of
    /// this value rather than of the blend's ([`DARK_SHARE`]).
    floor: [f32; 4],
    max_distance: f32,
    coordinate: SurfaceCoordinate,
    surface: &'s S,
}

impl<S: Fn(usize, usize) -> Option<f64>> Interpolation<'_, S> {
    /// Pixel (x, y) as the blend of `neighbours` by `weights` ([`blend_if_agreeing`]),
    /// where it lies on their surface.
    #[inline(always)]
    fn between<const N: usize>(
        &self,
        neighbours: [Pixel; N],
        weights: [f32; N],
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        let blend = blend_if_agreeing(
            neighbours,
            weights,
            self.tolerance,
            self.floor,
            self.max_distance,
            self.coordinate,
        )?;
        let surface = (self.surface)(x, y)?;
        let reach = surface.min(self.max_distance as f64) as f32;
        if !self.coordinate.holds(blend.coordinate, reach) {
            return None;
        }
        Some(Pixel {
            volume: blend.volume,
            visibility: blend.visibility,
            depth: layer_depth(surface, self.max_distance as f64) as f32,
        })
    }

    /// Pixel (x, y) as the mean of `neighbours`, where they agree and it lies on their
    /// surface.
    #[inline]
    fn mean<const N: usize>(&self, neighbours: [Pixel; N], x: usize, y: usize) -> Option<Pixel> {
        self.between(neighbours, [1.0 / N as f32; N], x, y)
    }

    /// Pixel (x, y) as the mean of the first of two pairs either side of it that agrees
    /// ([`Interpolation::mean`]): `first`, else `second()`; `None` where a pair is missing
    /// counts as disagreeing.
    #[inline]
    fn mean_of_either(
        &self,
        first: Option<[Pixel; 2]>,
        second: impl FnOnce() -> Option<[Pixel; 2]>,
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        first
            .and_then(|pair| self.mean(pair, x, y))
            .or_else(|| self.mean(second()?, x, y))
    }

    /// Pixel (x, y) between `pair`, apart along the epipolar line through it by the span
    /// of `pairing`, `fraction` of the way from the first: the tolerance widened in
    /// proportion to the span ([`TOLERANCE_SPAN`]).
    #[inline]
    fn along(
        &self,
        pair: [Pixel; 2],
        fraction: f32,
        pairing: &Pairing,
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        let wider = Interpolation {
            tolerance: self.tolerance * pairing.widening,
            ..*self
        };
        wider.between(pair, [1.0 - fraction, fraction], x, y)
    }
}

/// The finer grid's points in bands of [`TILE`] rows, even and odd bands apart so that
/// one parity's bands can be completed in parallel while their pairs read the lattice
/// points of the others. Every point is set before it is read, so the storage is an
/// earlier frame's where one is kept (see `crate::spare`).
struct FinerGrid {
    width: usize,
    /// The points of one band: [`TILE`] rows (the last band may have fewer).
    band_len: usize,
    /// The even bands one after another, then the odd ones.
    parities: [Vec<Pixel>; 2],
}

/// A pair spans at most [`MAX_ALONG`] / 2 of the finer grid's rows, fewer than a band
/// has, so it reaches only into the bands beside.
const _: () = assert!(MAX_ALONG / 2.0 < TILE as f64);

static SPARE_EVEN_BANDS: Spare<Pixel> = Spare::new();
static SPARE_ODD_BANDS: Spare<Pixel> = Spare::new();

/// Lets go of the finer grid's and the band edges' kept buffers ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_EVEN_BANDS.clear();
    SPARE_ODD_BANDS.clear();
    SPARE_BAND_EDGES.clear();
}

impl FinerGrid {
    fn new(width: usize, height: usize) -> Self {
        let band_len = TILE * width;
        let count = height.div_ceil(TILE);
        // Only the last band can be short, and it is the last of its parity.
        let rows_of = |parity: usize| {
            (parity..count)
                .step_by(2)
                .map(|band| TILE.min(height - band * TILE))
                .sum::<usize>()
        };
        Self {
            width,
            band_len,
            parities: [
                SPARE_EVEN_BANDS.take(rows_of(0) * width),
                SPARE_ODD_BANDS.take(rows_of(1) * width),
            ],
        }
    }

    /// Row `j`, `None` past the last.
    #[inline]
    fn row(&self, j: usize) -> Option<&[Pixel]> {
        let band = j / TILE;
        let start = band / 2 * self.band_len + j % TILE * self.width;
        self.parities[band % 2].get(start..start + self.width)
    }
}

impl Drop for FinerGrid {
    fn drop(&mut self) {
        let [even, odd] = &mut self.parities;
        SPARE_EVEN_BANDS.keep(std::mem::take(even));
        SPARE_ODD_BANDS.keep(std::mem::take(odd));
    }
}

/// The centres on each band's last odd row ([`TILE`] rows a band), one row of them a
/// band: the band below reads them too. Every one is set before it is read, so the
/// storage is an earlier frame's where one is kept.
struct BandEdges {
    values: Vec<Pixel>,
}

static SPARE_BAND_EDGES: Spare<Pixel> = Spare::new();

impl BandEdges {
    fn new(len: usize) -> Self {
        Self {
            values: SPARE_BAND_EDGES.take(len),
        }
    }

    /// Band `band`'s row of `width` centres.
    #[inline]
    fn row(&self, band: usize, width: usize) -> &[Pixel] {
        &self.values[band * width..(band + 1) * width]
    }
}

impl Drop for BandEdges {
    fn drop(&mut self) {
        SPARE_BAND_EDGES.keep(std::mem::take(&mut self.values));
    }
}

/// The most points of the finer grid a pair may lie apart along an epipolar line, so
/// that at best one in this many is shaded: along the grid's axes six, pairs
/// [`MAX_ALONG`] apart, and along its diagonals four. (At most four shaded 21% more of
/// plane's pixels, whose lines run down the image; eight, with pairs 16 px apart, took
/// as long on tree and moved the layers twice as far from every pixel shaded.)
const MAX_STRIDE: i64 = 6;

/// The largest component of a lattice's step.
const MAX_STEP: i64 = 3;

/// The longest a pair may span along an epipolar line, in pixels.
const MAX_ALONG: f64 = 12.0;

/// Side of the squares of the finer grid that share one [`Lattice`], in its points.
const LATTICE_TILE: usize = 8;

/// The points of the finer grid shaded first in a square of it: on each of its lines
/// along `step` (a primitive vector of the finer grid, close to the square's epipolar
/// lines), every `stride`-th point, so that every other point lies between two of them
/// on its own line, at most [`MAX_ALONG`] pixels apart and [`MAX_ACROSS`] across the
/// epipolar line through it. A stride of 1 shades every point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Lattice {
    step: [i64; 2],
    stride: i64,
    /// Integer coefficients with `position`·`step` = 1, so that `position`·p counts
    /// steps along the lines.
    position: [i64; 2],
}

impl Lattice {
    const EVERY_POINT: Lattice = Lattice {
        step: [1, 0],
        stride: 1,
        position: [1, 0],
    };

    /// The steps a lattice may take, in the order [`Lattice::along`] prefers them among
    /// equals, with their Bézout coefficients and length in pixels: the primitive vectors
    /// of the finer grid up to [`MAX_STEP`], one of each ± pair, short enough that a pair
    /// two steps apart fits within [`MAX_ALONG`] (longer ones only ever have stride 1,
    /// which never wins). Found once per frame, not once per square.
    fn candidates() -> Vec<LatticeStep> {
        let mut candidates = Vec::new();
        for a in -MAX_STEP..=MAX_STEP {
            for b in 0..=MAX_STEP {
                // (−1, 0) is (1, 0) the other way round.
                if b == 0 && a != 1 {
                    continue;
                }
                let Some(position) = bezout([a, b]) else {
                    continue;
                };
                // Pixels per step: the finer grid's points lie two pixels apart.
                let length = 2.0 * ((a * a + b * b) as f64).sqrt();
                if 2.0 * length <= MAX_ALONG {
                    candidates.push(LatticeStep {
                        step: [a, b],
                        position,
                        length,
                    });
                }
            }
        }
        candidates
    }

    /// The sparsest lattice for a square whose epipolar lines run along `directions`
    /// (in pixels, at its corners: around an epipole off the square the extremes lie
    /// there), with the shortest pairs among equally sparse ones, of `candidates`
    /// ([`Lattice::candidates`]).
    fn along(directions: &[[f64; 2]; 4], candidates: &[LatticeStep]) -> Self {
        let mut units = [[0.0; 2]; 4];
        for (unit, &[dx, dy]) in units.iter_mut().zip(directions) {
            let norm = dx.hypot(dy);
            if !(norm > 1e-12 && norm.is_finite()) {
                return Self::EVERY_POINT;
            }
            *unit = [dx / norm, dy / norm];
        }
        let mut best = Self::EVERY_POINT;
        let mut best_span = f64::INFINITY;
        for &LatticeStep {
            step: [a, b],
            position,
            length,
        } in candidates
        {
            let cross_max = units
                .iter()
                .map(|[dx, dy]| (dx * b as f64 - dy * a as f64).abs())
                .fold(0.0, f64::max);
            let sin_max = 2.0 * cross_max / length;
            let mut stride = MAX_STRIDE;
            while stride > 1 {
                let span = stride as f64 * length;
                if span <= MAX_ALONG && span * sin_max <= MAX_ACROSS {
                    break;
                }
                stride -= 1;
            }
            let span = stride as f64 * length;
            if stride > best.stride || (stride == best.stride && stride > 1 && span < best_span) {
                best = Lattice {
                    step: [a, b],
                    stride,
                    position,
                };
                best_span = span;
            }
        }
        best
    }

    /// How many steps point (i, j) of the finer grid lies past the lattice point behind
    /// it on its line: 0 for the lattice's own points.
    #[inline]
    fn offset(&self, i: usize, j: usize) -> i64 {
        self.wrap(self.position[0] * i as i64 + self.position[1] * j as i64)
    }

    /// `steps` modulo the stride, in [0, stride).
    #[inline]
    fn wrap(&self, steps: i64) -> i64 {
        // Strides are at most MAX_STRIDE: constant divisors rather than a division by a
        // variable, which took a tenth of completing the finer grid.
        match self.stride {
            1 => 0,
            2 => steps.rem_euclid(2),
            3 => steps.rem_euclid(3),
            4 => steps.rem_euclid(4),
            5 => steps.rem_euclid(5),
            6 => steps.rem_euclid(6),
            stride => steps.rem_euclid(stride),
        }
    }
}

/// A step a [`Lattice`] may take ([`Lattice::candidates`]).
#[derive(Clone, Copy, Debug)]
struct LatticeStep {
    step: [i64; 2],
    /// Its Bézout coefficients ([`Lattice::position`]).
    position: [i64; 2],
    /// Pixels per step.
    length: f64,
}

/// Integers (c, d) with c·a + d·b = 1 for `step` (a, b), `None` where it is not primitive
/// (a and b share a factor, or both are 0).
fn bezout([a, b]: [i64; 2]) -> Option<[i64; 2]> {
    // Extended Euclid on (a, b), tracking the coefficients of a and b.
    let (mut r0, mut r1) = (a, b);
    let (mut c0, mut c1) = (1i64, 0i64);
    let (mut d0, mut d1) = (0i64, 1i64);
    while r1 != 0 {
        let q = r0.div_euclid(r1);
        (r0, r1) = (r1, r0 - q * r1);
        (c0, c1) = (c1, c0 - q * c1);
        (d0, d1) = (d1, d0 - q * d1);
    }
    // r0 is the greatest common divisor, up to its sign.
    (r0.abs() == 1).then(|| [c0 * r0, d0 * r0])
}

/// What the pairs of a [`Lattice`] have in common, found once per square rather than
/// once per point.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Pairing {
    /// From the first point of a pair to the second, in pixels.
    span: [f64; 2],
    /// The tolerance's factor for pairs that far apart ([`TOLERANCE_SPAN`]).
    widening: f32,
    /// The fraction of the way from the first point of a pair to the second that a point
    /// `behind` steps past the first lies: `behind` / stride.
    fractions: [f32; MAX_STRIDE as usize],
}

impl Pairing {
    fn of(lattice: &Lattice) -> Self {
        let [a, b] = lattice.step;
        // The finer grid's points lie two pixels apart.
        let span = [
            (2 * lattice.stride * a) as f64,
            (2 * lattice.stride * b) as f64,
        ];
        let length = (span[0] * span[0] + span[1] * span[1]).sqrt();
        Self {
            span,
            widening: (length / TOLERANCE_SPAN).max(1.0) as f32,
            fractions: std::array::from_fn(|behind| behind as f32 / lattice.stride as f32),
        }
    }
}

/// The [`Lattice`] of each square of a finer grid.
struct Lattices {
    across: usize,
    squares: Vec<Lattice>,
    /// Each square's [`Pairing`].
    pairings: Vec<Pairing>,
}

impl Lattices {
    /// For a finer grid of `width` × `height` points, whose point (i, j) is pixel
    /// (2i, 2j), under `lines` (every point shaded without).
    fn of_grid(width: usize, height: usize, lines: Option<&EpipolarLines>) -> Self {
        let across = width.div_ceil(LATTICE_TILE);
        let down = height.div_ceil(LATTICE_TILE);
        let candidates = Lattice::candidates();
        let squares = (0..down * across)
            .into_par_iter()
            .map(|square| {
                let Some(lines) = lines else {
                    return Lattice::EVERY_POINT;
                };
                let (i0, j0) = (
                    square % across * LATTICE_TILE,
                    square / across * LATTICE_TILE,
                );
                let (i1, j1) = (
                    (i0 + LATTICE_TILE).min(width) - 1,
                    (j0 + LATTICE_TILE).min(height) - 1,
                );
                let corners = [(i0, j0), (i1, j0), (i0, j1), (i1, j1)]
                    .map(|(i, j)| lines.direction(2 * i, 2 * j));
                Lattice::along(&corners, &candidates)
            })
            .collect::<Vec<_>>();
        let pairings = squares.iter().map(Pairing::of).collect();
        Self {
            across,
            squares,
            pairings,
        }
    }

    /// The index of the square of point (i, j).
    #[inline]
    fn square(&self, i: usize, j: usize) -> usize {
        j / LATTICE_TILE * self.across + i / LATTICE_TILE
    }

    #[inline]
    fn at(&self, i: usize, j: usize) -> &Lattice {
        &self.squares[self.square(i, j)]
    }

    /// Whether point (i, j) is one of its square's lattice points.
    #[inline]
    fn contains(&self, i: usize, j: usize) -> bool {
        self.at(i, j).offset(i, j) == 0
    }

    /// Calls `visit(i, offset)` for the points `columns` of row `j` with their
    /// [`Lattice::offset`]s, found by adding rather than dividing.
    #[inline]
    fn offsets_in_row(
        &self,
        columns: std::ops::Range<usize>,
        j: usize,
        mut visit: impl FnMut(usize, i64),
    ) {
        let mut i = columns.start;
        while i < columns.end {
            let lattice = self.at(i, j);
            let advance = lattice.wrap(lattice.position[0]);
            let mut offset = lattice.offset(i, j);
            let square_end = ((i / LATTICE_TILE + 1) * LATTICE_TILE).min(columns.end);
            for i in i..square_end {
                visit(i, offset);
                offset += advance;
                if offset >= lattice.stride {
                    offset -= lattice.stride;
                }
            }
            i = square_end;
        }
    }
}

/// Where [`shade_adaptively`]'s time went, in seconds: its first pass (the lattice
/// points, shaded), its second (the rest of the finer grid, interpolated along the
/// epipolar lines or shaded) and its last (the pixels between the finer grid's points).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptivePasses {
    pub lattice: f64,
    pub finer_grid: f64,
    pub between: f64,
}

/// Shades a `width` × `height` image adaptively. `shade(pixels, out)` gives the layers of
/// a run of pixels (x, y), in shading order (tile by tile), and is called on several runs
/// at once, so a pixel's layers may depend on nothing but the pixel;
/// `surface(x, y)` the distance to the surface its whole footprint sees (+∞ for
/// background), or `None` where a depth edge runs through it, which is then shaded.
/// `lines`, the image's epipolar lines where the light is directional, let the grid be
/// sparser along them; without, every other pixel of every other row is shaded.
/// `control` advances by one unit per row. Returns the layers, how many pixels were
/// shaded, and how long each pass took.
#[allow(clippy::too_many_arguments)]
pub fn shade_adaptively(
    width: usize,
    height: usize,
    tolerance: f32,
    max_distance: f32,
    lines: Option<EpipolarLines>,
    coordinate: SurfaceCoordinate,
    control: &RenderControl,
    surface: impl Fn(usize, usize) -> Option<f64> + Sync,
    shade: impl Fn(&[(usize, usize)], &mut [Pixel]) + Sync,
) -> (Layers, usize, AdaptivePasses) {
    let mut stopwatch = Stopwatch::start();
    let lines = lines.as_ref();
    let grid_width = width.div_ceil(2);
    let grid_height = height.div_ceil(2);
    let lattices = Lattices::of_grid(grid_width, grid_height, lines);
    let shaded_count = AtomicUsize::new(0);
    let mut grid = FinerGrid::new(grid_width, grid_height);
    // The lattices' points, shaded tile by tile for the locality of their rectified data.
    let band_len = grid.band_len;
    let [even, odd] = &mut grid.parities;
    let numbered = |parity: usize| move |(k, pixels)| (2 * k + parity, pixels);
    let (sums, points) = even
        .par_chunks_mut(band_len)
        .enumerate()
        .map(numbered(0))
        .chain(odd.par_chunks_mut(band_len).enumerate().map(numbered(1)))
        .map(|(band, pixels): (usize, &mut [Pixel])| {
            if control.is_cancelled() {
                return ([0.0f64; 4], 0usize);
            }
            let first = band * TILE;
            let mut batch = Batch::default();
            for tile in (0..grid_width).step_by(TILE) {
                for row in 0..pixels.len() / grid_width {
                    let columns = tile..(tile + TILE).min(grid_width);
                    lattices.offsets_in_row(columns, first + row, |i, offset| {
                        if offset == 0 {
                            batch.push(row * grid_width + i, (2 * i, 2 * (first + row)));
                        }
                    });
                }
            }
            shaded_count.fetch_add(batch.shade(&shade, pixels), Ordering::Relaxed);
            // Each lattice point stands for `stride` points of the finer grid.
            let (mut sums, mut points) = ([0.0; 4], 0);
            for &slot in &batch.slots {
                let (i, j) = (slot % grid_width, first + slot / grid_width);
                let stride = lattices.at(i, j).stride;
                for (sum, value) in sums.iter_mut().zip(pixels[slot].volume) {
                    *sum += stride as f64 * value as f64;
                }
                points += stride as usize;
            }
            (sums, points)
        })
        .reduce(
            || ([0.0; 4], 0),
            |(a, n), (b, m)| (std::array::from_fn(|k| a[k] + b[k]), n + m),
        );
    let lattice = stopwatch.lap();
    let floor = sums.map(|sum| (DARK_SHARE * sum / points.max(1) as f64) as f32);
    let interpolation = Interpolation {
        tolerance,
        floor,
        max_distance,
        coordinate,
        surface: &surface,
    };
    // The other points, the bands of each parity in parallel: a band's pairs reach only
    // into itself and the bands either side, of the other parity, whose lattice points
    // stay as they are.
    for parity in 0..2 {
        let [even, odd] = &mut grid.parities;
        let (completing, beside) = if parity == 0 {
            (even, &*odd)
        } else {
            (odd, &*even)
        };
        completing
            .par_chunks_mut(band_len)
            .enumerate()
            .for_each(|(k, pixels)| {
                if control.is_cancelled() {
                    return;
                }
                let band = 2 * k + parity;
                let first = band * TILE;
                let rows = pixels.len() / grid_width;
                // Lattice point (i, j), `None` off the grid or where (i, j) is none; the
                // square `home`'s own lattice points need no test.
                let lattice_point = |pixels: &[Pixel], i: i64, j: i64, home: usize| {
                    let (i, j) = (usize::try_from(i).ok()?, usize::try_from(j).ok()?);
                    if i >= grid_width || j >= grid_height {
                        return None;
                    }
                    if lattices.square(i, j) != home && !lattices.contains(i, j) {
                        return None;
                    }
                    let at = j % TILE * grid_width + i;
                    Some(match j / TILE {
                        b if b == band => pixels[at],
                        b => beside[b / 2 * band_len + at],
                    })
                };
                // Point (i, j), `behind` steps past the lattice point behind it on its
                // line, between that and the next where they lie along the epipolar line
                // through it ([`MAX_ACROSS`]), agree and see its surface.
                let interpolated = |pixels: &[Pixel], i: usize, j: usize, behind: i64| {
                    let home = lattices.square(i, j);
                    let lattice = &lattices.squares[home];
                    let ahead = lattice.stride - behind;
                    let [a, b] = lattice.step;
                    let (pi, pj) = (i as i64, j as i64);
                    let pair = [
                        lattice_point(pixels, pi - behind * a, pj - behind * b, home)?,
                        lattice_point(pixels, pi + ahead * a, pj + ahead * b, home)?,
                    ];
                    let (x, y) = (2 * i, 2 * j);
                    let pairing = &lattices.pairings[home];
                    if !lines?.pairs_along(x, y, pairing.span) {
                        return None;
                    }
                    let fraction = pairing.fractions[behind as usize];
                    interpolation.along(pair, fraction, pairing, x, y)
                };
                let mut batch = Batch::default();
                for row in 0..rows {
                    let j = first + row;
                    lattices.offsets_in_row(0..grid_width, j, |i, behind| {
                        if behind != 0 {
                            let k = row * grid_width + i;
                            match interpolated(pixels, i, j, behind) {
                                Some(value) => pixels[k] = value,
                                None => batch.push(k, (2 * i, 2 * j)),
                            }
                        }
                    });
                }
                let batch = batch.in_tiles(grid_width, |(x, _)| x / 2);
                shaded_count.fetch_add(batch.shade(&shade, pixels), Ordering::Relaxed);
                control.advance(rows as u64);
            });
    }
    let finer_grid = stopwatch.lap();
    // The centres of the finer grid's squares, pixels (2i + 1, 2j + 1): the mean of the
    // four corners where they agree, else of the diagonal pair along the epipolar line
    // through the centre; shaded where neither agrees or a corner is missing (on the last
    // column or row).
    let (centre_width, centre_height) = (width / 2, height / 2);
    let centre = |corners: [Pixel; 4], x: usize, y: usize| {
        interpolation.mean(corners, x, y).or_else(|| {
            let [top_left, top_right, bottom_left, bottom_right] = corners;
            let lines = lines?;
            let diagonal = if lines.pairs_along(x, y, [2.0, 2.0]) {
                [top_left, bottom_right]
            } else if lines.pairs_along(x, y, [2.0, -2.0]) {
                [bottom_left, top_right]
            } else {
                return None;
            };
            interpolation.mean(diagonal, x, y)
        })
    };
    // Row j of the centres appended to `out`, and those that must be shaded pushed to
    // `batch` with their index in `out`.
    let centre_row = |j: usize, out: &mut Vec<Pixel>, batch: &mut Batch| {
        let y = 2 * j + 1;
        let start = out.len();
        if let (Some(above), Some(below)) = (grid.row(j), grid.row(j + 1)) {
            for (i, (top, bottom)) in above.windows(2).zip(below.windows(2)).enumerate() {
                let value = centre([top[0], top[1], bottom[0], bottom[1]], 2 * i + 1, y);
                if value.is_none() {
                    batch.push(out.len(), (2 * i + 1, y));
                }
                out.push(value.unwrap_or_default());
            }
        }
        // Those with a corner missing: every one on the last row of an even height, and
        // the last column's where the width is even.
        for i in out.len() - start..centre_width {
            batch.push(out.len(), (2 * i + 1, y));
            out.push(Pixel::default());
        }
    };
    // A band's pixels read the centres of its own odd rows and of the odd row above it;
    // that row, the last of the band above, is completed first, so that every centre is
    // completed once and bands can be completed in parallel.
    let band_count = height.div_ceil(TILE);
    let last_centre_row = |band: usize| (band + 1) * TILE / 2 - 1;
    let mut edges = BandEdges::new(band_count * centre_width);
    edges
        .values
        .par_chunks_mut(centre_width.max(1))
        .enumerate()
        .for_each(|(band, out)| {
            let j = last_centre_row(band);
            if control.is_cancelled() || j >= centre_height {
                return;
            }
            let (mut row, mut batch) = (Vec::new(), Batch::default());
            centre_row(j, &mut row, &mut batch);
            shaded_count.fetch_add(batch.shade(&shade, &mut row), Ordering::Relaxed);
            out.copy_from_slice(&row);
        });
    let edges = &edges;
    let between_shaded = AtomicUsize::new(0);
    let mut layers = Layers::for_overwrite(width as u32, height as u32);
    layers.par_bands_mut(TILE).for_each(|mut band| {
        if control.is_cancelled() {
            return;
        }
        let rows = band.rows;
        let index = band.first_row / TILE;
        // The band's centres; its last row is the one completed first.
        let first_centre_row = band.first_row / 2;
        let centre_rows = (rows / 2).min(centre_height.saturating_sub(first_centre_row));
        let mut centres = Vec::with_capacity(centre_rows * centre_width);
        let mut batch = Batch::default();
        for j in first_centre_row..first_centre_row + centre_rows {
            if j == last_centre_row(index) {
                centres.extend_from_slice(edges.row(index, centre_width));
            } else {
                centre_row(j, &mut centres, &mut batch);
            }
        }
        let batch = batch.in_tiles(centre_width, |(x, _)| x / 2);
        between_shaded.fetch_add(batch.shade(&shade, &mut centres), Ordering::Relaxed);
        let centres_of = |j: usize| -> Option<&[Pixel]> {
            match j.checked_sub(first_centre_row) {
                None if j + 1 == first_centre_row => Some(edges.row(index - 1, centre_width)),
                None => None,
                Some(r) => centres.get(r * centre_width..(r + 1) * centre_width),
            }
        };
        // Interpolated row by row, which streams through the finer grid and the
        // surfaces; the pixels that must be shaded are shaded afterwards tile by tile,
        // for the locality of their rectified data. (Blending eight pixels to an AVX2
        // register, bit for bit the same, from a planar copy of the finer grid made per
        // band or per frame, made this pass 1–5 ms slower at 1080p: the loads, surface
        // reads and writes around each blend cost more than its arithmetic.)
        let mut batch = Batch::default();
        for row in 0..rows {
            let y = band.first_row + row;
            let start = row * width;
            let mut put = |x: usize, pixel: Option<Pixel>| match pixel {
                Some(pixel) => band.set(start + x, &pixel),
                None => batch.push(start + x, (x, y)),
            };
            let j = y / 2;
            let Some(above) = grid.row(j) else {
                (0..width).for_each(|x| put(x, None));
                continue;
            };
            // The other pixels lie between two of the finer grid's points (left and
            // right on its rows, above and below between them), or between two centres
            // the other way: the mean of the first pair that agrees.
            if y % 2 == 0 {
                let beside = j.checked_sub(1).and_then(centres_of).zip(centres_of(j));
                let centres_beside = |i: usize| {
                    let (above, below) = beside?;
                    Some([*above.get(i)?, *below.get(i)?])
                };
                for (i, &point) in above.iter().enumerate() {
                    let x = 2 * i + 1;
                    put(x - 1, Some(point));
                    if x < width {
                        let grid_pair = above.get(i + 1).map(|&next| [point, next]);
                        let value =
                            interpolation.mean_of_either(grid_pair, || centres_beside(i), x, y);
                        put(x, value);
                    }
                }
            } else {
                let centres = centres_of(j).unwrap_or_default();
                let centres_beside =
                    |i: usize| Some([*centres.get(i.checked_sub(1)?)?, *centres.get(i)?]);
                let below = grid.row(j + 1);
                for (i, &point) in above.iter().enumerate() {
                    let x = 2 * i;
                    let grid_pair = below.map(|below| [point, below[i]]);
                    put(
                        x,
                        interpolation.mean_of_either(grid_pair, || centres_beside(i), x, y),
                    );
                    if let Some(centre) = centres.get(i) {
                        put(x + 1, Some(*centre));
                    }
                }
            }
        }
        let batch = batch.in_tiles(width, |(x, _)| x);
        let shaded = batch.shade_each(&shade, |k, pixel| band.set(k, pixel));
        between_shaded.fetch_add(shaded, Ordering::Relaxed);
        // The finer grid's rows were counted as they were completed.
        control.advance((rows / 2) as u64);
    });
    let passes = AdaptivePasses {
        lattice,
        finer_grid,
        between: stopwatch.lap(),
    };
    (
        layers,
        shaded_count.into_inner() + between_shaded.into_inner(),
        passes,
    )
}

/// How many pixels of a [`Batch`] one thread shades at a time: long enough for a method's
/// look-ahead along them, short enough to share out a band's batch.
const SHADING_RUN: usize = 128;

/// Pixels to shade, in shading order, with where each result goes; shaded together so
/// that a method can look ahead along the batch (prefiltering locates the next rays while
/// it evaluates the current one).
#[derive(Default)]
struct Batch {
    slots: Vec<usize>,
    pixels: Vec<(usize, usize)>,
}

impl Batch {
    fn push(&mut self, slot: usize, pixel: (usize, usize)) {
        self.slots.push(slot);
        self.pixels.push(pixel);
    }

    /// The batch, pushed row by row, in the order
    /// [`for_each_in_tiles`](crate::render::for_each_in_tiles) visits a grid `width` wide:
    /// tile by tile of [`TILE`] columns, each tile's pixels in the order pushed. `column`
    /// gives a pixel's column in that grid. A counting sort of what was pushed, rather than
    /// a scan of every point in tile order for flags (a tenth of completing the pixels
    /// between the finer grid's).
    fn in_tiles(self, width: usize, column: impl Fn((usize, usize)) -> usize) -> Self {
        let tiles = width.div_ceil(TILE);
        if tiles <= 1 {
            return self;
        }
        let tile_of = |pixel| (column(pixel) / TILE).min(tiles - 1);
        let mut starts = vec![0usize; tiles + 1];
        for &pixel in &self.pixels {
            starts[tile_of(pixel) + 1] += 1;
        }
        for t in 0..tiles {
            starts[t + 1] += starts[t];
        }
        let mut sorted = Self {
            slots: vec![0; self.slots.len()],
            pixels: vec![(0, 0); self.pixels.len()],
        };
        for (&slot, &pixel) in self.slots.iter().zip(&self.pixels) {
            let at = &mut starts[tile_of(pixel)];
            sorted.slots[*at] = slot;
            sorted.pixels[*at] = pixel;
            *at += 1;
        }
        sorted
    }

    /// Shades the batch into `out[slot]`; returns how many were shaded.
    fn shade(
        &self,
        shade: &(impl Fn(&[(usize, usize)], &mut [Pixel]) + Sync),
        out: &mut [Pixel],
    ) -> usize {
        self.shade_each(shade, |slot, pixel| out[slot] = *pixel)
    }

    /// Shades the batch, handing each result to `store` with its slot. In runs of
    /// [`SHADING_RUN`] pixels that idle threads may take: the pixels to shade gather where
    /// shadow and depth edges are, in a few bands of the image, and one band's batch
    /// would otherwise keep one thread busy while the other waits at the end of the pass.
    fn shade_each(
        &self,
        shade: &(impl Fn(&[(usize, usize)], &mut [Pixel]) + Sync),
        mut store: impl FnMut(usize, &Pixel),
    ) -> usize {
        let mut results = vec![Pixel::default(); self.pixels.len()];
        results
            .par_chunks_mut(SHADING_RUN)
            .zip(self.pixels.par_chunks(SHADING_RUN))
            .for_each(|(out, pixels)| shade(pixels, out));
        for (&slot, pixel) in self.slots.iter().zip(&results) {
            store(slot, pixel);
        }
        self.pixels.len()
    }
}

/// Neighbours' blend where they agree ([`blend_if_agreeing`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Blend {
    volume: [f32; 4],
    visibility: f32,
    /// Their reaches interpolated in the [`SurfaceCoordinate`]: where the pixel's own ray
    /// ends, if it sees the surface through theirs ([`SurfaceCoordinate::holds`]).
    coordinate: f32,
}

/// The blend of `neighbours` by `weights` (summing to 1) where they agree: each of RGBA
/// spreads by at most `tolerance` times its blend, or times its `floor` where the blend
/// is below that (NaN stays a disagreement), and visibility by at most `tolerance`. Their
/// rays' ends (background and surfaces beyond it at `max_distance`) blend in `coordinate`.
/// NaN anywhere means disagreement.
#[inline(always)]
fn blend_if_agreeing<const N: usize>(
    neighbours: [Pixel; N],
    weights: [f32; N],
    tolerance: f32,
    floor: [f32; 4],
    max_distance: f32,
    coordinate: SurfaceCoordinate,
) -> Option<Blend> {
    // The reaches' coordinates first, side by side, so that their divisions overlap.
    let coordinates: [f32; N] = std::array::from_fn(|n| {
        let depth = neighbours[n].depth;
        // NaN stays NaN.
        coordinate.of(if depth > max_distance {
            max_distance
        } else {
            depth
        })
    });
    // Eight lanes, RGBA, visibility, the reach's coordinate and two of padding, so that
    // every step is one lane-wise operation.
    let mut low = [f32::INFINITY; 8];
    let mut high = [f32::NEG_INFINITY; 8];
    let lanes = |n: usize| {
        let pixel = &neighbours[n];
        let [r, g, b, a] = pixel.volume;
        [r, g, b, a, pixel.visibility, coordinates[n], 0.0, 0.0]
    };
    // The first neighbour plus the others' weighted differences from it, so that equal
    // neighbours blend to exactly their value.
    let first = lanes(0);
    let mut blend = first;
    for (n, weight) in weights.into_iter().enumerate() {
        let values = lanes(n);
        // Comparisons rather than f32::min and max, which vectorize without their NaN
        // handling and give the same: NaN never replaces a bound, and blends to NaN.
        for k in 0..8 {
            low[k] = if values[k] < low[k] {
                values[k]
            } else {
                low[k]
            };
            high[k] = if values[k] > high[k] {
                values[k]
            } else {
                high[k]
            };
            blend[k] += weight * (values[k] - first[k]);
        }
    }
    // Per lane, the spread allowed: relative for RGBA, absolute for visibility; the
    // reaches may spread as a receding surface's do (the pixel's own is tested against
    // their blend), and only NaN there disagrees.
    let allowed: [f32; 8] = std::array::from_fn(|k| match k {
        0..4 => {
            let magnitude = blend[k].abs();
            tolerance
                * if magnitude < floor[k] {
                    floor[k]
                } else {
                    magnitude
                }
        }
        4 => tolerance,
        5 => f32::INFINITY,
        _ => 0.0,
    });
    // Comparisons drop NaN from the bounds, so the reach's blend is checked itself.
    let mut agree = !blend[5].is_nan();
    for k in 0..8 {
        agree &= high[k] - low[k] <= allowed[k];
    }
    agree.then_some(Blend {
        volume: [blend[0], blend[1], blend[2], blend[3]],
        visibility: blend[4],
        coordinate: blend[5],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mean_if_agreeing<const N: usize>(
        neighbours: [Pixel; N],
        tolerance: f32,
        max_distance: f32,
    ) -> Option<Blend> {
        blend_if_agreeing(
            neighbours,
            [1.0 / N as f32; N],
            tolerance,
            [0.0; 4],
            max_distance,
            SurfaceCoordinate::InverseDistance,
        )
    }

    fn pixel(rgb: f32, alpha: f32, visibility: f32, depth: f32) -> Pixel {
        Pixel {
            volume: [rgb, 2.0 * rgb, 0.5 * rgb, alpha],
            visibility,
            depth,
        }
    }

    #[test]
    fn agreeing_neighbours_give_their_mean_and_the_depth_between_them() {
        let neighbours = [pixel(1.0, 0.5, 0.8, 10.1), pixel(1.005, 0.502, 0.805, 10.0)];
        let mean = mean_if_agreeing(neighbours, 0.01, 100.0).unwrap();
        let expected = [1.0025, 2.005, 0.50125, 0.501, 0.8025];
        let [r, g, b, a] = mean.volume;
        for (value, expected) in [r, g, b, a, mean.visibility].into_iter().zip(expected) {
            assert!(
                (value - expected).abs() < 1e-6,
                "{value} against {expected}"
            );
        }
        // Midway between them in inverse distance, as on a plane seen by a pinhole.
        let between = 2.0 / (1.0 / 10.1 + 1.0 / 10.0);
        let depth = SurfaceCoordinate::InverseDistance.reach(mean.coordinate);
        assert!((depth - between).abs() < 1e-5, "{depth}");
    }

    /// A surface receding from the camera (the ground towards the horizon) spreads its
    /// neighbours' depths far apart but keeps each pixel where the plane through theirs
    /// is; a step between surfaces does not.
    #[test]
    fn a_receding_surface_is_one_surface_and_a_step_is_not() {
        let (near, far) = (pixel(1.0, 0.5, 0.8, 10.0), pixel(1.0, 0.5, 0.8, 30.0));
        let pinhole = mean_if_agreeing([near, far], 0.01, 100.0).unwrap();
        let depth = SurfaceCoordinate::InverseDistance.reach(pinhole.coordinate);
        assert!((depth - 15.0).abs() < 1e-4, "{depth}");
        assert!(SurfaceCoordinate::InverseDistance.holds(pinhole.coordinate, 15.0));
        for step in [10.0, 30.0, 20.0] {
            assert!(
                !SurfaceCoordinate::InverseDistance.holds(pinhole.coordinate, step),
                "{step}"
            );
        }
        let parallel = blend_if_agreeing(
            [near, far],
            [0.5; 2],
            0.01,
            [0.0; 4],
            100.0,
            SurfaceCoordinate::Distance,
        )
        .unwrap();
        assert_eq!(SurfaceCoordinate::Distance.reach(parallel.coordinate), 20.0);
        assert!(SurfaceCoordinate::Distance.holds(parallel.coordinate, 20.0));
        assert!(!SurfaceCoordinate::Distance.holds(parallel.coordinate, 15.0));
        // A ground plane seen by a pinhole: each row's distance is inverse in its height
        // below the horizon, so rows two apart lie 5–50% apart in depth; the light varies
        // gently across it. Only the finer grid is shaded (a quarter, rounded up at the
        // edges) and every pixel keeps its value; with a post 4 m off on rows 20..30,
        // its edges are shaded.
        let (width, height) = (40, 40);
        let ground = |y: usize| 200.0 / (y as f64 + 4.0);
        for post in [false, true] {
            let depth = move |x: usize, y: usize| match (post, x, y) {
                (true, 19..=21, 20..30) => 4.0,
                _ => ground(y),
            };
            let value = |x: usize, y: usize| {
                let d = depth(x, y);
                let light = if d < 5.0 {
                    0.2
                } else {
                    0.5 + 0.0005 * (x + y) as f32
                };
                pixel(light, 0.3, 0.9, d as f32)
            };
            let (layers, shaded) =
                shade_image(width, height, 0.01, None, |x, y| Some(depth(x, y)), value);
            for y in 0..height {
                for x in 0..width {
                    let (got, want) = (layer_value(&layers, x, y), value(x, y));
                    assert!(
                        (got.volume[0] - want.volume[0]).abs() <= 0.01 * want.volume[0],
                        "({x}, {y}): {got:?} against {want:?}"
                    );
                    assert_eq!(got.depth, want.depth);
                }
            }
            let grid = width.div_ceil(2) * height.div_ceil(2);
            if post {
                assert!(shaded > grid + 20, "{shaded}");
            } else {
                assert!(shaded <= grid + width + height, "{shaded} of {grid}");
            }
        }
    }

    #[test]
    fn disagreement_anywhere_means_shading() {
        let base = pixel(1.0, 0.5, 0.8, 10.0);
        let cases = [
            ("radiance 2% apart", pixel(1.02, 0.5, 0.8, 10.0)),
            ("alpha 2% apart", pixel(1.0, 0.51, 0.8, 10.0)),
            ("visibility 0.02 apart", pixel(1.0, 0.5, 0.82, 10.0)),
            ("NaN radiance", pixel(f32::NAN, 0.5, 0.8, 10.0)),
            ("NaN depth", pixel(1.0, 0.5, 0.8, f32::NAN)),
        ];
        for (what, other) in cases {
            assert_eq!(mean_if_agreeing([base, other], 0.01, 100.0), None, "{what}");
            assert_eq!(
                mean_if_agreeing([base, base, base, other], 0.01, 100.0),
                None,
                "{what}, one of four"
            );
        }
        // A single channel's spread counts against that channel's own mean.
        let mut dim_blue = base;
        dim_blue.volume[2] = 0.01;
        let mut dimmer_blue = base;
        dimmer_blue.volume[2] = 0.0102;
        assert_eq!(mean_if_agreeing([dim_blue, dimmer_blue], 0.01, 100.0), None);
    }

    #[test]
    fn background_and_surfaces_past_the_max_distance_end_together() {
        let background = pixel(1.0, 0.5, 0.8, 100.0);
        let far_surface = pixel(1.0, 0.5, 0.8, 250.0);
        let mean = mean_if_agreeing([background, far_surface], 0.01, 100.0).unwrap();
        assert_eq!(
            SurfaceCoordinate::InverseDistance.reach(mean.coordinate),
            100.0
        );
        assert!(SurfaceCoordinate::InverseDistance.holds(mean.coordinate, 100.0));
        assert!(!SurfaceCoordinate::InverseDistance.holds(mean.coordinate, 50.0));
    }

    /// Shades a `width` × `height` image whose layers are `value(x, y)` and whose surface
    /// is `surface(x, y)`; returns the layers and how many pixels were shaded.
    fn shade_image(
        width: usize,
        height: usize,
        tolerance: f32,
        lines: Option<EpipolarLines>,
        surface: impl Fn(usize, usize) -> Option<f64> + Sync,
        value: impl Fn(usize, usize) -> Pixel + Sync,
    ) -> (Layers, usize) {
        let calls = AtomicUsize::new(0);
        let control = RenderControl::new();
        control.begin(height as u64);
        let (layers, shaded, _) = shade_adaptively(
            width,
            height,
            tolerance,
            100.0,
            lines,
            SurfaceCoordinate::InverseDistance,
            &control,
            surface,
            |pixels, out| {
                calls.fetch_add(pixels.len(), Ordering::Relaxed);
                for (&(x, y), out) in pixels.iter().zip(out) {
                    *out = value(x, y);
                }
            },
        );
        assert_eq!(control.progress(), (height as u64, height as u64));
        assert_eq!(shaded, calls.into_inner(), "the count of shaded pixels");
        (layers, shaded)
    }

    fn layer_value(layers: &Layers, x: usize, y: usize) -> Pixel {
        let k = y * layers.width as usize + x;
        Pixel {
            volume: layers.volume[k * 4..k * 4 + 4].try_into().unwrap(),
            visibility: layers.visibility[k],
            depth: layers.depth[k],
        }
    }

    #[test]
    fn a_smooth_image_is_interpolated_between_shaded_pixels() {
        // Linear in x and y, so every mean is exact up to rounding; 2% across the image.
        let value = |x: usize, y: usize| {
            let v = 1.0 + 0.0001 * x as f32 + 0.0002 * y as f32;
            pixel(v, 0.5 * v, 0.5 + 0.001 * v, 20.0)
        };
        for (width, height) in [(33, 17), (32, 18), (32, 17), (33, 18), (1, 1), (2, 2)] {
            let (layers, shaded) = shade_image(width, height, 0.01, None, |_, _| Some(20.0), value);
            // The even pixels of even rows; and where the last column is odd, its centres
            // (whose squares lack a corner) and the pixels at its ends (with a centre on
            // one side only); the same for the last row.
            let anchors = width.div_ceil(2) * height.div_ceil(2);
            let edge = |size: usize, along: usize| match size % 2 {
                0 => along / 2 + 1 + usize::from(along % 2 == 1 && along > 1),
                _ => 0,
            };
            let (last_column, last_row) = (edge(width, height), edge(height, width));
            let corner = usize::from(width % 2 == 0 && height % 2 == 0);
            assert_eq!(
                shaded,
                anchors + last_column + last_row - corner,
                "{width}×{height}"
            );
            for y in 0..height {
                for x in 0..width {
                    let got = layer_value(&layers, x, y);
                    let want = value(x, y);
                    for (got, want) in got.volume.iter().zip(want.volume) {
                        assert!(
                            (got - want).abs() < 1e-6,
                            "({x}, {y}): {got} against {want}"
                        );
                    }
                    assert!((got.visibility - want.visibility).abs() < 1e-6);
                    assert_eq!(got.depth, 20.0);
                }
            }
        }
    }

    #[test]
    fn shadow_edges_and_depth_edges_are_shaded() {
        let (width, height) = (40, 30);
        // A shaft two pixels wide at x = 20..22, a nearer object at y ≥ 21, and a pole
        // one pixel wide at x = 11, between pixels that agree: only its depth tells.
        let depth = |x: usize, y: usize| match (x, y) {
            (11, _) => 8.0,
            (_, 21..) => 5.0,
            _ => 20.0,
        };
        let value = |x: usize, y: usize| {
            let lit = (20..22).contains(&x);
            let v = if lit { 1.0 } else { 0.2 } * depth(x, y) as f32 / 20.0;
            pixel(v, 0.3, if lit { 1.0 } else { 0.0 }, depth(x, y) as f32)
        };
        let (layers, shaded) =
            shade_image(width, height, 0.01, None, |x, y| Some(depth(x, y)), value);
        for y in 0..height {
            for x in 0..width {
                assert_eq!(layer_value(&layers, x, y), value(x, y), "({x}, {y})");
            }
        }
        assert!(
            shaded < width * height / 2,
            "{shaded} of {} shaded",
            width * height
        );
        // A pixel with a depth edge inside is always shaded.
        let (_, every) = shade_image(8, 8, 1.0, None, |_, _| None, value);
        assert_eq!(every, 64);
    }

    #[test]
    fn epipolar_lines_measure_how_far_a_pair_lies_across_them() {
        // Parallel lines running down the image, and lines through (10, 10).
        let parallel = EpipolarLines::through([0.0, 3.0, 0.0]);
        assert_eq!(parallel.across(5, 7, [0.0, 2.0]), 0.0);
        assert_eq!(parallel.across(5, 7, [2.0, 0.0]), 4.0);
        assert!((parallel.across(5, 7, [2.0, 2.0]) - 4.0).abs() < 1e-12);
        let radial = EpipolarLines::through([20.0, 20.0, 2.0]);
        assert!(radial.across(10, 30, [0.0, 2.0]).abs() < 1e-12);
        assert!((radial.across(10, 30, [2.0, 0.0]) - 4.0).abs() < 1e-12);
        assert!(radial.across(14, 14, [2.0, 2.0]).abs() < 1e-12);
        assert_eq!(radial.across(10, 10, [0.0, 2.0]), f64::INFINITY);
    }

    #[test]
    fn a_view_s_epipolar_lines_are_the_images_of_light_rays() {
        use crate::scene::{Camera, Projection, SensorFit};
        use glam::{Mat4, Quat, Vec3};
        let perspective = Projection::Perspective {
            focal_length: 35.0,
            sensor_width: 36.0,
            sensor_height: 24.0,
            sensor_fit: SensorFit::Auto,
            shift_x: 0.1,
            shift_y: 0.0,
        };
        let orthographic = Projection::Orthographic {
            ortho_scale: 8.0,
            sensor_fit: SensorFit::Auto,
            shift_x: 0.0,
            shift_y: -0.2,
        };
        let light_travel = DVec3::new(0.3, -0.5, -0.8).normalize();
        for projection in [perspective, orthographic] {
            let camera = CameraModel::new(&Camera {
                world_from_camera: Mat4::from_rotation_translation(
                    Quat::from_euler(glam::EulerRot::XYZ, 1.2, 0.1, 0.7),
                    Vec3::new(1.0, -6.0, 2.0),
                ),
                projection,
                clip_start: 0.1,
                clip_end: 100.0,
                width: 160,
                height: 90,
            });
            for stride in [1, 2, 4] {
                let lines = EpipolarLines::of_view(&camera, light_travel, stride);
                for (x, y) in [(3, 4), (20, 11), (39, 21)] {
                    // The point this pixel sees 10 units off, and one 5 units further
                    // along the light: both lie in the pixel's epipolar plane.
                    let centre = |i: usize| (i as u32 * stride + stride / 2) as f64 + 0.5;
                    let seen = camera.ray(centre(x), centre(y)).at(10.0);
                    let lit = camera.pixel_from_world() * (seen + 5.0 * light_travel).extend(1.0);
                    let image = [lit.x / lit.w, lit.y / lit.w];
                    let along = [image[0] - centre(x), image[1] - centre(y)];
                    let length = along[0].hypot(along[1]);
                    let along = [2.0 * along[0] / length, 2.0 * along[1] / length];
                    let across = lines.across(x, y, along);
                    assert!(across < 1e-6, "stride {stride} ({x}, {y}): {across}");
                    let normal = lines.across(x, y, [-along[1], along[0]]);
                    assert!((normal - 4.0).abs() < 1e-6, "{normal}");
                }
            }
        }
    }

    /// Lit bands at least three pixels wide along `lines`' direction, so that no pixel
    /// pair two pixels apart straddles one unseen: the layers are exact everywhere.
    #[test]
    fn shafts_along_the_epipolar_lines_are_kept_on_the_sparser_grid() {
        let (width, height) = (61, 47);
        let cases = [
            ("parallel, steep", EpipolarLines::through([1.0, 3.0, 0.0])),
            (
                "parallel, diagonal",
                EpipolarLines::through([1.0, -1.0, 0.0]),
            ),
            ("parallel, flat", EpipolarLines::through([4.0, -1.0, 0.0])),
            (
                "through a point above",
                EpipolarLines::through([25.0, -40.0, 1.0]),
            ),
            (
                "through a point beside",
                EpipolarLines::through([-180.0, 60.0, -2.0]),
            ),
        ];
        for (what, lines) in cases {
            let [ex, ey, ew] = lines.epipole;
            // A coordinate across the lines: the angle around the epipole, or the
            // distance across parallel lines, scaled to pixels at the image's centre.
            let across = |x: usize, y: usize| {
                let (px, py) = (x as f64, y as f64);
                if ew == 0.0 {
                    (px * ey - py * ex) / ex.hypot(ey)
                } else {
                    let (cx, cy) = (ex / ew - 30.0, ey / ew - 23.0);
                    (py - ey / ew).atan2(px - ex / ew) * cx.hypot(cy)
                }
            };
            let value = |x: usize, y: usize| {
                let lit = across(x, y).rem_euclid(11.0) < 3.5;
                let v = if lit { 1.0 } else { 0.25 };
                pixel(v, 0.4, if lit { 1.0 } else { 0.0 }, 20.0)
            };
            let surface = |_, _| Some(20.0);
            // Sizes of every parity, down to images with no coarse square at all.
            for (width, height) in [
                (width, height),
                (64, 32),
                (1, 1),
                (2, 3),
                (5, 2),
                (4, 4),
                (9, 13),
            ] {
                let (layers, shaded) =
                    shade_image(width, height, 0.01, Some(lines), surface, value);
                for y in 0..height {
                    for x in 0..width {
                        let want = value(x, y);
                        let got = layer_value(&layers, x, y);
                        assert_eq!(got, want, "{what} {width}×{height} ({x}, {y})");
                    }
                }
                let (_, finer) = shade_image(width, height, 0.01, None, surface, value);
                assert!(
                    shaded <= finer,
                    "{what} {width}×{height}: {shaded} against {finer}"
                );
                if width * height > 1000 {
                    assert!(
                        shaded < finer,
                        "{what}: {shaded} shaded, {finer} without the lines"
                    );
                }
            }
        }
    }

    #[test]
    fn batches_pushed_row_by_row_are_shaded_in_tile_order() {
        for width in [1, 15, 16, 17, 53] {
            let rows = 7;
            let wanted = |x: usize, row: usize| (x * 7 + row * 3) % 5 < 2;
            let mut batch = Batch::default();
            for row in 0..rows {
                for x in (0..width).filter(|&x| wanted(x, row)) {
                    batch.push(row * width + x, (x, row));
                }
            }
            let sorted = batch.in_tiles(width, |(x, _)| x);
            let mut expected = Vec::new();
            crate::render::for_each_in_tiles(width, rows, |x, row| {
                if wanted(x, row) {
                    expected.push((row * width + x, (x, row)));
                }
            });
            let got: Vec<_> = sorted.slots.into_iter().zip(sorted.pixels).collect();
            assert_eq!(got, expected, "width {width}");
        }
    }

    #[test]
    fn a_pairings_fractions_are_its_steps_over_the_stride_and_its_span_widens_the_tolerance() {
        for stride in 1..=MAX_STRIDE {
            let pairing = Pairing::of(&Lattice {
                step: [1, 2],
                stride,
                position: [1, 0],
            });
            for behind in 0..stride {
                assert_eq!(
                    pairing.fractions[behind as usize],
                    behind as f32 / stride as f32,
                    "{behind} of {stride}"
                );
            }
            assert_eq!(pairing.span, [2.0 * stride as f64, 4.0 * stride as f64]);
            let length = 2.0 * stride as f64 * 5f64.sqrt();
            assert_eq!(pairing.widening, (length / TOLERANCE_SPAN).max(1.0) as f32);
        }
    }

    #[test]
    fn lattice_offsets_wrap_like_the_euclidean_remainder() {
        for stride in 1..=MAX_STRIDE {
            let lattice = Lattice {
                stride,
                ..Lattice::EVERY_POINT
            };
            for steps in -50..50 {
                assert_eq!(
                    lattice.wrap(steps),
                    steps.rem_euclid(stride),
                    "{steps} % {stride}"
                );
            }
        }
    }

    #[test]
    fn lattices_pair_every_other_point_along_the_epipolar_line_through_it() {
        let candidates = Lattice::candidates();
        let mut strides = Vec::new();
        for degrees in 0..360 {
            let angle = (degrees as f64 + 0.3).to_radians();
            let direction = [angle.cos(), angle.sin()];
            let lattice = Lattice::along(&[direction; 4], &candidates);
            let [a, b] = lattice.step;
            assert_eq!(lattice.position[0] * a + lattice.position[1] * b, 1);
            strides.push(lattice.stride);
            // Every point off the lattice lies between two lattice points on its line,
            // at most MAX_ALONG apart and MAX_ACROSS across the epipolar line.
            let span = [
                2.0 * (lattice.stride * a) as f64,
                2.0 * (lattice.stride * b) as f64,
            ];
            assert!(span[0].hypot(span[1]) <= MAX_ALONG + 1e-9, "{degrees}°");
            let across = (direction[0] * span[1] - direction[1] * span[0]).abs();
            assert!(across <= MAX_ACROSS + 1e-9, "{degrees}°: {across}");
            for (i, j) in [(10usize, 20usize), (11, 20), (12, 23), (17, 31)] {
                let behind = lattice.offset(i, j);
                let ahead = lattice.stride - behind;
                let back = (
                    (i as i64 - behind * a) as usize,
                    (j as i64 - behind * b) as usize,
                );
                let front = (
                    (i as i64 + ahead * a) as usize,
                    (j as i64 + ahead * b) as usize,
                );
                assert_eq!(lattice.offset(back.0, back.1), 0, "{degrees}°");
                assert_eq!(lattice.offset(front.0, front.1), 0, "{degrees}°");
            }
        }
        // Along any direction at most half the finer grid is shaded first, a sixth along
        // the grid's axes (pairs 12 px apart) and a quarter along its diagonals (11.3 px).
        assert!(strides.iter().all(|&stride| stride >= 2), "{strides:?}");
        for degrees in [0, 90, 180, 270] {
            assert_eq!(strides[degrees], 6, "{degrees}°");
        }
        for degrees in [45, 135, 225, 315] {
            assert_eq!(strides[degrees], 4, "{degrees}°");
        }
        // Around an epipole inside the square, and without a direction, every point.
        let around = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];
        assert_eq!(Lattice::along(&around, &candidates), Lattice::EVERY_POINT);
        assert_eq!(
            Lattice::along(&[[0.0, 0.0]; 4], &candidates),
            Lattice::EVERY_POINT
        );
        assert_eq!(
            Lattice::along(&[[f64::NAN, 1.0]; 4], &candidates),
            Lattice::EVERY_POINT
        );
    }

    #[test]
    fn lattices_choose_among_the_short_steps_what_they_would_among_all() {
        // Every primitive step up to MAX_STEP, in the same order, none left out.
        let mut every_step = Vec::new();
        for a in -MAX_STEP..=MAX_STEP {
            for b in 0..=MAX_STEP {
                if b == 0 && a != 1 {
                    continue;
                }
                if let Some(position) = bezout([a, b]) {
                    every_step.push(LatticeStep {
                        step: [a, b],
                        position,
                        length: 2.0 * ((a * a + b * b) as f64).sqrt(),
                    });
                }
            }
        }
        let candidates = Lattice::candidates();
        assert!(candidates.len() < every_step.len());
        // Squares whose lines fan out by up to 20° from a direction, every 0.7°.
        for step in 0..520 {
            let angle = (step as f64 * 0.7).to_radians();
            for fan in [0.0f64, 2.0, 8.0, 20.0] {
                let corners: [[f64; 2]; 4] = std::array::from_fn(|k| {
                    let turned = angle + (k as f64 / 3.0 - 0.5) * fan.to_radians();
                    [3.0 * turned.cos(), 3.0 * turned.sin()]
                });
                assert_eq!(
                    Lattice::along(&corners, &candidates),
                    Lattice::along(&corners, &every_step),
                    "{angle} rad, fan {fan}°"
                );
            }
        }
    }

    /// Along the lines the tolerance bounds the gradient: a pair twice as far apart may
    /// differ twice as much ([`TOLERANCE_SPAN`]).
    #[test]
    fn along_the_lines_the_tolerance_bounds_the_gradient() {
        let (width, height) = (128, 64);
        let lines = EpipolarLines::through([1.0, 0.0, 0.0]);
        let surface = |_, _| Some(20.0);
        let shaded_with = |per_pixel: f32| {
            let value = |x: usize, _: usize| pixel((per_pixel * x as f32).exp(), 0.4, 0.5, 20.0);
            let (layers, shaded) = shade_image(width, height, 0.01, Some(lines), surface, value);
            for y in 0..height {
                for x in 0..width {
                    let (got, want) = (layer_value(&layers, x, y), value(x, y));
                    for (got, want) in got.volume.iter().zip(want.volume) {
                        assert!((got - want).abs() <= 1e-4 * want, "({x}, {y})");
                    }
                }
            }
            shaded
        };
        let flat = shaded_with(0.0);
        // Growing by 1.4% over the lattice's eight pixels along the rows (0.7% over four):
        // shaded as a flat image is.
        assert_eq!(shaded_with(0.0018), flat);
        // By 2.4% over eight (1.2% over four): every point of the finer grid is shaded.
        let steep = shaded_with(0.003);
        let finer = width.div_ceil(2) * height.div_ceil(2);
        assert!(flat < finer / 2, "{flat} of {finer}");
        assert!(steep >= finer, "{steep} of {finer}");
    }

    #[test]
    fn depth_edges_across_the_epipolar_lines_are_shaded() {
        let (width, height) = (40, 30);
        // Lines running down the image; a wire one pixel thick across them at y = 13, a
        // pole one pixel wide at x = 11, and a nearer object at y ≥ 21.
        let lines = EpipolarLines::through([0.0, 1.0, 0.0]);
        let depth = |x: usize, y: usize| match (x, y) {
            (_, 13) => 6.0,
            (11, _) => 8.0,
            (_, 21..) => 5.0,
            _ => 20.0,
        };
        let value = |x: usize, y: usize| {
            let lit = (20..23).contains(&x);
            let v = if lit { 1.0 } else { 0.2 } * depth(x, y) as f32 / 20.0;
            pixel(v, 0.3, if lit { 1.0 } else { 0.0 }, depth(x, y) as f32)
        };
        let surface = |x, y| Some(depth(x, y));
        let (layers, shaded) = shade_image(width, height, 0.01, Some(lines), surface, value);
        for y in 0..height {
            for x in 0..width {
                assert_eq!(layer_value(&layers, x, y), value(x, y), "({x}, {y})");
            }
        }
        let (_, finer) = shade_image(width, height, 0.01, None, surface, value);
        assert!(shaded < finer, "{shaded} shaded, {finer} without the lines");
    }

    /// Neighbours far darker than the image's mean may spread by the tolerance of a share
    /// of the mean: a ripple there is interpolated, the same ripple relative to a bright
    /// region is shaded, and features in the dark (a shaft, a depth edge) still are.
    #[test]
    fn dark_ripples_are_interpolated_but_dark_features_are_shaded() {
        let (width, height) = (64, 48);
        let depth = |x: usize, y: usize| if x == 45 && y > 30 { 8.0 } else { 20.0 };
        // Bright left, dark right (1/100), each with a ripple of ±3% of its own level; a
        // shaft of 0.3 two pixels wide at x = 50..52 in the dark half.
        let level = |x: usize, y: usize| match x {
            0..32 => 1.0,
            50..52 => 0.3,
            _ => 0.01 * (20.0 / depth(x, y) as f32),
        };
        let value = |x: usize, y: usize| {
            let ripple = 1.0 + 0.03 * ((x * 7 + y * 3) % 5) as f32 / 4.0;
            pixel(level(x, y) * ripple, 0.3, 0.5, depth(x, y) as f32)
        };
        let shaded = std::sync::Mutex::new(std::collections::HashSet::new());
        let recorded = |x: usize, y: usize| {
            shaded.lock().unwrap().insert((x, y));
            value(x, y)
        };
        let (layers, _) = shade_image(
            width,
            height,
            0.01,
            None,
            |x, y| Some(depth(x, y)),
            recorded,
        );
        let shaded = shaded.into_inner().unwrap();
        let share = |columns: std::ops::Range<usize>| {
            let count = columns.len() * height;
            let hit = shaded.iter().filter(|(x, _)| columns.contains(x)).count();
            hit as f64 / count as f64
        };
        // The finer grid, every other pixel of every other row, is a quarter; the
        // ripple leaves some neighbours agreeing.
        assert!(share(0..31) > 0.5, "bright ripple: {}", share(0..31));
        assert!(share(34..44) < 0.3, "dark ripple: {}", share(34..44));
        for y in 0..height {
            // Nothing is blended across the shaft's edges.
            for x in 48..54 {
                let (got, want) = (layer_value(&layers, x, y).volume[0], value(x, y).volume[0]);
                assert!(
                    (got - want).abs() <= 0.03 * want,
                    "shaft ({x}, {y}): {got} against {want}"
                );
            }
            // The pole one pixel wide keeps its own depth and light.
            let (got, want) = (layer_value(&layers, 45, y), value(45, y));
            assert_eq!(got.depth, want.depth, "pole (45, {y})");
        }
        // Interpolated dark pixels stay within the ripple and the floor's tolerance: the
        // mean is about half of the bright level.
        for y in 0..height {
            for x in (33..width).filter(|x| !(48..54).contains(x)) {
                let (got, want) = (layer_value(&layers, x, y).volume[0], value(x, y).volume[0]);
                assert!(
                    (got - want).abs() <= 0.03 * 0.01 + 0.01 * DARK_SHARE as f32 * 0.6,
                    "({x}, {y}): {got} against {want}"
                );
            }
        }
    }

    /// `value` shaded adaptively on a 40 × 30 image at one depth, exact everywhere;
    /// returns the pixels shaded.
    fn shaded_pixels(
        lines: Option<EpipolarLines>,
        value: impl Fn(usize, usize) -> Pixel + Sync,
    ) -> std::collections::HashSet<(usize, usize)> {
        let (width, height) = (40, 30);
        let shaded = std::sync::Mutex::new(std::collections::HashSet::new());
        let recorded = |x: usize, y: usize| {
            shaded.lock().unwrap().insert((x, y));
            value(x, y)
        };
        let (layers, count) = shade_image(width, height, 0.01, lines, |_, _| Some(20.0), recorded);
        for y in 0..height {
            for x in 0..width {
                assert_eq!(layer_value(&layers, x, y), value(x, y), "({x}, {y})");
            }
        }
        let shaded = shaded.into_inner().unwrap();
        assert_eq!(shaded.len(), count);
        shaded
    }

    #[test]
    fn pixels_between_disagreeing_neighbours_take_the_centres_the_other_way() {
        // A shaft two pixels wide: the pixels of its left column on even rows lie between
        // a dark and a lit point of the finer grid, and between two centres, shaded,
        // that agree.
        let value = |x: usize, _: usize| {
            let lit = (21..23).contains(&x);
            pixel(
                if lit { 1.0 } else { 0.2 },
                0.3,
                f32::from(u8::from(lit)),
                20.0,
            )
        };
        for lines in [None, Some(EpipolarLines::through([0.0, 1.0, 0.0]))] {
            let shaded = shaded_pixels(lines, value);
            for y in (1..29).step_by(2) {
                assert!(shaded.contains(&(21, y)), "{lines:?}: centre (21, {y})");
                assert!(!shaded.contains(&(21, y + 1)), "{lines:?}: (21, {})", y + 1);
            }
        }
    }

    #[test]
    fn centres_on_edges_along_the_epipolar_lines_take_the_diagonal_along_them() {
        // A shaft along the image's diagonal, four pixels wide across the rows.
        let value = |x: usize, y: usize| {
            let lit = (0..4).contains(&(x as i64 - y as i64));
            pixel(
                if lit { 1.0 } else { 0.2 },
                0.3,
                f32::from(u8::from(lit)),
                20.0,
            )
        };
        let along = shaded_pixels(Some(EpipolarLines::through([1.0, 1.0, 0.0])), value);
        let without = shaded_pixels(None, value);
        // On its edges, the centres (odd x and y) whose four corners disagree.
        let edges = (1..29usize)
            .step_by(2)
            .flat_map(|y| [y.checked_sub(2), Some(y), Some(y + 2), Some(y + 4)].map(|x| (x, y)))
            .filter_map(|(x, y)| Some((x?, y)))
            .filter(|&(x, _)| x < 39)
            .collect::<Vec<_>>();
        for centre in edges {
            assert!(!along.contains(&centre), "{centre:?} along the lines");
            assert!(without.contains(&centre), "{centre:?} without the lines");
        }
    }
}
