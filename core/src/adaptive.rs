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
//! where it crosses each strip smoothly. So along an epipolar line the grid can be twice
//! as sparse as across it. Every other pixel of every other row is found in two steps:
//! every fourth pixel of every fourth row is shaded, and each pixel of the finer grid
//! between them is interpolated from two of those on either side where the pair lies
//! along the epipolar line through it, as they must to resolve shafts no worse than the
//! finer grid would. The pixels between those are then interpolated from the finer
//! grid in any direction.
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
use crate::render::{for_each_in_tiles, layer_depth, EDGE_DEPTH_SPREAD, SHADING_TILE as TILE};

/// The default tolerance: neighbours whose radiance spreads by at most 1% of its mean
/// are interpolated. On the built-in scenes' default views at 1920×1080 this shades
/// 13–52% of the pixels and moves the layers from shading every pixel by at most 0.023%
/// of the mean radiance (prefiltering; 0.047% for min-max).
pub const DEFAULT_TOLERANCE: f32 = 0.01;

/// How far apart across the epipolar line through a pixel, in pixels, the two pixels it
/// is interpolated from on the finer grid may lie: as far as the finer grid's own
/// neighbours, two pixels apart.
const MAX_ACROSS: f64 = 2.0;

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
    max_distance: f32,
    surface: &'s S,
}

impl<S: Fn(usize, usize) -> Option<f64>> Interpolation<'_, S> {
    /// Pixel (x, y) as the mean of `neighbours` ([`mean_if_agreeing`]), where it lies on
    /// their surface.
    #[inline]
    fn between<const N: usize>(&self, neighbours: [Pixel; N], x: usize, y: usize) -> Option<Pixel> {
        let mean = mean_if_agreeing(neighbours, self.tolerance, self.max_distance)?;
        let surface = (self.surface)(x, y)?;
        let reach = surface.min(self.max_distance as f64) as f32;
        if !on_one_surface(mean.depth, reach) {
            return None;
        }
        let depth = layer_depth(surface, self.max_distance as f64) as f32;
        Some(Pixel { depth, ..mean })
    }
}

/// The rows of the finer grid (every other pixel of every other row), even and odd
/// ones apart so that each step writes one kind while reading the other, in bands of
/// [`TILE`] rows.
struct FinerGrid {
    width: usize,
    even: Vec<Vec<Pixel>>,
    odd: Vec<Vec<Pixel>>,
}

impl FinerGrid {
    /// Row `j` of the finer grid, `None` past the last.
    #[inline]
    fn row(&self, j: usize) -> Option<&[Pixel]> {
        let bands = if j % 2 == 0 { &self.even } else { &self.odd };
        band_row(bands, self.width, j / 2)
    }
}

/// Row `k` of rows kept in bands of [`TILE`] rows of `width` pixels, `None` past the last.
#[inline]
fn band_row(bands: &[Vec<Pixel>], width: usize, k: usize) -> Option<&[Pixel]> {
    bands
        .get(k / TILE)?
        .get(k % TILE * width..(k % TILE + 1) * width)
}

/// Pixel `up` of row `above` and pixel `down` of row `below` as a pair to interpolate
/// from, at ±`offset`, where both rows exist.
#[inline]
fn across_rows(
    above: Option<&[Pixel]>,
    below: Option<&[Pixel]>,
    up: usize,
    down: usize,
    offset: [f64; 2],
) -> Option<([Pixel; 2], [f64; 2])> {
    Some(([*above?.get(up)?, *below?.get(down)?], offset))
}

/// A pixel of the finer grid interpolated from its row and the others: (row, k, i) for
/// pixel i of row k, `None` where it must be shaded.
type Interpolated<'a> = dyn Fn(&[Pixel], usize, usize) -> Option<Pixel> + Sync + 'a;

/// Of the ways to interpolate a pixel of the finer grid, each a pair of neighbours at
/// ±offset: the one whose pair lies closest along the epipolar line through it, if any
/// lies close enough ([`MAX_ACROSS`]; [`EpipolarLines::across`], without its root and
/// division).
#[inline]
fn along_the_line<const K: usize>(
    lines: Option<&EpipolarLines>,
    x: usize,
    y: usize,
    pairs: [Option<([Pixel; 2], [f64; 2])>; K],
) -> Option<[Pixel; 2]> {
    let [dx, dy] = lines?.direction(x, y);
    let mut best = None;
    // The cross product with the direction: half the distance across times its length.
    let mut closest = f64::INFINITY;
    for (pair, [ox, oy]) in pairs.into_iter().flatten() {
        let cross = (dx * oy - dy * ox).abs();
        if cross < closest {
            closest = cross;
            best = Some(pair);
        }
    }
    let length_squared = dx * dx + dy * dy;
    let half = 0.5 * MAX_ACROSS;
    (length_squared > 1e-24 && closest * closest <= half * half * length_squared)
        .then_some(best)
        .flatten()
}

/// Shades a `width` × `height` image adaptively. `shade(x, y)` gives a pixel's layers;
/// `surface(x, y)` the distance to the surface its whole footprint sees (+∞ for
/// background), or `None` where a depth edge runs through it, which is then shaded.
/// `lines`, the image's epipolar lines where the light is directional, let the grid be
/// sparser along them; without, every other pixel of every other row is shaded.
/// `control` advances by one unit per row. Returns the layers and how many pixels were
/// shaded.
#[allow(clippy::too_many_arguments)]
pub fn shade_adaptively(
    width: usize,
    height: usize,
    tolerance: f32,
    max_distance: f32,
    lines: Option<EpipolarLines>,
    control: &RenderControl,
    surface: impl Fn(usize, usize) -> Option<f64> + Sync,
    shade: impl Fn(usize, usize) -> Pixel + Sync,
) -> (Layers, usize) {
    let lines = lines.as_ref();
    let interpolation = Interpolation {
        tolerance,
        max_distance,
        surface: &surface,
    };
    let grid_width = width.div_ceil(2);
    let grid_height = height.div_ceil(2);
    let shaded_count = AtomicUsize::new(0);
    let new_bands = |rows: usize| {
        (0..rows.div_ceil(TILE))
            .map(|band| vec![Pixel::default(); TILE.min(rows - band * TILE) * grid_width])
            .collect::<Vec<_>>()
    };
    // Completes the pixels of one kind in a band of finer-grid rows, `first` on (image
    // rows 4·(first + row) + `y0`): those in columns `first_column`, +2, … take
    // `interpolated(row, k, i)` for pixel i of row k; where it is `None` they are shaded
    // afterwards, tile by tile for the locality of their rectified data.
    let complete = |pixels: &mut [Pixel],
                    first: usize,
                    y0: usize,
                    first_column: usize,
                    interpolated: &Interpolated| {
        let mut flags = vec![false; pixels.len()];
        for (row, (pixels, flags)) in pixels
            .chunks_exact_mut(grid_width)
            .zip(flags.chunks_exact_mut(grid_width))
            .enumerate()
        {
            for i in (first_column..grid_width).step_by(2) {
                match interpolated(pixels, first + row, i) {
                    Some(value) => pixels[i] = value,
                    None => flags[i] = true,
                }
            }
        }
        let mut count = 0;
        for_each_in_tiles(grid_width, pixels.len() / grid_width, |i, row| {
            let k = row * grid_width + i;
            if flags[k] {
                pixels[k] = shade(2 * i, 4 * (first + row) + y0);
                count += 1;
            }
        });
        shaded_count.fetch_add(count, Ordering::Relaxed);
    };
    // `complete` over every band of `bands` in parallel; with `advance`, their rows count
    // as done.
    let complete_all = |bands: &mut [Vec<Pixel>],
                        y0: usize,
                        first_column: usize,
                        advance: bool,
                        interpolated: &Interpolated| {
        bands.par_iter_mut().enumerate().for_each(|(band, pixels)| {
            if control.is_cancelled() {
                return;
            }
            complete(pixels, band * TILE, y0, first_column, interpolated);
            if advance {
                control.advance((pixels.len() / grid_width) as u64);
            }
        });
    };
    let mut grid = FinerGrid {
        width: grid_width,
        even: new_bands(grid_height.div_ceil(2)),
        odd: new_bands(grid_height / 2),
    };
    // The coarsest grid: every other pixel of the even rows, all shaded.
    complete_all(&mut grid.even, 0, 0, false, &|_, _, _| None);
    // The odd rows' pixels below those: between one above and one below.
    let even = &grid.even;
    complete_all(&mut grid.odd, 2, 0, false, &|_, k, i| {
        let (above, below) = (
            band_row(even, grid_width, k),
            band_row(even, grid_width, k + 1),
        );
        let (x, y) = (2 * i, 4 * k + 2);
        let pair = along_the_line(lines, x, y, [across_rows(above, below, i, i, [0.0, 2.0])])?;
        interpolation.between(pair, x, y)
    });
    // The even rows' other pixels: between their left and right neighbours, or the odd
    // rows' pixels diagonally above and below.
    let odd = &grid.odd;
    complete_all(&mut grid.even, 0, 1, true, &|row, k, i| {
        let right = *row.get(i + 1)?;
        let above = k.checked_sub(1).and_then(|k| band_row(odd, grid_width, k));
        let below = band_row(odd, grid_width, k);
        let (x, y) = (2 * i, 4 * k);
        let pair = along_the_line(
            lines,
            x,
            y,
            [
                Some(([row[i - 1], right], [2.0, 0.0])),
                across_rows(above, below, i - 1, i + 1, [2.0, 2.0]),
                across_rows(above, below, i + 1, i - 1, [2.0, -2.0]),
            ],
        )?;
        interpolation.between(pair, x, y)
    });
    // The odd rows' other pixels, at the centres of the coarsest grid's squares: along
    // the row, the column or a diagonal.
    let even = &grid.even;
    complete_all(&mut grid.odd, 2, 1, true, &|row, k, i| {
        let right = *row.get(i + 1)?;
        let (above, below) = (
            band_row(even, grid_width, k),
            band_row(even, grid_width, k + 1),
        );
        let (x, y) = (2 * i, 4 * k + 2);
        let pair = along_the_line(
            lines,
            x,
            y,
            [
                Some(([row[i - 1], right], [2.0, 0.0])),
                across_rows(above, below, i, i, [0.0, 2.0]),
                across_rows(above, below, i - 1, i + 1, [2.0, 2.0]),
                across_rows(above, below, i + 1, i - 1, [2.0, -2.0]),
            ],
        )?;
        interpolation.between(pair, x, y)
    });
    // Pixel (x, y) as the mean of the finer grid's pixels beside it (left and right,
    // above and below, or the four diagonal ones) where they agree. `None` on the last
    // column or row where one is missing.
    let between = |x: usize, y: usize, above: &[Pixel], below: Option<&[Pixel]>| {
        let i = x / 2;
        match (x % 2 == 1, below) {
            (true, None) => interpolation.between([above[i], *above.get(i + 1)?], x, y),
            (false, Some(below)) => interpolation.between([above[i], below[i]], x, y),
            (true, Some(below)) => interpolation.between(
                [above[i], *above.get(i + 1)?, below[i], *below.get(i + 1)?],
                x,
                y,
            ),
            (false, None) => Some(above[i]),
        }
    };
    let between_shaded = AtomicUsize::new(0);
    let mut layers = Layers::new(width as u32, height as u32);
    layers.par_bands_mut(TILE).for_each(|mut band| {
        if control.is_cancelled() {
            return;
        }
        let rows = band.rows;
        // Interpolated row by row, which streams through the finer grid and the
        // surfaces; the pixels that must be shaded are shaded afterwards tile by tile,
        // for the locality of their rectified data.
        let mut to_shade = vec![false; rows * width];
        for row in 0..rows {
            let y = band.first_row + row;
            let above = grid.row(y / 2);
            // The last odd row of an even height has nothing below.
            let below = (y % 2 == 1).then(|| grid.row(y / 2 + 1));
            for x in 0..width {
                let k = row * width + x;
                let pixel = match (above, below) {
                    (Some(above), None) => between(x, y, above, None),
                    (Some(above), Some(Some(below))) => between(x, y, above, Some(below)),
                    _ => None,
                };
                match pixel {
                    Some(pixel) => band.set(k, &pixel),
                    None => to_shade[k] = true,
                }
            }
        }
        let first_row = band.first_row;
        for_each_in_tiles(width, rows, |x, row| {
            let k = row * width + x;
            if to_shade[k] {
                band.set(k, &shade(x, first_row + row));
            }
        });
        let count = to_shade.iter().filter(|&&shade| shade).count();
        between_shaded.fetch_add(count, Ordering::Relaxed);
        // The finer grid's rows were counted as they were completed.
        control.advance((rows / 2) as u64);
    });
    (
        layers,
        shaded_count.into_inner() + between_shaded.into_inner(),
    )
}

/// The mean of `neighbours` where they agree: each of RGBA spreads by at most
/// `tolerance` times its mean, visibility by at most `tolerance`, and their view rays end
/// within [`EDGE_DEPTH_SPREAD`] of each other (background and surfaces beyond it at
/// `max_distance`). The mean's depth is their nearest ray end. NaN anywhere means
/// disagreement.
fn mean_if_agreeing<const N: usize>(
    neighbours: [Pixel; N],
    tolerance: f32,
    max_distance: f32,
) -> Option<Pixel> {
    // Eight lanes, RGBA, visibility, reach and two of padding, so that every step is one
    // lane-wise operation.
    let mut low = [f32::INFINITY; 8];
    let mut high = [f32::NEG_INFINITY; 8];
    let mut sum = [0.0f32; 8];
    for neighbour in neighbours {
        let [r, g, b, a] = neighbour.volume;
        let reach = neighbour.depth.min(max_distance);
        let values = [r, g, b, a, neighbour.visibility, reach, 0.0, 0.0];
        for k in 0..8 {
            low[k] = low[k].min(values[k]);
            high[k] = high[k].max(values[k]);
            sum[k] += values[k];
        }
    }
    let mean = sum.map(|total| total / N as f32);
    // Per lane, the spread allowed: relative for RGBA, absolute for visibility, and
    // relative to the nearest end for the reach.
    let edge = EDGE_DEPTH_SPREAD as f32 * low[5];
    let allowed: [f32; 8] = std::array::from_fn(|k| match k {
        0..4 => tolerance * mean[k].abs(),
        4 => tolerance,
        5 => edge,
        _ => 0.0,
    });
    let mut agree = true;
    for k in 0..8 {
        agree &= high[k] - low[k] <= allowed[k];
    }
    agree.then_some(Pixel {
        volume: [mean[0], mean[1], mean[2], mean[3]],
        visibility: mean[4],
        depth: low[5],
    })
}

/// Whether a ray ending at `reach` ends on the same surface as rays whose nearest end
/// is `nearest`: within [`EDGE_DEPTH_SPREAD`].
fn on_one_surface(nearest: f32, reach: f32) -> bool {
    (nearest - reach).abs() <= EDGE_DEPTH_SPREAD as f32 * reach
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pixel(rgb: f32, alpha: f32, visibility: f32, depth: f32) -> Pixel {
        Pixel {
            volume: [rgb, 2.0 * rgb, 0.5 * rgb, alpha],
            visibility,
            depth,
        }
    }

    #[test]
    fn agreeing_neighbours_give_their_mean_and_nearest_depth() {
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
        assert_eq!(mean.depth, 10.0);
    }

    #[test]
    fn disagreement_anywhere_means_shading() {
        let base = pixel(1.0, 0.5, 0.8, 10.0);
        let cases = [
            ("radiance 2% apart", pixel(1.02, 0.5, 0.8, 10.0)),
            ("alpha 2% apart", pixel(1.0, 0.51, 0.8, 10.0)),
            ("visibility 0.02 apart", pixel(1.0, 0.5, 0.82, 10.0)),
            ("another surface", pixel(1.0, 0.5, 0.8, 10.3)),
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
        assert_eq!(mean.depth, 100.0);
        assert!(on_one_surface(mean.depth, 100.0));
        assert!(!on_one_surface(mean.depth, 50.0));
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
        let (layers, shaded) = shade_adaptively(
            width,
            height,
            tolerance,
            100.0,
            lines,
            &control,
            surface,
            |x, y| {
                calls.fetch_add(1, Ordering::Relaxed);
                value(x, y)
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
        for (width, height) in [(33, 17), (32, 18), (1, 1), (2, 2)] {
            let (layers, shaded) = shade_image(width, height, 0.01, None, |_, _| Some(20.0), value);
            // The even pixels of even rows, and the last column and row where they are
            // odd: nothing lies beyond them to interpolate from.
            let anchors = width.div_ceil(2) * height.div_ceil(2);
            let last_column = if width % 2 == 0 { height } else { 0 };
            let last_row = if height % 2 == 0 { width } else { 0 };
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
}
