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
//! is found in two steps. In each square of the finer grid, a sublattice of its points
//! whose cells are long along the square's epipolar lines and thin across them is
//! shaded first; each other point lies in a triangle of those (or on a side of one) and
//! is interpolated from its corners where they lie along the epipolar line through it,
//! closely enough to resolve shafts no worse than the finer grid would. The pixels
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
use crate::error::{Result, Sizing};
use crate::layers::{Layers, Pixel};
use crate::render::{layer_depth, Stopwatch, EDGE_DEPTH_SPREAD, SHADING_TILE as TILE};
use crate::spare::Spare;

/// The default tolerance: neighbours whose radiance spreads by at most 1% of its mean
/// (or, in regions darker than a quarter of the image's mean, of that quarter) are
/// interpolated, and so are pairs that spread more on a smooth ramp with the points beyond.
/// On the built-in scenes' default views at 1920×1080 this shades 5.5–12% of the pixels
/// (min-max 5.5–14%) and moves the layers from shading every pixel by at most 0.040% of
/// the mean radiance (prefiltering; 0.085% for min-max).
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
    /// is `expected` ([`Agreement::blend`]): within [`EDGE_DEPTH_SPREAD`] of it. Without
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
        self.spans_along(x, y, [span])
    }

    /// Whether pixels around (`x`, `y`), one of them and the others `spans` from it, lie
    /// within [`MAX_ACROSS`] across the epipolar line through it: never at the epipole.
    #[inline]
    fn spans_along<const N: usize>(&self, x: usize, y: usize, spans: [[f64; 2]; N]) -> bool {
        let [dx, dy] = self.direction(x, y);
        // Distances across the line, times the direction's length.
        let (mut low, mut high) = (0.0f64, 0.0f64);
        for span in spans {
            let cross = dx * span[1] - dy * span[0];
            low = low.min(cross);
            high = high.max(cross);
        }
        let spread = high - low;
        let length_squared = dx * dx + dy * dy;
        length_squared > 1e-24 && spread * spread <= MAX_ACROSS * MAX_ACROSS * length_squared
    }

    /// Of the pairs of pixels at ±(a, b) from pixel (`x`, `y`), (a, b) among `offsets`,
    /// the one most nearly along the epipolar line through it, where it lies within
    /// [`MAX_ACROSS`] across and more nearly along than any pair of `tried`.
    fn offset_along(
        &self,
        x: usize,
        y: usize,
        offsets: &[[i64; 2]],
        tried: &[[i64; 2]],
    ) -> Option<[i64; 2]> {
        let [dx, dy] = self.direction(x, y);
        // The squared sine of each pair's angle to the line, times the direction's squared
        // length, as a fraction: compared by cross-multiplying, without a division.
        let across = |[a, b]: [i64; 2]| {
            let cross = dx * b as f64 - dy * a as f64;
            (cross * cross, (a * a + b * b) as f64)
        };
        let nearer =
            |(p, p_length): (f64, f64), (q, q_length): (f64, f64)| p * q_length < q * p_length;
        let mut best: Option<([i64; 2], (f64, f64))> = None;
        for &offset in offsets {
            let this = across(offset);
            if best.is_none_or(|(_, other)| nearer(this, other)) {
                best = Some((offset, this));
            }
        }
        let (offset, best_across) = best?;
        if !tried.iter().all(|&pair| nearer(best_across, across(pair))) {
            return None;
        }
        let [a, b] = offset;
        self.pairs_along(x, y, [2.0 * a as f64, 2.0 * b as f64])
            .then_some(offset)
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
    agreement: Agreement,
    surface: &'s S,
}

impl<S: Fn(usize, usize) -> Option<f64>> Interpolation<'_, S> {
    /// Pixel (x, y) as the blend of `neighbours` by `weights` ([`Agreement::blend`]),
    /// where it lies on their surface.
    #[inline(always)]
    fn between<const N: usize>(
        &self,
        neighbours: [Pixel; N],
        weights: [f32; N],
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        let blend = self.agreement.blend(neighbours, weights)?;
        self.on_surface(blend, x, y)
    }

    /// Pixel (x, y) as `blend`, where its own ray ends on the surface the blend's do.
    #[inline(always)]
    fn on_surface(&self, blend: Blend, x: usize, y: usize) -> Option<Pixel> {
        let Agreement {
            max_distance,
            coordinate,
            ..
        } = self.agreement;
        let surface = (self.surface)(x, y)?;
        let reach = surface.min(max_distance as f64) as f32;
        if !coordinate.holds(blend.coordinate, reach) {
            return None;
        }
        Some(Pixel {
            volume: blend.volume,
            visibility: blend.visibility,
            depth: layer_depth(surface, max_distance as f64) as f32,
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

    /// Pixel (x, y) as the blend of `corners` by `weights`, which lie along the epipolar
    /// line through it: the tolerance `widening`-fold ([`TOLERANCE_SPAN`]).
    #[inline]
    fn along<const N: usize>(
        &self,
        corners: [Pixel; N],
        weights: [f32; N],
        widening: f32,
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        let wider = Interpolation {
            agreement: Agreement {
                tolerance: self.agreement.tolerance * widening,
                ..self.agreement
            },
            ..*self
        };
        wider.between(corners, weights, x, y)
    }

    /// Pixel (x, y) as the mean of the middle two of `points`, four in a row at even
    /// steps with the pixel midway, where the four lie on a smooth ramp
    /// ([`Agreement::blend_on_ramp`]) and it lies on their surface; `None` where a point
    /// is missing.
    #[inline]
    fn on_ramp(&self, points: [Option<Pixel>; 4], x: usize, y: usize) -> Option<Pixel> {
        let [Some(before), Some(first), Some(second), Some(after)] = points else {
            return None;
        };
        let blend = self
            .agreement
            .blend_on_ramp([before, first, second, after])?;
        self.on_surface(blend, x, y)
    }

    /// Pixel (x, y) as the mean of `pair`, at ∓`offset` from it along the epipolar line
    /// through it ([`Interpolation::along`]).
    #[inline]
    fn midway_along(
        &self,
        pair: [Pixel; 2],
        [a, b]: [i64; 2],
        x: usize,
        y: usize,
    ) -> Option<Pixel> {
        let span = 2.0 * ((a * a + b * b) as f64).sqrt();
        let widening = (span / TOLERANCE_SPAN).max(1.0) as f32;
        self.along(pair, [0.5, 0.5], widening, x, y)
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

static SPARE_EVEN_BANDS: Spare<Pixel> = Spare::new(Sizing::Image);
static SPARE_ODD_BANDS: Spare<Pixel> = Spare::new(Sizing::Image);

/// Lets go of the finer grid's and the band edges' kept buffers ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_EVEN_BANDS.clear();
    SPARE_ODD_BANDS.clear();
    SPARE_BAND_EDGES.clear();
}

impl FinerGrid {
    fn new(width: usize, height: usize) -> Result<Self> {
        let band_len = TILE * width;
        let count = height.div_ceil(TILE);
        // Only the last band can be short, and it is the last of its parity.
        let rows_of = |parity: usize| {
            (parity..count)
                .step_by(2)
                .map(|band| TILE.min(height - band * TILE))
                .sum::<usize>()
        };
        let what = || format!("adaptive shading's grid of {width}×{height} points");
        Ok(Self {
            width,
            band_len,
            parities: [
                SPARE_EVEN_BANDS.try_take(rows_of(0) * width, what)?,
                SPARE_ODD_BANDS.try_take(rows_of(1) * width, what)?,
            ],
        })
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

static SPARE_BAND_EDGES: Spare<Pixel> = Spare::new(Sizing::Image);

impl BandEdges {
    fn new(len: usize) -> Result<Self> {
        Ok(Self {
            values: SPARE_BAND_EDGES.try_take(len, || {
                format!("adaptive shading's band edges ({len} pixels)")
            })?,
        })
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

/// The most points of the finer grid one lattice point may stand for, so that at best one
/// in this many is shaded: along the grid's axes six, pairs [`MAX_ALONG`] apart, and
/// along its diagonals four. (At most four shaded 21% more of plane's pixels, whose lines
/// run down the image; eight, with pairs 16 px apart, took as long on tree and moved the
/// layers twice as far from every pixel shaded.)
const MAX_INDEX: i64 = 6;

/// The largest component of a step of the lattices whose points all lie on lines along
/// one step ([`LatticeCandidate::collinear`]).
const MAX_STEP: i64 = 3;

/// The longest a pair, or a triangle's side, may span, in pixels.
const MAX_ALONG: f64 = 12.0;

/// Side of the squares of the finer grid that share one [`Lattice`], in its points.
const LATTICE_TILE: usize = 8;

/// The points of the finer grid shaded first in a square of it: a sublattice of the grid
/// with basis `u`, `v` (in its points), each of whose points stands for `index` =
/// det(u, v) points of the grid. Every other point p = o + m·u + n·v, with o a lattice
/// point and 0 ≤ m, n < 1, lies in one of its cell's triangles, (o, o + u, o + v) or
/// (o + u + v, o + v, o + u), and is interpolated from its corners, or from the two on
/// whose side it lies. `u` runs close to the square's epipolar lines, so that a triangle
/// spans at most [`MAX_ALONG`] and lies within [`MAX_ACROSS`] across the lines: at that
/// width, a shaft that covers a point covers a corner. Where `u` is `index` times a step
/// of the grid, every point lies on a line along `u` between two lattice points. An index
/// of 1 shades every point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Lattice {
    u: [i64; 2],
    v: [i64; 2],
    index: i64,
}

impl Lattice {
    const EVERY_POINT: Lattice = Lattice {
        u: [1, 0],
        v: [0, 1],
        index: 1,
    };

    /// Point (i, j) as index·(m, n) modulo the index ([`Lattice`]): [0, 0] for the
    /// lattice's own points. (index·m = det(p, v) and index·n = det(u, p).)
    #[inline]
    fn residues(&self, i: usize, j: usize) -> [i64; 2] {
        let (i, j) = (i as i64, j as i64);
        let [u, v] = [self.u, self.v];
        [
            self.wrap(i * v[1] - j * v[0]),
            self.wrap(u[0] * j - u[1] * i),
        ]
    }

    /// `value`, a multiple of the index, over the index.
    #[inline]
    fn divide(&self, value: i64) -> i64 {
        // Constant divisors, as in `wrap`.
        match self.index {
            1 => value,
            2 => value / 2,
            3 => value / 3,
            4 => value / 4,
            5 => value / 5,
            6 => value / 6,
            index => value / index,
        }
    }

    /// `value` modulo the index, in [0, index).
    #[inline]
    fn wrap(&self, value: i64) -> i64 {
        // Indices are at most MAX_INDEX: constant divisors rather than a division by a
        // variable, which took a tenth of completing the finer grid.
        match self.index {
            1 => 0,
            2 => value.rem_euclid(2),
            3 => value.rem_euclid(3),
            4 => value.rem_euclid(4),
            5 => value.rem_euclid(5),
            6 => value.rem_euclid(6),
            index => value.rem_euclid(index),
        }
    }

    /// [`LatticeChoice::first_fitting`]'s lattice, or every point where none fits.
    #[cfg(test)]
    fn along(directions: &[[f64; 2]; 4], choice: &LatticeChoice) -> Self {
        choice
            .first_fitting(directions)
            .map_or(Self::EVERY_POINT, |candidate| candidate.lattice)
    }
}

/// `directions` normalized, `None` where one has no direction.
fn unit_directions(directions: &[[f64; 2]; 4]) -> Option<[[f64; 2]; 4]> {
    let mut units = [[0.0; 2]; 4];
    for (unit, &[dx, dy]) in units.iter_mut().zip(directions) {
        let norm = dx.hypot(dy);
        if !(norm > 1e-12 && norm.is_finite()) {
            return None;
        }
        *unit = [dx / norm, dy / norm];
    }
    Some(units)
}

/// A lattice a square may take, with its basis in pixels.
#[derive(Clone, Copy, Debug)]
struct LatticeCandidate {
    lattice: Lattice,
    u: [f64; 2],
    v: [f64; 2],
    /// Whether `u` is `index` steps of the grid, so that every point lies on a line along
    /// it and only `u` need run along the epipolar lines (then n = 0 everywhere).
    collinear: bool,
    /// The longest pair a point is interpolated from, in pixels: `u`, or a triangle's
    /// longest side.
    span: f64,
}

impl LatticeCandidate {
    fn new(lattice: Lattice) -> Self {
        let collinear = lattice.u.iter().all(|c| c % lattice.index == 0);
        let pixels = |[a, b]: [i64; 2]| [2.0 * a as f64, 2.0 * b as f64];
        let (u, v) = (pixels(lattice.u), pixels(lattice.v));
        let length = |[a, b]: [f64; 2]| a.hypot(b);
        let span = if collinear {
            length(u)
        } else {
            length(u)
                .max(length(v))
                .max(length([u[0] - v[0], u[1] - v[1]]))
        };
        Self {
            lattice,
            u,
            v,
            collinear,
            span,
        }
    }

    /// Whether the lattice's pairs and triangles lie within [`MAX_ACROSS`] across lines
    /// along each of the unit `directions`.
    #[inline]
    fn fits(&self, directions: &[[f64; 2]]) -> bool {
        self.fits_within(directions, MAX_ACROSS)
    }

    #[inline]
    fn fits_within(&self, directions: &[[f64; 2]], most_across: f64) -> bool {
        directions.iter().all(|&[dx, dy]| {
            let across_u = dx * self.u[1] - dy * self.u[0];
            if self.collinear {
                return across_u.abs() <= most_across;
            }
            let across_v = dx * self.v[1] - dy * self.v[0];
            across_u.max(across_v).max(0.0) - across_u.min(across_v).min(0.0) <= most_across
        })
    }

    /// Every lattice a square may take, sparsest first; among equals collinear ones
    /// (whose points need only a pair to agree), then the shortest span.
    fn all() -> Vec<Self> {
        let mut candidates = Vec::new();
        // Lines along a primitive step, every `index`-th point on them: v completes the
        // step's Bézout coefficients, so that m counts steps along the line.
        for a in -MAX_STEP..=MAX_STEP {
            for b in 0..=MAX_STEP {
                // (−1, 0) is (1, 0) the other way round.
                if b == 0 && a != 1 {
                    continue;
                }
                let Some([c, d]) = bezout([a, b]) else {
                    continue;
                };
                for index in 2..=MAX_INDEX {
                    let lattice = Lattice {
                        u: [index * a, index * b],
                        v: [-d, c],
                        index,
                    };
                    let candidate = Self::new(lattice);
                    if candidate.span <= MAX_ALONG {
                        candidates.push(candidate);
                    }
                }
            }
        }
        // Every other sublattice of index up to MAX_INDEX (in Hermite normal form, the
        // columns (a, 0) and (b, d) with a·d = index and 0 ≤ b < a), in every basis whose
        // triangles are short enough: one of each ± pair.
        let reach = (MAX_ALONG / 2.0) as i64;
        for index in 2..=MAX_INDEX {
            for a in (1..=index).filter(|a| index % a == 0) {
                let d = index / a;
                for b in 0..a {
                    let mut vectors = Vec::new();
                    for m in -reach..=reach {
                        for n in -reach..=reach {
                            let vector = [m * a + n * b, n * d];
                            let [x, y] = vector;
                            if vector != [0, 0] && 2.0 * (x as f64).hypot(y as f64) <= MAX_ALONG {
                                vectors.push(vector);
                            }
                        }
                    }
                    for &u in vectors
                        .iter()
                        .filter(|u| u[0] > 0 || (u[0] == 0 && u[1] > 0))
                    {
                        for &v in &vectors {
                            if u[0] * v[1] - u[1] * v[0] != index {
                                continue;
                            }
                            let candidate = Self::new(Lattice { u, v, index });
                            if !candidate.collinear && candidate.span <= MAX_ALONG {
                                candidates.push(candidate);
                            }
                        }
                    }
                }
            }
        }
        candidates.sort_by(|p, q| {
            (q.lattice.index, q.collinear)
                .cmp(&(p.lattice.index, p.collinear))
                .then(p.span.total_cmp(&q.span))
        });
        candidates
    }
}

/// How many bins of the epipolar lines' angle (modulo π) [`LatticeChoice`] keeps.
const DIRECTION_BINS: usize = 720;

/// The candidate lattices ([`LatticeCandidate::all`]) and, for each bin of direction, the
/// ones that fit some direction in it, in order of preference: a square tests only those
/// of its first corner's bin. Found once per process.
struct LatticeChoice {
    candidates: Vec<LatticeCandidate>,
    starts: Vec<usize>,
    fitting: Vec<u32>,
}

impl LatticeChoice {
    fn get() -> &'static Self {
        static CHOICE: std::sync::OnceLock<LatticeChoice> = std::sync::OnceLock::new();
        CHOICE.get_or_init(Self::new)
    }

    fn new() -> Self {
        let candidates = LatticeCandidate::all();
        // Each bin's edges and points between, with room for how far a pair or triangle
        // no longer than MAX_ALONG turns across the lines between them, so that every
        // lattice that fits a direction in the bin is kept.
        const SAMPLES: usize = 4;
        let between = std::f64::consts::PI / (DIRECTION_BINS * SAMPLES) as f64;
        let most_across = MAX_ACROSS + MAX_ALONG * between;
        let per_bin: Vec<Vec<u32>> = (0..DIRECTION_BINS)
            .into_par_iter()
            .map(|bin| {
                let directions: Vec<[f64; 2]> = (0..=SAMPLES)
                    .map(|k| {
                        let angle = (bin as f64 + k as f64 / SAMPLES as f64) * std::f64::consts::PI
                            / DIRECTION_BINS as f64;
                        [angle.cos(), angle.sin()]
                    })
                    .collect();
                (0..candidates.len() as u32)
                    .filter(|&k| {
                        let candidate = &candidates[k as usize];
                        directions.iter().any(|direction| {
                            candidate.fits_within(std::slice::from_ref(direction), most_across)
                        })
                    })
                    .collect()
            })
            .collect();
        let mut starts = vec![0];
        let mut fitting = Vec::new();
        for bin in per_bin {
            fitting.extend(bin);
            starts.push(fitting.len());
        }
        Self {
            candidates,
            starts,
            fitting,
        }
    }

    /// The sparsest candidate for a square whose epipolar lines run along `directions`
    /// (in pixels, at its corners: around an epipole off the square the extremes lie
    /// there), first in order of preference among equally sparse ones; `None` where none
    /// fits (or a corner has no direction), and every point is shaded.
    fn first_fitting(&self, directions: &[[f64; 2]; 4]) -> Option<&LatticeCandidate> {
        let units = unit_directions(directions)?;
        self.fitting(units[0])
            .iter()
            .map(|&k| &self.candidates[k as usize])
            .find(|candidate| candidate.fits(&units))
    }

    /// The candidates that fit some direction in `unit`'s bin, in order of preference.
    fn fitting(&self, [dx, dy]: [f64; 2]) -> &[u32] {
        let angle = dy.atan2(dx).rem_euclid(std::f64::consts::PI);
        let bin = ((angle / std::f64::consts::PI * DIRECTION_BINS as f64) as usize)
            .min(DIRECTION_BINS - 1);
        &self.fitting[self.starts[bin]..self.starts[bin + 1]]
    }
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

/// What the points of a [`Lattice`]'s square have in common, found once per square
/// rather than once per point.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Pairing {
    /// `u` and `v` in pixels.
    u: [f64; 2],
    v: [f64; 2],
    /// The tolerance's factor for the lattice's longest pairs ([`TOLERANCE_SPAN`]).
    widening: f32,
    /// k / index, for the weights of a point whose residues are k.
    fractions: [f32; MAX_INDEX as usize],
}

impl Pairing {
    fn of(candidate: &LatticeCandidate) -> Self {
        let index = candidate.lattice.index;
        Self {
            u: candidate.u,
            v: candidate.v,
            widening: (candidate.span / TOLERANCE_SPAN).max(1.0) as f32,
            fractions: std::array::from_fn(|k| k as f32 / index as f32),
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
        let choice = lines.map(|_| LatticeChoice::get());
        let every_point = (
            Lattice::EVERY_POINT,
            Pairing::of(&LatticeCandidate::new(Lattice::EVERY_POINT)),
        );
        let (squares, pairings) = (0..down * across)
            .into_par_iter()
            .map(|square| {
                let (Some(lines), Some(choice)) = (lines, choice) else {
                    return every_point;
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
                choice
                    .first_fitting(&corners)
                    .map_or(every_point, |candidate| {
                        (candidate.lattice, Pairing::of(candidate))
                    })
            })
            .unzip();
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
        self.at(i, j).residues(i, j) == [0, 0]
    }

    /// Calls `visit(i, square, residues)` for the points `columns` of row `j` with their
    /// square and [`Lattice::residues`], found by adding rather than dividing.
    #[inline]
    fn residues_in_row(
        &self,
        columns: std::ops::Range<usize>,
        j: usize,
        mut visit: impl FnMut(usize, usize, [i64; 2]),
    ) {
        let mut i = columns.start;
        while i < columns.end {
            let square = self.square(i, j);
            let lattice = &self.squares[square];
            let index = lattice.index;
            let advance = [lattice.wrap(lattice.v[1]), lattice.wrap(-lattice.u[1])];
            let mut residues = lattice.residues(i, j);
            let square_end = ((i / LATTICE_TILE + 1) * LATTICE_TILE).min(columns.end);
            for i in i..square_end {
                visit(i, square, residues);
                for (residue, advance) in residues.iter_mut().zip(advance) {
                    *residue += advance;
                    if *residue >= index {
                        *residue -= index;
                    }
                }
            }
            i = square_end;
        }
    }
}

/// A band of the finer grid being completed, and the bands either side of it. (A method
/// inlined always: as a closure it was called, which cost a sixth of completing the
/// finer grid.)
struct BandView<'a> {
    lattices: &'a Lattices,
    beside: &'a [Pixel],
    band: usize,
    band_len: usize,
    grid_width: usize,
    grid_height: usize,
}

impl BandView<'_> {
    /// Lattice point (i, j), `None` off the grid or where (i, j) is none; the square
    /// `home`'s own lattice points need no test. `pixels` is the band's own.
    #[inline(always)]
    fn lattice_point(&self, pixels: &[Pixel], i: i64, j: i64, home: usize) -> Option<Pixel> {
        let (i, j) = (usize::try_from(i).ok()?, usize::try_from(j).ok()?);
        if i >= self.grid_width || j >= self.grid_height {
            return None;
        }
        if self.lattices.square(i, j) != home && !self.lattices.contains(i, j) {
            return None;
        }
        let at = j % TILE * self.grid_width + i;
        Some(match j / TILE {
            b if b == self.band => pixels[at],
            b => self.beside[b / 2 * self.band_len + at],
        })
    }
}

/// Where [`shade_adaptively`]'s time went, in seconds, and how many points each pass
/// shaded: its first pass (the lattice points, all shaded), its second (the rest of the
/// finer grid, interpolated along the epipolar lines or shaded) and its last (the pixels
/// between the finer grid's points, the centres of its squares first).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AdaptivePasses {
    pub lattice: f64,
    pub finer_grid: f64,
    pub between: f64,
    pub lattice_shaded: usize,
    pub finer_grid_shaded: usize,
    pub between_shaded: usize,
}

impl AdaptivePasses {
    /// Adds another frame pass's (`crate::channels`).
    pub(crate) fn accumulate(&mut self, other: &AdaptivePasses) {
        self.lattice += other.lattice;
        self.finer_grid += other.finer_grid;
        self.between += other.between;
        self.lattice_shaded += other.lattice_shaded;
        self.finer_grid_shaded += other.finer_grid_shaded;
        self.between_shaded += other.between_shaded;
    }
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
) -> Result<(Layers, usize, AdaptivePasses)> {
    let mut stopwatch = Stopwatch::start();
    let lines = lines.as_ref();
    let grid_width = width.div_ceil(2);
    let grid_height = height.div_ceil(2);
    let lattices = Lattices::of_grid(grid_width, grid_height, lines);
    let shaded_count = AtomicUsize::new(0);
    let mut grid = FinerGrid::new(grid_width, grid_height)?;
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
                    lattices.residues_in_row(columns, first + row, |i, _, residues| {
                        if residues == [0, 0] {
                            batch.push(row * grid_width + i, (2 * i, 2 * (first + row)));
                        }
                    });
                }
            }
            shaded_count.fetch_add(batch.shade(&shade, pixels), Ordering::Relaxed);
            // Each lattice point stands for `index` points of the finer grid.
            let (mut sums, mut points) = ([0.0; 4], 0);
            for &slot in &batch.slots {
                let (i, j) = (slot % grid_width, first + slot / grid_width);
                let index = lattices.at(i, j).index;
                for (sum, value) in sums.iter_mut().zip(pixels[slot].volume) {
                    *sum += index as f64 * value as f64;
                }
                points += index as usize;
            }
            (sums, points)
        })
        .reduce(
            || ([0.0; 4], 0),
            |(a, n), (b, m)| (std::array::from_fn(|k| a[k] + b[k]), n + m),
        );
    let lattice = stopwatch.lap();
    let lattice_shaded = shaded_count.load(Ordering::Relaxed);
    let floor = sums.map(|sum| (DARK_SHARE * sum / points.max(1) as f64) as f32);
    let interpolation = Interpolation {
        agreement: Agreement {
            tolerance,
            floor,
            max_distance,
            coordinate,
        },
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
                let view = BandView {
                    lattices: &lattices,
                    beside,
                    band,
                    band_len,
                    grid_width,
                    grid_height,
                };
                // Point (i, j) of square `home`, with `residues` [m, n] (index·(m, n) in
                // its cell, modulo the index): from the corners of the triangle of its
                // cell it lies in, or of the side it lies on, where they lie along the
                // epipolar line through it ([`MAX_ACROSS`]), agree and see its surface.
                let interpolated = |pixels: &[Pixel], i, j, home: usize, [m, n]: [i64; 2]| {
                    let lattice = &lattices.squares[home];
                    let Lattice { u, v, index } = *lattice;
                    let pairing = &lattices.pairings[home];
                    // The cell's first corner: p less (m·u + n·v) / index, a point of the
                    // grid.
                    let o = [
                        i as i64 - lattice.divide(m * u[0] + n * v[0]),
                        j as i64 - lattice.divide(m * u[1] + n * v[1]),
                    ];
                    let corner = |[a, b]: [i64; 2]| {
                        let (ci, cj) = (o[0] + a * u[0] + b * v[0], o[1] + a * u[1] + b * v[1]);
                        view.lattice_point(pixels, ci, cj, home)
                    };
                    let lines = lines?;
                    let (x, y) = (2 * i, 2 * j);
                    let [fm, fn_] = [pairing.fractions[m as usize], pairing.fractions[n as usize]];
                    let [pu, pv] = [pairing.u, pairing.v];
                    let widening = pairing.widening;
                    if n == 0 {
                        let pair = [corner([0, 0])?, corner([1, 0])?];
                        if !lines.spans_along(x, y, [pu]) {
                            return None;
                        }
                        interpolation.along(pair, [1.0 - fm, fm], widening, x, y)
                    } else if m == 0 {
                        let pair = [corner([0, 0])?, corner([0, 1])?];
                        if !lines.spans_along(x, y, [pv]) {
                            return None;
                        }
                        interpolation.along(pair, [1.0 - fn_, fn_], widening, x, y)
                    } else if m + n == index {
                        let pair = [corner([1, 0])?, corner([0, 1])?];
                        if !lines.spans_along(x, y, [[pv[0] - pu[0], pv[1] - pu[1]]]) {
                            return None;
                        }
                        interpolation.along(pair, [fm, fn_], widening, x, y)
                    } else if m + n < index {
                        let triangle = [corner([0, 0])?, corner([1, 0])?, corner([0, 1])?];
                        if !lines.spans_along(x, y, [pu, pv]) {
                            return None;
                        }
                        let weights = [1.0 - fm - fn_, fm, fn_];
                        interpolation.along(triangle, weights, widening, x, y)
                    } else {
                        let triangle = [corner([1, 1])?, corner([0, 1])?, corner([1, 0])?];
                        if !lines.spans_along(x, y, [pu, pv]) {
                            return None;
                        }
                        let weights = [fm + fn_ - 1.0, 1.0 - fm, 1.0 - fn_];
                        interpolation.along(triangle, weights, widening, x, y)
                    }
                };
                let mut batch = Batch::default();
                for row in 0..rows {
                    let j = first + row;
                    lattices.residues_in_row(0..grid_width, j, |i, home, residues| {
                        if residues != [0, 0] {
                            let k = row * grid_width + i;
                            match interpolated(pixels, i, j, home, residues) {
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
    let finer_grid_shaded = shaded_count.load(Ordering::Relaxed) - lattice_shaded;
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
    // A centre whose corners disagree both ways: from a pair of the finer grid's points
    // more nearly along the epipolar line through it than the diagonals
    // ([`CENTRE_ALONG`]); else from a diagonal pair on a smooth ramp with the points
    // beyond them ([`Interpolation::on_ramp`]). Tried on the centres left to shade,
    // apart from the pass above, whose code it would slow.
    let centre_along = |(x, y): (usize, usize)| {
        let point = |px: i64, py: i64| {
            let (i, j) = (usize::try_from(px).ok()? / 2, usize::try_from(py).ok()? / 2);
            grid.row(j)?.get(i).copied()
        };
        let (px, py) = (x as i64, y as i64);
        let along = || {
            let [a, b] = lines?.offset_along(x, y, &CENTRE_ALONG, &[[1, 1], [1, -1]])?;
            let pair = [point(px - a, py - b)?, point(px + a, py + b)?];
            interpolation.midway_along(pair, [a, b], x, y)
        };
        let diagonal = |[a, b]: [i64; 2]| [-3, -1, 1, 3].map(|k| point(px + k * a, py + k * b));
        along()
            .or_else(|| interpolation.on_ramp(diagonal([1, 1]), x, y))
            .or_else(|| interpolation.on_ramp(diagonal([1, -1]), x, y))
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
    let mut edges = BandEdges::new(band_count * centre_width)?;
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
            let batch = batch.resolved_by(centre_along, |slot, pixel| row[slot] = pixel);
            shaded_count.fetch_add(batch.shade(&shade, &mut row), Ordering::Relaxed);
            out.copy_from_slice(&row);
        });
    let edges = &edges;
    let between_shaded = AtomicUsize::new(0);
    let mut layers = Layers::for_overwrite(width as u32, height as u32)?;
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
        let batch = batch
            .resolved_by(centre_along, |slot, pixel| centres[slot] = pixel)
            .in_tiles(centre_width, |(x, _)| x / 2);
        between_shaded.fetch_add(batch.shade(&shade, &mut centres), Ordering::Relaxed);
        let centres_of = |j: usize| -> Option<&[Pixel]> {
            match j.checked_sub(first_centre_row) {
                None if j + 1 == first_centre_row => Some(edges.row(index - 1, centre_width)),
                None => None,
                Some(r) => centres.get(r * centre_width..(r + 1) * centre_width),
            }
        };
        // A pixel neither of whose pairs beside agrees: from a pair along the epipolar
        // line through it, of the finer grid's points or of centres, whichever lie there
        // ([`BETWEEN_ALONG`]), where that is more nearly along the line than the pairs
        // beside. A shadow edge that runs obliquely between the pairs beside need not
        // run between this one. Else from either pair beside on a smooth ramp with the
        // points beyond them ([`Interpolation::on_ramp`]). Tried on the pixels left to
        // shade, apart from the loop below, whose code it would slow.
        let along_line = |(x, y): (usize, usize)| -> Option<Pixel> {
            let value = |px: i64, py: i64| -> Option<Pixel> {
                let (px, py) = (usize::try_from(px).ok()?, usize::try_from(py).ok()?);
                match (px % 2, py % 2) {
                    (0, 0) => grid.row(py / 2)?.get(px / 2).copied(),
                    (1, 1) => centres_of(py / 2)?.get(px / 2).copied(),
                    _ => None,
                }
            };
            let (px, py) = (x as i64, y as i64);
            let along = || {
                let [a, b] = lines?.offset_along(x, y, &BETWEEN_ALONG, &[[1, 0], [0, 1]])?;
                let pair = [value(px - a, py - b)?, value(px + a, py + b)?];
                interpolation.midway_along(pair, [a, b], x, y)
            };
            // Four in a row on the pixel's row, of the finer grid's points on its rows
            // and of centres between them, else in its column, of centres on the finer
            // grid's rows and of its points between them.
            let (i, j) = (x / 2, y / 2);
            let on_row = || match y % 2 {
                0 => four_from(grid.row(j), i.checked_sub(1)),
                _ => four_from(centres_of(j), i.checked_sub(2)),
            };
            let in_column = || match y % 2 {
                0 => four_down(j.checked_sub(2), |k| centres_of(k)?.get(i).copied()),
                _ => four_down(j.checked_sub(1), |k| grid.row(k)?.get(i).copied()),
            };
            along()
                .or_else(|| interpolation.on_ramp(on_row(), x, y))
                .or_else(|| interpolation.on_ramp(in_column(), x, y))
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
        let batch = batch
            .resolved_by(along_line, |k, pixel| band.set(k, &pixel))
            .in_tiles(width, |(x, _)| x);
        let shaded = batch.shade_each(&shade, |k, pixel| band.set(k, pixel));
        between_shaded.fetch_add(shaded, Ordering::Relaxed);
        // The finer grid's rows were counted as they were completed.
        control.advance((rows / 2) as u64);
    });
    let shaded = shaded_count.into_inner() + between_shaded.into_inner();
    let passes = AdaptivePasses {
        lattice,
        finer_grid,
        between: stopwatch.lap(),
        lattice_shaded,
        finer_grid_shaded,
        // With the band edges' centres, completed between the finer grid and this pass.
        between_shaded: shaded - lattice_shaded - finer_grid_shaded,
    };
    Ok((layers, shaded, passes))
}

/// The half-spans, in pixels, of the pairs along the epipolar lines that a pixel between
/// the finer grid's points may take where the pairs beside it disagree: between the axes
/// and the diagonals, and their mirror images. Their ends lie on the finer grid or on
/// centres, whichever the pixel's parity puts there.
const BETWEEN_ALONG: [[i64; 2]; 8] = [
    [2, 1],
    [2, -1],
    [1, 2],
    [1, -2],
    [3, 2],
    [3, -2],
    [2, 3],
    [2, -3],
];

/// The same for the centres of the finer grid's squares, beyond the diagonals: their
/// ends lie on the finer grid.
const CENTRE_ALONG: [[i64; 2]; 4] = [[3, 1], [3, -1], [1, 3], [1, -3]];

/// Four consecutive pixels of `row` from `first`, each `None` where it has none there.
#[inline]
fn four_from(row: Option<&[Pixel]>, first: Option<usize>) -> [Option<Pixel>; 4] {
    let four = row
        .zip(first)
        .and_then(|(row, first)| row.get(first..first + 4));
    std::array::from_fn(|k| four.map(|four| four[k]))
}

/// The pixels `at` rows `first` to `first + 3` of a column gives, each `None` where it has
/// none there.
#[inline]
fn four_down(first: Option<usize>, at: impl Fn(usize) -> Option<Pixel>) -> [Option<Pixel>; 4] {
    std::array::from_fn(|k| at(first? + k))
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

    /// The batch without the pixels `resolve` gives a value, which `store` takes with
    /// their slot. (Not inlined: in the passes' loops, its code slowed them more than
    /// the pixels it resolves saved.)
    #[inline(never)]
    fn resolved_by(
        self,
        mut resolve: impl FnMut((usize, usize)) -> Option<Pixel>,
        mut store: impl FnMut(usize, Pixel),
    ) -> Self {
        let mut left = Self::default();
        for (slot, pixel) in self.slots.into_iter().zip(self.pixels) {
            match resolve(pixel) {
                Some(value) => store(slot, value),
                None => left.push(slot, pixel),
            }
        }
        left
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

/// Neighbours' blend where they agree ([`Agreement::blend`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Blend {
    volume: [f32; 4],
    visibility: f32,
    /// Their reaches interpolated in the [`SurfaceCoordinate`]: where the pixel's own ray
    /// ends, if it sees the surface through theirs ([`SurfaceCoordinate::holds`]).
    coordinate: f32,
}

/// What neighbours must share to be blended: how far their light may spread, and where
/// their rays end.
#[derive(Clone, Copy, Debug)]
struct Agreement {
    tolerance: f32,
    /// Per channel of RGBA, the value below which spreads are held to the tolerance of
    /// this value rather than of the blend's ([`DARK_SHARE`]).
    floor: [f32; 4],
    /// Where background rays end, and surfaces beyond it count as lying.
    max_distance: f32,
    coordinate: SurfaceCoordinate,
}

impl Agreement {
    /// The blend of `neighbours` by `weights` (summing to 1) where they agree: each of
    /// RGBA spreads by at most the tolerance times its blend, or times its floor where the
    /// blend is below that (NaN stays a disagreement), and visibility by at most the
    /// tolerance. Their rays' ends blend in the surface coordinate. NaN anywhere means
    /// disagreement.
    #[inline(always)]
    fn blend<const N: usize>(&self, neighbours: [Pixel; N], weights: [f32; N]) -> Option<Blend> {
        let lanes = self.lanes(neighbours);
        let lanes = |n: usize| lanes[n];
        let mut low = [f32::INFINITY; 8];
        let mut high = [f32::NEG_INFINITY; 8];
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
        // The reaches may spread as a receding surface's do (the pixel's own is tested
        // against their blend), and only NaN there disagrees.
        let allowed = self.allowed_spreads(&blend);
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

    /// The mean of the middle two of `points`, four in a row at even steps, where they
    /// lie on a smooth ramp: per lane, each step differs from the one before by at most
    /// what [`Agreement::blend`] allows the pair to spread. The middle pair of a steep
    /// smooth gradient (a shaft's soft edge, or the light where a shaft meets the ground)
    /// may spread by far more than that, while their mean is off the curve between them
    /// by about an eighth of that change of step. A step or a crease anywhere among them
    /// changes the steps by as much as it rises, and is refused. What no four points show
    /// is not found either: a line thinner than their spacing between the pair, or a
    /// ripple that samples to a straight line, as [`Agreement::blend`] misses one between
    /// agreeing neighbours. The reaches' coordinates need not be smooth (the pixel's own
    /// is tested against their blend), but NaN anywhere is refused. Most ramps tried are
    /// refused, so the coordinates (a division each) are found only for those that pass.
    #[inline]
    fn blend_on_ramp(&self, points: [Pixel; 4]) -> Option<Blend> {
        let lanes = points.map(|pixel| {
            let [r, g, b, a] = pixel.volume;
            [r, g, b, a, pixel.visibility, 0.0, 0.0, 0.0]
        });
        let [before, first, second, after] = lanes;
        let mut blend: [f32; 8] = std::array::from_fn(|k| first[k] + 0.5 * (second[k] - first[k]));
        let allowed = self.allowed_spreads(&blend);
        let mut smooth = true;
        for k in 0..5 {
            let steps = [
                first[k] - before[k],
                second[k] - first[k],
                after[k] - second[k],
            ];
            smooth &= (steps[1] - steps[0]).abs() <= allowed[k];
            smooth &= (steps[2] - steps[1]).abs() <= allowed[k];
        }
        if !smooth || points[0].depth.is_nan() || points[3].depth.is_nan() {
            return None;
        }
        let [first, second] = [points[1], points[2]].map(|pixel| self.reach_coordinate(pixel));
        blend[5] = first + 0.5 * (second - first);
        (!blend[5].is_nan()).then_some(Blend {
            volume: [blend[0], blend[1], blend[2], blend[3]],
            visibility: blend[4],
            coordinate: blend[5],
        })
    }

    /// Each pixel's eight lanes, RGBA, visibility, the reach's coordinate
    /// ([`Agreement::reach_coordinate`]) and two of padding, so that every step of a
    /// blend is one lane-wise operation.
    #[inline(always)]
    fn lanes<const N: usize>(&self, pixels: [Pixel; N]) -> [[f32; 8]; N] {
        // The reaches' coordinates first, side by side, so that their divisions overlap.
        let coordinates: [f32; N] = std::array::from_fn(|n| self.reach_coordinate(pixels[n]));
        std::array::from_fn(|n| {
            let [r, g, b, a] = pixels[n].volume;
            [r, g, b, a, pixels[n].visibility, coordinates[n], 0.0, 0.0]
        })
    }

    /// Where `pixel`'s ray ends in the surface coordinate: background, and surfaces beyond
    /// the max distance, at the max distance. NaN stays NaN.
    #[inline(always)]
    fn reach_coordinate(&self, pixel: Pixel) -> f32 {
        let depth = pixel.depth;
        self.coordinate.of(if depth > self.max_distance {
            self.max_distance
        } else {
            depth
        })
    }

    /// Per lane of a `blend` ([`Agreement::lanes`]), the spread allowed: the tolerance
    /// relative to it for RGBA, or to the floor where it is darker, and absolute for
    /// visibility; any for the reach's coordinate.
    #[inline(always)]
    fn allowed_spreads(&self, blend: &[f32; 8]) -> [f32; 8] {
        let (tolerance, floor) = (self.tolerance, self.floor);
        std::array::from_fn(|k| match k {
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
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// No floor, reaches in inverse distance.
    fn agreement(tolerance: f32, max_distance: f32) -> Agreement {
        Agreement {
            tolerance,
            floor: [0.0; 4],
            max_distance,
            coordinate: SurfaceCoordinate::InverseDistance,
        }
    }

    fn mean_if_agreeing<const N: usize>(
        neighbours: [Pixel; N],
        tolerance: f32,
        max_distance: f32,
    ) -> Option<Blend> {
        agreement(tolerance, max_distance).blend(neighbours, [1.0 / N as f32; N])
    }

    fn pixel(rgb: f32, alpha: f32, visibility: f32, depth: f32) -> Pixel {
        Pixel {
            volume: [rgb, 2.0 * rgb, 0.5 * rgb, alpha],
            visibility,
            depth,
        }
    }

    #[test]
    fn smooth_ramps_give_their_middle_pairs_mean_and_steps_and_creases_are_refused() {
        let ramp = |f: &dyn Fn(f32) -> f32, visibility: &dyn Fn(f32) -> f32| {
            let points = [-3.0, -1.0, 1.0, 3.0].map(|t| pixel(f(t), 0.4, visibility(t), 10.0));
            agreement(0.01, 100.0).blend_on_ramp(points)
        };
        let level = |_: f32| 0.5;
        // A gradient of 5% per pixel, its pair 10% apart (ten times the tolerance), and a
        // gentle bend of it: their means.
        let steep = ramp(&|t| 1.0 + 0.05 * t, &level).unwrap();
        assert_eq!(steep.volume, [1.0, 2.0, 0.5, 0.4]);
        assert_eq!((steep.visibility, steep.coordinate), (0.5, 0.1));
        let bent = ramp(&|t| 1.0 + 0.05 * t + 0.001 * t * t, &level).unwrap();
        assert!((bent.volume[0] - 1.001).abs() < 1e-6, "{bent:?}");
        // A step between the pair, a step beyond it, a crease between them, a bend of
        // the light twice as sharp as allowed, and one in visibility alone.
        assert_eq!(ramp(&|t| if t < 0.0 { 1.0 } else { 1.1 }, &level), None);
        assert_eq!(ramp(&|t| if t < 2.0 { 1.0 } else { 1.1 }, &level), None);
        assert_eq!(ramp(&|t| 1.0 + 0.05 * t.abs(), &level), None);
        assert_eq!(ramp(&|t| 1.0 + 0.05 * t + 0.0013 * t * t, &level), None);
        assert_eq!(ramp(&|_| 1.0, &|t| 0.5 + 0.05 * t.abs()), None);
        // Visibility ramps as the light does, absolute.
        assert!(ramp(&|_| 1.0, &|t| 0.5 + 0.1 * t).is_some());
        // NaN anywhere, or an end without a reach, is refused.
        assert_eq!(
            ramp(&|t| if t > 2.0 { f32::NAN } else { 1.0 }, &level),
            None
        );
        let mut points = [-3.0f32, -1.0, 1.0, 3.0].map(|t| pixel(1.0 + 0.05 * t, 0.4, 0.5, 10.0));
        points[0].depth = f32::NAN;
        assert_eq!(agreement(0.01, 100.0).blend_on_ramp(points), None);
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
        let parallel = Agreement {
            coordinate: SurfaceCoordinate::Distance,
            ..agreement(0.01, 100.0)
        }
        .blend([near, far], [0.5; 2])
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
        )
        .unwrap();
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
    fn pairs_along_the_lines_are_the_nearest_offsets_nearer_than_those_tried() {
        let lines_at = |degrees: f64| {
            let angle = degrees.to_radians();
            EpipolarLines::through([angle.cos(), angle.sin(), 0.0])
        };
        let axes = [[1, 0], [0, 1]];
        let diagonals = [[1, 1], [1, -1]];
        let between = |degrees| lines_at(degrees).offset_along(40, 30, &BETWEEN_ALONG, &axes);
        let centre = |degrees| lines_at(degrees).offset_along(41, 31, &CENTRE_ALONG, &diagonals);
        // Between the pixels beside: the nearest of the eight, either way along the line.
        assert_eq!(between(27.0), Some([2, 1]));
        assert_eq!(between(207.0), Some([2, 1]));
        assert_eq!(between(34.0), Some([3, 2]));
        assert_eq!(between(-27.0), Some([2, -1]));
        assert_eq!(between(62.0), Some([1, 2]));
        assert_eq!(between(-57.0), Some([2, -3]));
        // Near an axis the pair beside, which was tried, lies nearer.
        assert_eq!(between(5.0), None);
        assert_eq!(between(-84.0), None);
        // Centres: beyond the diagonals, which were tried.
        assert_eq!(centre(18.0), Some([3, 1]));
        assert_eq!(centre(-72.0), Some([1, -3]));
        assert_eq!(centre(45.0), None);
        assert_eq!(centre(135.0), None);
        // Never at an epipole, and never a pair farther across than MAX_ACROSS.
        let at = EpipolarLines::through([40.0, 30.0, 1.0]);
        assert_eq!(at.offset_along(40, 30, &BETWEEN_ALONG, &axes), None);
        let long = [[6, 1]];
        assert_eq!(
            lines_at(9.46).offset_along(40, 30, &long, &axes),
            Some([6, 1])
        );
        // 10.5° off a pair 12.2 px long: 2.2 px across.
        assert_eq!(lines_at(20.0).offset_along(40, 30, &long, &axes), None);
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
                pixel_aspect: 1.5,
                window: None,
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
    fn a_pairings_fractions_are_residues_over_the_index_and_its_span_widens_the_tolerance() {
        for candidate in LatticeCandidate::all() {
            let pairing = Pairing::of(&candidate);
            let index = candidate.lattice.index;
            for k in 0..index {
                assert_eq!(pairing.fractions[k as usize], k as f32 / index as f32);
            }
            let pixels = |[a, b]: [i64; 2]| [2.0 * a as f64, 2.0 * b as f64];
            assert_eq!(pairing.u, pixels(candidate.lattice.u));
            assert_eq!(pairing.v, pixels(candidate.lattice.v));
            let widening = (candidate.span / TOLERANCE_SPAN).max(1.0) as f32;
            assert_eq!(pairing.widening, widening);
        }
    }

    #[test]
    fn lattice_residues_wrap_and_divide_like_the_euclidean_operations() {
        for index in 1..=MAX_INDEX {
            let lattice = Lattice {
                index,
                ..Lattice::EVERY_POINT
            };
            for value in -50..50 {
                assert_eq!(
                    lattice.wrap(value),
                    value.rem_euclid(index),
                    "{value} % {index}"
                );
                assert_eq!(lattice.divide(value * index), value, "{value}·{index}");
            }
        }
    }

    /// The corners a point with `residues` off `lattice` is interpolated from, and their
    /// weights (× index), found independently of the finer grid's pass: the triangle of
    /// its cell it lies in, or the side it lies on.
    fn corners_of(lattice: &Lattice, (i, j): (i64, i64), [m, n]: [i64; 2]) -> Vec<([i64; 2], i64)> {
        let Lattice { u, v, index } = *lattice;
        let o = [
            (index * i - m * u[0] - n * v[0]) / index,
            (index * j - m * u[1] - n * v[1]) / index,
        ];
        let at = |a: i64, b: i64| [o[0] + a * u[0] + b * v[0], o[1] + a * u[1] + b * v[1]];
        let all = if m + n <= index {
            [(at(0, 0), index - m - n), (at(1, 0), m), (at(0, 1), n)]
        } else {
            [
                (at(1, 1), m + n - index),
                (at(0, 1), index - m),
                (at(1, 0), index - n),
            ]
        };
        all.into_iter().filter(|&(_, weight)| weight != 0).collect()
    }

    #[test]
    fn lattices_put_every_other_point_between_lattice_points_along_the_epipolar_line() {
        let choice = LatticeChoice::get();
        let mut indices = Vec::new();
        for tenths in 0..3600 {
            let angle = (tenths as f64 / 10.0 + 0.03).to_radians();
            let direction = [angle.cos(), angle.sin()];
            let lattice = Lattice::along(&[direction; 4], choice);
            let Lattice { u, v, index } = lattice;
            assert_eq!(u[0] * v[1] - u[1] * v[0], index, "{angle}");
            indices.push(index);
            let across =
                |[a, b]: [i64; 2]| 2.0 * (direction[0] * b as f64 - direction[1] * a as f64);
            for j in 20..20 + 2 * MAX_INDEX {
                for i in 20..20 + 2 * MAX_INDEX {
                    let residues = lattice.residues(i as usize, j as usize);
                    if residues == [0, 0] {
                        continue;
                    }
                    let corners = corners_of(&lattice, (i, j), residues);
                    assert!((2..=3).contains(&corners.len()), "{angle}: {corners:?}");
                    let mut sum = [0, 0, 0];
                    for &([ci, cj], weight) in &corners {
                        assert_eq!(lattice.residues(ci as usize, cj as usize), [0, 0]);
                        sum = [sum[0] + weight * ci, sum[1] + weight * cj, sum[2] + weight];
                    }
                    assert_eq!(sum, [index * i, index * j, index], "{angle}: ({i}, {j})");
                    let (mut low, mut high) = (0.0f64, 0.0f64);
                    for &(a, _) in &corners {
                        for &(b, _) in &corners {
                            let span = [b[0] - a[0], b[1] - a[1]];
                            let length = 2.0 * (span[0] as f64).hypot(span[1] as f64);
                            assert!(length <= MAX_ALONG + 1e-9, "{angle}: {corners:?}");
                        }
                        let offset = [a[0] - corners[0].0[0], a[1] - corners[0].0[1]];
                        low = low.min(across(offset));
                        high = high.max(across(offset));
                    }
                    assert!(high - low <= MAX_ACROSS + 1e-9, "{angle}: {corners:?}");
                }
            }
        }
        // At most half the finer grid is shaded first, a sixth along the grid's axes
        // (pairs 12 px apart) and a quarter along its diagonals (11.3 px); on average
        // over directions, about a fifth.
        assert!(indices.iter().all(|&index| index >= 2), "{indices:?}");
        for tenths in [0, 900, 1800, 2700] {
            assert_eq!(indices[tenths], 6, "{tenths}");
        }
        for tenths in [450, 1350, 2250, 3150] {
            assert_eq!(indices[tenths], 4, "{tenths}");
        }
        let shaded = indices.iter().map(|&index| 1.0 / index as f64).sum::<f64>() / 3600.0;
        assert!(shaded < 0.21, "{shaded}");
        // Lines of lattice points alone (pairs, no triangles) shade half as much again.
        let collinear = (0..3600)
            .map(|tenths| {
                let angle = (tenths as f64 / 10.0 + 0.03).to_radians();
                let direction = [[angle.cos(), angle.sin()]];
                let mut candidates = choice.candidates.iter().filter(|c| c.collinear);
                let first = candidates.find(|c| c.fits(&direction));
                1.0 / first.map_or(1, |c| c.lattice.index) as f64
            })
            .sum::<f64>()
            / 3600.0;
        assert!(shaded < collinear / 1.4, "{shaded} against {collinear}");
        // Around an epipole inside the square, and without a direction, every point.
        let around = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];
        assert_eq!(Lattice::along(&around, choice), Lattice::EVERY_POINT);
        assert_eq!(
            Lattice::along(&[[0.0, 0.0]; 4], choice),
            Lattice::EVERY_POINT
        );
        assert_eq!(
            Lattice::along(&[[f64::NAN, 1.0]; 4], choice),
            Lattice::EVERY_POINT
        );
    }

    #[test]
    fn lattices_choose_from_their_direction_s_bin_what_they_would_from_all() {
        let choice = LatticeChoice::get();
        // Squares whose lines fan out by up to 20° from a direction, every 0.07°.
        for step in 0..5200 {
            let angle = (step as f64 * 0.07).to_radians();
            for fan in [0.0f64, 0.5, 2.0, 8.0, 20.0] {
                let corners: [[f64; 2]; 4] = std::array::from_fn(|k| {
                    let turned = angle + (k as f64 / 3.0 - 0.5) * fan.to_radians();
                    [3.0 * turned.cos(), 3.0 * turned.sin()]
                });
                let units = unit_directions(&corners).unwrap();
                let first = choice
                    .candidates
                    .iter()
                    .find(|candidate| candidate.fits(&units))
                    .map_or(Lattice::EVERY_POINT, |candidate| candidate.lattice);
                assert_eq!(
                    Lattice::along(&corners, choice),
                    first,
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
        // shaft of 0.3 two pixels wide at x = 50..52 in the dark half. The ripple is
        // quadratic in x and y (mod 5): a linear one, sampled every other pixel, would
        // read as smooth ramps, which are interpolated.
        let level = |x: usize, y: usize| match x {
            0..32 => 1.0,
            50..52 => 0.3,
            _ => 0.01 * (20.0 / depth(x, y) as f32),
        };
        let value = |x: usize, y: usize| {
            let ripple = 1.0 + 0.03 * ((3 * x * x + y * y + x + 2 * y) % 5) as f32 / 4.0;
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
        // Without the lines, from the diagonal's four points as a ramp
        // ([`Agreement::blend_on_ramp`]), which along the edge are equal; except near the image's
        // sides, where there are not four. (Every pixel keeps its exact value either way.)
        for centre in edges {
            assert!(!along.contains(&centre), "{centre:?} along the lines");
            let (x, y) = centre;
            let four_inside = (3..37).contains(&x) && (3..27).contains(&y);
            assert_eq!(
                without.contains(&centre),
                !four_inside,
                "{centre:?} without the lines"
            );
        }
    }
}
