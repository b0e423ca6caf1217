//! 1D min-max mipmaps on the rectified shadow map (Chen et al. 2011, as described in the
//! dissertation §4.2–4.3): the peer method the prefiltered method is compared against.
//!
//! Per slice, each level stores the minimum and maximum of K over runs of 2^level samples.
//! A ray (constant threshold per slice) walks its samples, climbing to the largest run
//! that is entirely lit (min ≥ threshold) or entirely shadowed (max < threshold), so that
//! it visits one node per change of visibility instead of one per sample. Lit spans are
//! integrated in closed form, so the result equals ray marching the rectified map with
//! infinitely many steps.

use rayon::prelude::*;

use crate::camera::Ray;
use crate::epipolar::{EpipolarMap, RaySlice};
use crate::error::{Result, Sizing};
use crate::reference::{integral_exp, medium_segment, weighted_visibility, BoxMedium, RaySample};
use crate::scene::{Medium, Sun};
use crate::spans::JoinedSpans;
use crate::spare::Spare;

/// Minimum and maximum of K over aligned runs of samples, for levels 1 and up. Each
/// slice's pyramid is contiguous, so that a ray's walk stays within a few cache lines.
#[derive(Clone, Debug)]
pub struct MinMaxMipmap {
    /// Start of each level (index 0 is level 1) within a slice's pyramid.
    level_offsets: Vec<usize>,
    /// Nodes per slice over all levels.
    stride: usize,
    nodes: Vec<[f32; 2]>,
}

// The last frame's pyramids, kept for the next (see `crate::spare`).
static SPARE_NODES: Spare<[f32; 2]> = Spare::on_huge_pages(Sizing::Rectified);

/// Lets go of the kept pyramids ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_NODES.clear();
}

impl Drop for MinMaxMipmap {
    fn drop(&mut self) {
        SPARE_NODES.keep(std::mem::take(&mut self.nodes));
    }
}

impl MinMaxMipmap {
    /// An error where its memory cannot be allocated.
    pub fn build(map: &EpipolarMap) -> Result<Self> {
        let samples = map.samples as usize;
        let mut level_offsets = Vec::new();
        let mut stride = 0;
        let mut width = samples;
        while width > 1 {
            level_offsets.push(stride);
            width = width.div_ceil(2);
            stride += width;
        }
        // Every node is set below, so a kept buffer's old values do not matter.
        let mut nodes = SPARE_NODES.try_take(map.slices as usize * stride, || {
            format!("the min-max mipmaps ({} slices)", map.slices)
        })?;
        if stride > 0 {
            nodes
                .par_chunks_mut(stride)
                .enumerate()
                .for_each(|(slice, pyramid)| {
                    let row = map.row(slice as u32);
                    // Level 0 bounds K over each sample's whole interval, not just its centre.
                    let leaves: Vec<[f32; 2]> = row
                        .iter()
                        .enumerate()
                        .map(|(i, &centre)| {
                            let (low, high) = map.sample_bounds(i, centre);
                            [low, high]
                        })
                        .collect();
                    let mut below: &[[f32; 2]] = &leaves;
                    let mut width = samples;
                    for &offset in &level_offsets {
                        let next = width.div_ceil(2);
                        let (done, rest) = pyramid.split_at_mut(offset);
                        let level = &mut rest[..next];
                        let source = if offset == 0 {
                            below
                        } else {
                            &done[offset - width..offset]
                        };
                        for (node, out) in level.iter_mut().enumerate() {
                            let a = source[2 * node];
                            let b = source[(2 * node + 1).min(width - 1)];
                            *out = [a[0].min(b[0]), a[1].max(b[1])];
                        }
                        below = &[];
                        width = next;
                    }
                });
        }
        Ok(Self {
            level_offsets,
            stride,
            nodes,
        })
    }

    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<[f32; 2]>()
    }

    /// Calls `visit(s0, s1)` for each maximal lit interval of [s_a, s_b] along `slice`,
    /// in order. Positions off the map are lit.
    pub fn lit_spans(
        &self,
        map: &EpipolarMap,
        slice: u32,
        threshold: f64,
        s_a: f64,
        s_b: f64,
        mut visit: impl FnMut(f64, f64),
    ) {
        let samples = map.samples as usize;
        let (s_start_of_map, s_end_of_map) = map.s_range();
        let mut spans = JoinedSpans::default();
        if s_a < s_start_of_map {
            spans.push(s_a, s_b.min(s_start_of_map), &mut visit);
        }
        let (inside_a, inside_b) = (s_a.max(s_start_of_map), s_b.min(s_end_of_map));
        if inside_b > inside_a {
            let row = map.row(slice);
            let leaf = |s: f64| (map.sample_coordinate(s) as usize).min(samples - 1);
            let (first, last) = (leaf(inside_a), leaf(inside_b));
            let exact_threshold = threshold;
            let threshold = threshold as f32;
            let mut i = first;
            while i <= last {
                let (low, high) = map.sample_bounds(i, row[i]);
                if low < threshold && high >= threshold {
                    // The ray crosses the occluder depth inside this sample: split it.
                    if let Some((s0, s1)) = map.lit_part(i, row[i], exact_threshold) {
                        spans.push(s0.max(inside_a), s1.min(inside_b), &mut visit);
                    }
                    i += 1;
                    continue;
                }
                let lit = low >= threshold;
                let pyramid = &self.nodes[slice as usize * self.stride..][..self.stride];
                let mut level = 0usize;
                while level < self.level_offsets.len() {
                    let run = 1usize << (level + 1);
                    if i % run != 0 || i + run - 1 > last {
                        break;
                    }
                    let [min, max] = pyramid[self.level_offsets[level] + (i >> (level + 1))];
                    let uniform = if lit {
                        min >= threshold
                    } else {
                        max < threshold
                    };
                    if !uniform {
                        break;
                    }
                    level += 1;
                }
                let run = 1usize << level;
                if lit {
                    let (s0, _) = map.sample_interval(i);
                    let (_, s1) = map.sample_interval(i + run - 1);
                    spans.push(s0.max(inside_a), s1.min(inside_b), &mut visit);
                }
                i += run;
            }
        }
        if s_b > s_end_of_map {
            spans.push(s_a.max(s_end_of_map), s_b, &mut visit);
        }
        spans.finish(&mut visit);
    }
}

/// Per-frame constants of the min-max method.
pub struct MinMaxMethod<'a> {
    map: &'a EpipolarMap,
    mipmap: &'a MinMaxMipmap,
    medium: &'a Medium,
    box_medium: Option<BoxMedium>,
}

impl<'a> MinMaxMethod<'a> {
    pub fn new(
        map: &'a EpipolarMap,
        mipmap: &'a MinMaxMipmap,
        sun: &Sun,
        medium: &'a Medium,
    ) -> Self {
        Self {
            map,
            mipmap,
            medium,
            box_medium: BoxMedium::new(&medium.extent, sun),
        }
    }

    /// Integrates one ray over [t_start, t_end]; `None` when the ray runs along the light
    /// or crosses too few texels for the rectified map, in all or within its first optical
    /// depth ([`EpipolarMap::is_short`], [`EpipolarMap::is_short_in_medium`]): the caller
    /// computes those exactly.
    pub fn march(&self, ray: &Ray, t_start: f64, t_end: f64) -> Option<RaySample> {
        let located = self.map.locate(ray)?;
        if t_end <= t_start {
            return Some(RaySample::EMPTY);
        }
        if self.map.is_short(&located, t_start, t_end) {
            return None;
        }
        let sigma = self.medium.extinction as f64;
        let medium_segment = medium_segment(self.box_medium.as_ref(), ray, t_start, t_end);
        if let Some((a, b)) = medium_segment {
            if self.map.is_short_in_medium(&located, a, b, sigma) {
                return None;
            }
        }
        let along_box = self.box_medium.as_ref().map(|b| b.along(ray));
        let mut blended = RaySample::default();
        for (slice, weight) in self.map.neighbours(located.slice) {
            if weight == 0.0 {
                continue;
            }
            let mut lit_length = 0.0;
            let mut scattering = 0.0;
            self.lit_t_spans(&located, slice, t_start, t_end, |t0, t1| {
                lit_length += t1 - t0;
                let Some((a, b)) = medium_segment else {
                    return;
                };
                let (t0, t1) = (t0.max(a), t1.min(b));
                if t1 <= t0 {
                    return;
                }
                scattering += match &along_box {
                    None => (-sigma * (t0 - a)).exp() * integral_exp(sigma, t1 - t0),
                    Some(along) => along.integrate(t0, t1, a, sigma),
                };
            });
            blended.scattering += weight * scattering;
            blended.visibility += weight * lit_length / (t_end - t_start);
        }
        if let Some((a, b)) = medium_segment {
            let unshadowed = match &along_box {
                None => integral_exp(sigma, b - a),
                Some(along) => along.integrate(a, b, a, sigma),
            };
            blended.alpha = -(-sigma * (b - a)).exp_m1();
            if let Some(visibility) = weighted_visibility(blended.scattering, unshadowed) {
                blended.visibility = visibility;
            }
        }
        Some(blended)
    }

    fn lit_t_spans(
        &self,
        located: &RaySlice,
        slice: u32,
        t_start: f64,
        t_end: f64,
        mut visit: impl FnMut(f64, f64),
    ) {
        let s_a = located.s_origin + located.s_per_t * t_start;
        let s_b = located.s_origin + located.s_per_t * t_end;
        self.mipmap
            .lit_spans(self.map, slice, located.threshold, s_a, s_b, |s0, s1| {
                visit(located.t_at(s0).max(t_start), located.t_at(s1).min(t_end))
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::CameraModel;
    use crate::epipolar::RectifyDesc;
    use crate::render::FlatGeometry;
    use crate::scene::{Camera, Medium, Mesh, Rectification, RenderSettings};
    use crate::shadow_map::ShadowMap;
    use glam::{Mat4, Vec3};
    use rand::{RngExt, SeedableRng};

    /// A rectified map of 200 random floating quads, seen by a pinhole camera.
    fn rectified(rectification: Rectification) -> EpipolarMap {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut positions = Vec::new();
        let mut triangles = Vec::new();
        for i in 0..200u32 {
            let (x, y, z) = (
                rng.random_range(-10.0..10.0f32),
                rng.random_range(-10.0..10.0f32),
                rng.random_range(1.0..6.0f32),
            );
            let size = rng.random_range(0.2..1.5f32);
            positions.extend([
                [x, y, z],
                [x + size, y, z],
                [x + size, y + size, z],
                [x, y + size, z],
            ]);
            triangles.extend([[4 * i, 4 * i + 1, 4 * i + 2], [4 * i, 4 * i + 2, 4 * i + 3]]);
        }
        let mesh = Mesh {
            name: "quads".into(),
            object_id: 2,
            world_from_object: Mat4::IDENTITY,
            positions,
            triangles,
            uvs: None,
            alpha_mask: None,
            blocks_sun: true,
            seen_by_camera: true,
        };
        let scene_camera = Camera::pinhole_looking_at(
            Vec3::new(-12.0, -4.0, 2.0),
            Vec3::new(0.0, 0.0, 3.0),
            30.0,
            64,
            36,
        );
        let camera = CameraModel::new(&scene_camera);
        let sun = crate::scene::Sun {
            direction: Vec3::new(0.3, 0.4, -1.0),
            color: Vec3::ONE,
            strength: 1.0,
            angular_diameter: 0.0,
            attenuated_by_medium: true,
        };
        let medium = Medium {
            extinction: 0.1,
            channel_extinction: None,
            albedo: Vec3::ONE,
            anisotropy: 0.0,
            phase: Default::default(),
            extent: Default::default(),
        };
        let settings = RenderSettings {
            shadow_map_size: 128,
            max_distance: 40.0,
            ..RenderSettings::default()
        };
        let flat = FlatGeometry {
            object_ids: vec![2; mesh.triangles.len()],
            positions: mesh.positions,
            triangles: mesh.triangles,
            origin: glam::DVec3::ZERO,
            ..FlatGeometry::default()
        };
        let shadow = ShadowMap::build(&camera, &sun, &medium, &settings, &flat.view()).unwrap();
        let map = EpipolarMap::rectify(
            &camera,
            &shadow,
            &flat.view(),
            sun.direction.as_dvec3(),
            settings.max_distance as f64,
            rectification,
            &RectifyDesc::min_max(0),
        );
        let map = map
            .expect("a valid view")
            .expect("a pinhole camera rectifies");
        assert_eq!(
            map.is_projective(),
            rectification == Rectification::Projective
        );
        map
    }

    #[test]
    fn the_mipmap_walk_equals_testing_every_sample() {
        for rectification in [Rectification::Epipolar, Rectification::Projective] {
            walk_equals_testing_every_sample(&rectified(rectification));
        }
    }

    fn walk_equals_testing_every_sample(map: &EpipolarMap) {
        let mipmap = MinMaxMipmap::build(map).expect("memory for the mipmaps");
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let (s_start, s_end) = map.s_range();
        for _ in 0..2000 {
            let slice = rng.random_range(0..map.slices);
            let threshold = rng.random_range(-1.5..1.5);
            let s_a = rng.random_range(s_start..s_end);
            let s_b = rng.random_range(s_a..s_end + 5.0);
            let mut walked = Vec::new();
            mipmap.lit_spans(map, slice, threshold, s_a, s_b, |a, b| walked.push((a, b)));
            let mut brute: Vec<(f64, f64)> = Vec::new();
            let row = map.row(slice);
            for (i, &value) in row.iter().enumerate() {
                if let Some((a, b)) = map.lit_part(i, value, threshold) {
                    let (a, b) = (a.max(s_a), b.min(s_b));
                    if b > a {
                        match brute.last_mut() {
                            Some(last) if last.1 >= a => last.1 = b,
                            _ => brute.push((a, b)),
                        }
                    }
                }
            }
            if s_b > s_end {
                match brute.last_mut() {
                    Some(last) if last.1 >= s_end.max(s_a) => last.1 = s_b,
                    _ => brute.push((s_end.max(s_a), s_b)),
                }
            }
            let total = |spans: &[(f64, f64)]| spans.iter().map(|(a, b)| b - a).sum::<f64>();
            assert!(
                (total(&walked) - total(&brute)).abs() < 1e-9 * (s_b - s_a).max(1.0),
                "slice {slice} threshold {threshold}: {walked:?} vs {brute:?}"
            );
            assert_eq!(walked.len(), brute.len());
        }
    }
}
