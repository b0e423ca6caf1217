//! How far along each slice of a rectified map the frame's view rays reach. A slice's
//! prefix sums are read only up to the farthest ray end on it, and most views end their
//! rays on surfaces well inside the map (on the built-in scenes' default views 12–89% of
//! the rows were ever read): the rest need not be weighted, summed or stored.
//!
//! The bound is conservative. Per square block of pixels, the farthest surface any of its
//! depth samples sees ([`FarthestPerBlock`]) bounds its rays' ends: they all lie in the
//! pyramid from the camera through the block's four corner rays, cut by a plane at that
//! distance, or for an orthographic camera in the box its parallel rays sweep. The map
//! coordinates of those solids' vertices then bound their rays' slices and positions
//! along them ([`slice_reaches`]).

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::CameraModel;
use crate::epipolar::{EpipolarMap, RaySlice};

/// Side of the blocks, in pixels: a frame of 1920×1080 has 8,160.
pub const BLOCK: u32 = 16;

/// The farthest surface distance per block of [`BLOCK`]² pixels, row by row (+∞ where
/// a sample sees the background); blocks on the right and bottom edges may be partial.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FarthestPerBlock {
    pub across: usize,
    pub down: usize,
    pub values: Vec<f32>,
}

impl FarthestPerBlock {
    /// For an image of `width` × `height` pixels.
    pub fn for_image(width: u32, height: u32) -> Self {
        let (across, down) = (
            width.div_ceil(BLOCK) as usize,
            height.div_ceil(BLOCK) as usize,
        );
        Self {
            across,
            down,
            values: vec![0.0; across * down],
        }
    }

    /// Sample rows per band of blocks, with `ss` samples per pixel along each axis.
    pub fn band_rows(ss: u32) -> usize {
        (BLOCK * ss) as usize
    }

    /// Folds one band of sample rows (`sample_width` samples each, `ss`² per pixel) into
    /// `farthest`, the band's blocks.
    pub fn fold_band(band: &[f32], sample_width: usize, ss: u32, farthest: &mut [f32]) {
        let block_samples = (BLOCK * ss) as usize;
        for row in band.chunks(sample_width.max(1)) {
            for (far, stretch) in farthest.iter_mut().zip(row.chunks(block_samples)) {
                // A comparison rather than `f32::max`, whose NaN rules keep it scalar. A
                // NaN distance ends its ray at the reach, as +∞ does.
                *far = stretch.iter().fold(*far, |far, &d| {
                    let d = if d.is_nan() { f32::INFINITY } else { d };
                    if d > far {
                        d
                    } else {
                        far
                    }
                });
            }
        }
    }

    /// Of `distances` (`ss`² samples per pixel, row by row) for an image of `width` ×
    /// `height` pixels.
    pub fn of(distances: &[f32], width: u32, height: u32, ss: u32) -> Self {
        let mut farthest = Self::for_image(width, height);
        let sample_width = (width * ss) as usize;
        let across = farthest.across;
        distances
            .par_chunks(sample_width * Self::band_rows(ss))
            .zip(farthest.values.par_chunks_mut(across.max(1)))
            .for_each(|(band, far)| Self::fold_band(band, sample_width, ss, far));
        farthest
    }
}

/// Per slice of `map`, the farthest position s along it that any of `camera`'s rays
/// reaches before its end, the nearer of its surface ([`FarthestPerBlock`]) and
/// `max_distance`; 0 for slices no ray reads. A ray may also read the slices beside the
/// one it lies on, so each block's rays count for a slice more either side.
pub fn slice_reaches(
    map: &EpipolarMap,
    camera: &CameraModel,
    farthest: &FarthestPerBlock,
    max_distance: f64,
) -> Vec<f64> {
    let slices = map.slices as usize;
    let (width, height) = (camera.width, camera.height);
    // The rays through the blocks' corners, located once for the blocks around them.
    let corners: Vec<Corner> = (0..(farthest.down + 1) * (farthest.across + 1))
        .into_par_iter()
        .map(|index| {
            let (i, j) = (index % (farthest.across + 1), index / (farthest.across + 1));
            let x = (i as u32 * BLOCK).min(width) as f64;
            let y = (j as u32 * BLOCK).min(height) as f64;
            let ray = camera.ray(x, y);
            Corner {
                direction: ray.direction,
                located: map.locate(&ray),
            }
        })
        .collect();
    let corner = |i: usize, j: usize| &corners[j * (farthest.across + 1) + i];
    let per_band: Vec<Vec<f64>> = (0..farthest.down)
        .into_par_iter()
        .map(|j| {
            let mut reach = vec![0.0f64; slices];
            for i in 0..farthest.across {
                let far = farthest.values[j * farthest.across + i] as f64;
                let end = far.min(max_distance);
                if end.is_nan() || end <= 0.0 {
                    continue;
                }
                let block = [
                    corner(i, j),
                    corner(i + 1, j),
                    corner(i, j + 1),
                    corner(i + 1, j + 1),
                ];
                let (s, first, last) = block_reach(map, &block, end);
                for k in first..=last {
                    let slice = map.slice_of(k);
                    reach[slice] = reach[slice].max(s);
                }
            }
            reach
        })
        .collect();
    let mut reach = vec![0.0f64; slices];
    for band in per_band {
        for (reach, band) in reach.iter_mut().zip(band) {
            *reach = reach.max(band);
        }
    }
    reach
}

/// A block corner's ray: its direction, and where it lies in the map.
struct Corner {
    direction: DVec3,
    located: Option<RaySlice>,
}

/// For the rays between the four `corners` of a block, ending within `end` of their
/// origin: the farthest s they reach, and the first and last slice index they may read
/// (before [`EpipolarMap::slice_of`] wraps or clamps them). Where no corner ray can be
/// located, every slice to its end.
fn block_reach(map: &EpipolarMap, corners: &[&Corner; 4], end: f64) -> (f64, i64, i64) {
    let everywhere = (f64::INFINITY, 0, map.slices as i64 - 1);
    // The far face: the plane across the block's axis at distance `end`, which every
    // point at most `end` from the camera in the pyramid lies before. For parallel rays
    // every factor is 1.
    let axis = corners
        .iter()
        .fold(DVec3::ZERO, |sum, corner| sum + corner.direction)
        .normalize();
    let mut s_max = 0.0f64;
    let mut coordinates = [0.0f64; 4];
    let mut located = 0;
    let mut around_the_epipole = false;
    for corner in corners {
        let along = corner.direction.dot(axis);
        if along.is_nan() || along <= 0.0 {
            return everywhere;
        }
        let t_far = end / along;
        match &corner.located {
            Some(slice) => {
                s_max = s_max.max(slice.s_origin + slice.s_per_t * t_far);
                coordinates[located] = slice.slice;
                located += 1;
            }
            // A ray along the light, which moves along no slice: the block's rays lie
            // around the epipole, and the other corners bound how far they reach.
            None => around_the_epipole = true,
        }
    }
    if located == 0 {
        return everywhere;
    }
    let count = map.slices as f64;
    let reference = coordinates[0];
    let (mut low, mut high) = (0.0f64, 0.0f64);
    for &c in &coordinates[..located] {
        let mut offset = c - reference;
        if map.wraps_around() {
            if offset >= 0.5 * count {
                offset -= count;
            } else if offset < -0.5 * count {
                offset += count;
            }
        }
        low = low.min(offset);
        high = high.max(offset);
    }
    // Corners more than half a turn apart around the epipole surround it: the block's
    // rays then run in every direction of the map.
    if around_the_epipole || (map.wraps_around() && high - low >= 0.5 * count) {
        return (s_max, 0, map.slices as i64 - 1);
    }
    // A slice either side: rays read the slices around their coordinate, and rounding
    // may put an inner ray a hair outside its corners'.
    let first = (reference + low).floor() as i64 - 1;
    let last = (reference + high).floor() as i64 + 2;
    (
        s_max,
        map.bounded_slice_index(first),
        map.bounded_slice_index(last),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::epipolar::test_support::rectified;
    use crate::epipolar::RectifyDesc;
    use crate::render::{FlatGeometry, Frame, SurfaceDistances};
    use crate::scene::{Projection, Rectification, Scene, SensorFit};
    use crate::shadow_map::ShadowMap;
    use glam::Vec3;

    /// Built-in scenes seen as a frame sees them, and as it rarely does: from behind and
    /// into the sun (whose epipoles then lie in the image), orthographically, rectified
    /// both ways, supersampled, with short reaches, on images whose blocks are partial.
    fn views() -> Vec<(String, Scene)> {
        let mut views = Vec::new();
        for name in ["tree", "torus", "plane", "colonnade"] {
            let base = crate::builtin_scene(name).expect("built-in scene");
            let mut add = |label: &str, change: &dyn Fn(&mut Scene)| {
                let mut scene = base.clone();
                scene.camera.width = 150;
                scene.camera.height = 85;
                change(&mut scene);
                views.push((format!("{name} {label}"), scene));
            };
            add("default", &|_| {});
            add("epipolar", &|s| {
                s.render.rectification = Rectification::Epipolar
            });
            add("supersampled", &|s| s.render.supersampling = 2);
            add("short reach", &|s| s.render.max_distance = 9.0);
            add("tiny", &|s| (s.camera.width, s.camera.height) = (19, 7));
            let forward = |s: &Scene| {
                s.camera
                    .world_from_camera
                    .transform_vector3(Vec3::NEG_Z)
                    .normalize()
            };
            add("sun ahead", &|s| {
                s.sun.direction = -forward(s) + Vec3::new(0.1, 0.05, -0.3)
            });
            add("sun behind", &|s| {
                s.sun.direction = forward(s) + Vec3::new(0.05, 0.1, -0.3)
            });
            add("orthographic", &|s| {
                s.camera.projection = Projection::Orthographic {
                    ortho_scale: 14.0,
                    sensor_fit: SensorFit::Auto,
                    shift_x: 0.1,
                    shift_y: 0.0,
                }
            });
        }
        views
    }

    /// `scene`'s camera, depth samples, shadow map, rectified map and slice reaches, as a
    /// frame builds them.
    fn reached(
        scene: &Scene,
    ) -> (
        CameraModel,
        SurfaceDistances,
        ShadowMap,
        EpipolarMap,
        Vec<f64>,
    ) {
        let geometry = FlatGeometry::from_scene(scene);
        let camera = CameraModel::new(&scene.camera);
        let surfaces = SurfaceDistances::new(&camera, &Frame::of_scene(scene, &geometry)).unwrap();
        let (_, shadow, map) = rectified(
            scene,
            scene.render.rectification,
            &RectifyDesc::prefiltered(scene.render.epipolar_slices),
        );
        let max_distance = scene.render.max_distance as f64;
        let reaches = slice_reaches(&map, &camera, &surfaces.farthest, max_distance);
        (camera, surfaces, shadow, map, reaches)
    }

    #[test]
    fn every_ray_ends_within_the_reach_of_the_slices_it_reads() {
        let mut cut = 0.0;
        for (label, scene) in views() {
            let (camera, surfaces, _, map, reaches) = reached(&scene);
            let max_distance = scene.render.max_distance as f64;
            assert_eq!(reaches.len(), map.slices as usize, "{label}");
            let ss = surfaces.supersampling;
            let sample_width = (camera.width * ss) as usize;
            let mut checked = 0;
            for (index, &surface) in surfaces.distances.iter().enumerate() {
                let (sx, sy) = (index % sample_width, index / sample_width);
                let pixel = |s: usize| (s as f64 + 0.5) / ss as f64;
                let ray = camera.ray(pixel(sx), pixel(sy));
                let Some(located) = map.locate(&ray) else {
                    continue;
                };
                let end = (surface as f64).min(max_distance);
                let s_end = located.s_origin + located.s_per_t * end;
                for (slice, _) in map.neighbours(located.slice) {
                    let reach = reaches[slice as usize];
                    assert!(
                        s_end <= reach + 1e-9 * reach.abs().max(1.0),
                        "{label}: sample ({sx}, {sy}) ends at s = {s_end} past slice \
                         {slice}'s reach {reach}"
                    );
                }
                checked += 1;
            }
            assert!(
                checked > surfaces.distances.len() / 2,
                "{label}: {checked} checked"
            );
            let (first, last) = map.s_range();
            cut += reaches
                .iter()
                .map(|r| (last - r.min(last)) / (last - first))
                .sum::<f64>()
                / reaches.len() as f64;
        }
        // The bound is not merely the map's length: on average most of a slice is cut.
        let mean_cut = cut / views().len() as f64;
        assert!(mean_cut > 0.3, "{mean_cut}");
    }

    /// Cutting the rows, and the samples resampled, changes no pixel: each is marched
    /// bit for bit as with every row of a whole map, in open and box media, while the
    /// filtered basis shrinks and slices are resampled only in part.
    #[test]
    fn cut_rows_and_samples_change_no_pixel() {
        use crate::epipolar::{epipoles_in_image, CpuPartialResampler};
        use crate::prefiltered::{samples_read, CpuPrefixSums, Prefiltered, PrefilteredDesc};
        use crate::scene::Extent;
        let (mut shrunk, mut resampled_in_part) = (0, 0);
        let views = views();
        let chosen = views
            .iter()
            .filter(|(label, _)| label.ends_with("default") || label.ends_with("sun ahead"));
        for (index, (label, scene)) in chosen.enumerate() {
            let mut scene = scene.clone();
            if index % 2 == 1 {
                scene.medium.extinction = scene.medium.extinction.max(0.1);
                scene.medium.extent = Extent::Box {
                    world_from_cube: glam::Mat4::from_scale(Vec3::new(8.0, 8.0, 3.0)),
                };
            }
            let (camera, surfaces, shadow, map, reaches) = reached(&scene);
            let epipoles: Vec<[f64; 2]> =
                epipoles_in_image(&camera, &shadow, f64::INFINITY).collect();
            let desc = PrefilteredDesc::from_settings(&scene.render);
            let max_distance = scene.render.max_distance as f64;
            let geometry = FlatGeometry::from_scene(&scene);
            let lengths = std::cell::OnceCell::new();
            let partial = CpuPartialResampler {
                lengths: |map: &EpipolarMap| {
                    let along = slice_reaches(map, &camera, &surfaces.farthest, max_distance);
                    let read: Vec<usize> = along.iter().map(|&s| samples_read(map, s)).collect();
                    lengths.set(read.clone()).expect("one resampling");
                    read
                },
            };
            let read_map = EpipolarMap::rectify_with(
                &camera,
                &shadow,
                &geometry.view(),
                scene.sun.direction.as_dvec3().normalize(),
                max_distance,
                scene.render.rectification,
                &RectifyDesc::prefiltered(scene.render.epipolar_slices),
                &partial,
            )
            .expect("a valid view")
            .expect("a view that rectifies");
            let lengths = lengths.into_inner().unwrap_or_default();
            for slice in 0..map.slices {
                let (whole, read) = (map.row(slice), read_map.row(slice));
                let length = lengths.get(slice as usize).map_or(whole.len(), |&l| l);
                assert_eq!(&whole[..length], &read[..length], "{label}: slice {slice}");
                assert!(
                    read[length..].iter().all(|&v| v == f32::INFINITY),
                    "{label}"
                );
                resampled_in_part += (length < whole.len()) as usize;
            }
            let (sun, medium) = (&scene.sun, &scene.medium);
            let whole = Prefiltered::build_with_every_row(
                &map, &camera, &epipoles, &desc, sun, medium, &reaches,
            )
            .expect("memory for the method");
            let cut = Prefiltered::build_with(
                &read_map,
                &camera,
                &epipoles,
                &desc,
                sun,
                medium,
                Some(&reaches),
                &CpuPrefixSums,
            )
            .expect("prefix sums on the CPU");
            let t_start = camera.clip_start;
            for (index, &surface) in surfaces.distances.iter().enumerate() {
                let (x, y) = (index as u32 % camera.width, index as u32 / camera.width);
                let ray = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
                let t_end = (surface as f64).min(max_distance);
                let t_start = t_start * ray.distance_per_depth;
                let (a, b) = (
                    whole.march(&ray, t_start, t_end),
                    cut.march(&ray, t_start, t_end),
                );
                let bits = |sample: Option<crate::reference::RaySample>| {
                    sample.map(|s| [s.scattering, s.alpha, s.visibility].map(f64::to_bits))
                };
                assert_eq!(bits(a), bits(b), "{label}: pixel ({x}, {y})");
            }
            shrunk += (cut.memory_bytes() < whole.memory_bytes()) as usize;
        }
        assert!(shrunk >= 6, "{shrunk}");
        assert!(resampled_in_part > 1000, "{resampled_in_part}");
    }
}
