//! The unlit side of a surface a view ray ends on. Fog just in front of a surface that
//! faces away from the sun lies in that surface's own shadow, but the shadow map's depth
//! bias (which keeps lit surfaces from shadowing the fog in front of them) lights a sliver
//! of it: every point less than the bias, plus a texel's worth of the surface's slope,
//! behind the surface in light depth. Seen at a slant the sliver is long, and over a
//! surface in the dark it shows as faint moiré (a ground under a sun below the horizon,
//! a wall seen from inside a lit room). The surface's plane, estimated from the camera
//! depth around the ray's end, gives the sliver's length along the ray
//! ([`shadowed_tail`]); shading integrates the light only up to where it begins, and the
//! opacity and visibility over the whole ray (`render::shade_pixels`). The GPU's
//! shaders do the same (`shaders/march_common.glsl`: `lit_end`). Frames whose style
//! reshaped the map keep its light there: it no longer holds the surfaces the camera sees.

use glam::DVec3;

use crate::camera::{CameraModel, Ray};
use crate::shadow_map::ShadowMap;

/// A neighbouring depth sample further from the camera than this fraction of the ray's
/// distance lies on another surface, and gives no plane.
pub const SAME_SURFACE_SPREAD: f64 = 0.25;

/// The least cosine between a view ray and the surface it ends on that the sliver's
/// length is divided by: a surface seen edge-on would otherwise cut the whole ray.
pub const MIN_FACING: f64 = 0.02;

/// How far across a texel, in texels, a point may lie from the texel's centre, where the
/// map holds the surface's depth (half the diagonal).
pub const TEXEL_REACH: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// The camera's depth samples and their surfaces' orientation: `distances` holds the ray
/// distance of each of `camera`'s pixels' `supersampling`² samples, row by row, +∞ for
/// background. A sample's surface point is P = O + d̂·t (O the ray's origin, d̂ its unit
/// direction, t the distance), so its tangents across and down are
/// Pₓ = Oₓ + d̂ₓ·t + d̂·tₓ and likewise: the distance's differences to the neighbours give
/// tₓ and t_y, the camera the rest.
pub struct DepthSamples<'a> {
    distances: &'a [f32],
    width: i64,
    height: i64,
    /// Samples per pixel along each axis.
    supersampling: f64,
    /// World-space ray origin (relative to the camera's position; zero for a pinhole) and
    /// unnormalized direction as `v[0] + px·v[1] + py·v[2]` ([`crate::camera::RayTerms`]
    /// in the world).
    origin: [DVec3; 3],
    direction: [DVec3; 3],
    perspective: bool,
    facing: FacingTerms,
}

/// The frame's constants of [`DepthSamples::unlit_side_seen`], for light travelling
/// along l. A pinhole's surface normal n = Pₓ × P_y has n·v of the sign of
/// `camera_side` = (D₁ × D₂)·D₀ everywhere, and n·l, times the positive |d|⁴/t, of
/// t·(m₁₂|d|² − (d·D₂)m₁ − (d·D₁)m₂) + |d|²(t_y·m₁ + tₓ·m₂), with m₁₂ = (D₁ × D₂)·l
/// (`both`), m₁ = (D₁ × D₀)·l + py·m₁₂ (`across`) and m₂ = (D₀ × D₂)·l + px·m₁₂
/// (`down`). An orthographic camera's d̂ is fixed, Pₓ = O₁ + d̂·tₓ: n·v has the sign of
/// (O₁ × O₂)·d̂, and n·l = (O₁ × O₂)·l + t_y·(O₁ × d̂)·l + tₓ·(d̂ × O₂)·l.
#[derive(Clone, Copy, Debug)]
struct FacingTerms {
    camera_side: f64,
    both: f64,
    across: f64,
    down: f64,
}

impl FacingTerms {
    fn new(perspective: bool, origin: &[DVec3; 3], direction: &[DVec3; 3], light: DVec3) -> Self {
        let [d0, d1, d2] = *direction;
        if perspective {
            let across_down = d1.cross(d2);
            Self {
                camera_side: across_down.dot(d0),
                both: across_down.dot(light),
                across: d1.cross(d0).dot(light),
                down: d0.cross(d2).dot(light),
            }
        } else {
            let [_, o1, o2] = *origin;
            let view = d0.normalize();
            Self {
                camera_side: o1.cross(o2).dot(view),
                both: o1.cross(o2).dot(light),
                across: o1.cross(view).dot(light),
                down: view.cross(o2).dot(light),
            }
        }
    }
}

/// Where a depth sample's surface faces, as [`DepthSamples::surface`] gives it.
#[derive(Clone, Copy, Debug)]
pub struct SampleSurface {
    /// The sample's continuous pixel coordinates and distance.
    pub pixel: [f64; 2],
    pub distance: f64,
    /// ∂t/∂px and ∂t/∂py, from the nearer neighbour on each axis.
    pub slopes: [f64; 2],
    /// Which neighbour each slope is taken to: +1 after, −1 before.
    pub sides: [f64; 2],
}

impl<'a> DepthSamples<'a> {
    /// The samples of `camera`, lit by light travelling along `light_travel`.
    pub fn new(
        camera: &CameraModel,
        distances: &'a [f32],
        supersampling: u32,
        light_travel: DVec3,
    ) -> Self {
        let terms = camera.ray_terms();
        let to_world = |v: DVec3| camera.world_from_camera.transform_vector3(v);
        let (origin, direction) = (terms.origin.map(to_world), terms.direction.map(to_world));
        let perspective = camera.is_perspective();
        Self {
            distances,
            width: (camera.width * supersampling) as i64,
            height: (camera.height * supersampling) as i64,
            supersampling: supersampling as f64,
            origin,
            direction,
            perspective,
            facing: FacingTerms::new(perspective, &origin, &direction, light_travel),
        }
    }

    /// The depth sample nearest continuous pixel coordinates `pixel`.
    #[inline]
    pub fn sample_at(&self, pixel: [f64; 2]) -> (i64, i64) {
        // Truncation, not `floor` (a library call without SSE4.1, an eighth of this module's
        // instructions): the two differ only below 0, which clamps to 0 either way.
        (
            ((pixel[0] * self.supersampling) as i64).clamp(0, self.width - 1),
            ((pixel[1] * self.supersampling) as i64).clamp(0, self.height - 1),
        )
    }

    /// Asks the CPU to fetch the samples above and below the one nearest `pixel`, which
    /// [`DepthSamples::surface`] reads: shaded pixels lie apart, and their rows beside
    /// are rarely in cache.
    #[inline]
    pub fn prefetch_around(&self, pixel: [f64; 2]) {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let (gx, gy) = self.sample_at(pixel);
            for y in [gy - 1, gy + 1] {
                if (0..self.height).contains(&y) {
                    let at = self.distances[(y * self.width + gx) as usize..].as_ptr();
                    // SAFETY: prefetching is only a hint, and never faults.
                    unsafe { _mm_prefetch::<_MM_HINT_T0>(at.cast()) };
                }
            }
        }
    }

    /// Depth sample (gx, gy)'s distance and its slopes across and down, each from the
    /// neighbour on its axis nearer in distance, within [`SAME_SURFACE_SPREAD`]; `None`
    /// for background, or where an axis has no such neighbour (a sample alone on its
    /// surface, at the image's edge with the other side off the surface).
    #[inline]
    pub fn surface(&self, gx: i64, gy: i64) -> Option<SampleSurface> {
        let at = |x: i64, y: i64| {
            if x < 0 || y < 0 || x >= self.width || y >= self.height {
                f64::INFINITY
            } else {
                self.distances[(y * self.width + x) as usize] as f64
            }
        };
        // Inside the image's border the five samples are read without a test each.
        let [distance, right, left, below, above] =
            if gx > 0 && gy > 0 && gx < self.width - 1 && gy < self.height - 1 {
                let centre = (gy * self.width + gx) as usize;
                let row = self.width as usize;
                let rows = &self.distances[centre - row..=centre + row];
                [row, row + 1, row - 1, 2 * row, 0].map(|i| rows[i] as f64)
            } else {
                [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)].map(|(x, y)| at(gx + x, gy + y))
            };
        if !distance.is_finite() {
            return None;
        }
        // The nearer difference (background is infinitely far), the one after on a tie.
        let nearer = |after: f64, before: f64| {
            let (after, before) = (after - distance, distance - before);
            if after.abs() <= before.abs() {
                (after, 1.0)
            } else {
                (before, -1.0)
            }
        };
        let (across, across_side) = nearer(right, left);
        let (down, down_side) = nearer(below, above);
        let limit = SAME_SURFACE_SPREAD * distance;
        if !(across.abs() <= limit && down.abs() <= limit) {
            return None;
        }
        let ss = self.supersampling;
        Some(SampleSurface {
            pixel: [(gx as f64 + 0.5) / ss, (gy as f64 + 0.5) / ss],
            distance,
            // Per sample, so per pixel ×ss.
            slopes: [across * ss, down * ss],
            sides: [across_side, down_side],
        })
    }

    /// Whether the side of `surface` the camera sees faces away from light travelling
    /// along `light`: the sign of (n·v)(n·l) for n = Pₓ × P_y, in closed form in the ray
    /// terms, without a square root (most rays end on a lit side, and need no more).
    #[inline]
    pub fn unlit_side_seen(&self, surface: &SampleSurface) -> bool {
        let [px, py] = surface.pixel;
        let [tx, ty] = surface.slopes;
        let t = surface.distance;
        let f = &self.facing;
        let along_light = if self.perspective {
            let [d0, d1, d2] = self.direction;
            let d = d0 + d1 * px + d2 * py;
            let (m1, m2) = (f.across + py * f.both, f.down + px * f.both);
            let dd = d.length_squared();
            t * (f.both * dd - d.dot(d2) * m1 - d.dot(d1) * m2) + dd * (ty * m1 + tx * m2)
        } else {
            f.both + ty * f.across + tx * f.down
        };
        along_light * f.camera_side < 0.0
    }

    /// The unit normal of `surface` (either sign), through its point and the neighbours'
    /// its slopes were taken to: exact for a plane.
    pub fn normal_of(&self, surface: &SampleSurface) -> Option<DVec3> {
        let point = |px: f64, py: f64, t: f64| {
            let affine = |v: &[DVec3; 3]| v[0] + v[1] * px + v[2] * py;
            let direction = affine(&self.direction);
            affine(&self.origin) + direction * (t / direction.length())
        };
        let step = 1.0 / self.supersampling;
        let [px, py] = surface.pixel;
        let [across_side, down_side] = surface.sides.map(|side| side * step);
        let t = surface.distance;
        let centre = point(px, py, t);
        let after = point(px + across_side, py, t + surface.slopes[0] * across_side);
        let below = point(px, py + down_side, t + surface.slopes[1] * down_side);
        let across = (after - centre) * surface.sides[0];
        let down = (below - centre) * surface.sides[1];
        let normal = across.cross(down);
        let squared = normal.length_squared();
        (squared > 0.0 && squared.is_finite()).then(|| normal / squared.sqrt())
    }

    /// The unit normal of the surface at depth sample (gx, gy) ([`DepthSamples::surface`]);
    /// its sign is arbitrary.
    pub fn normal(&self, gx: i64, gy: i64) -> Option<DVec3> {
        self.normal_of(&self.surface(gx, gy)?)
    }
}

/// The length of the end of a view ray in the shadow of the surface it ends on that the
/// shadow map's bias would light: 0 where the side the ray sees faces the sun. `normal`
/// is the surface's (either sign), `view` the ray's unit direction, `light_travel` the
/// sun's light's. A point s before the ray's end lies s·(n·−v)/(n·l) behind the surface
/// in light depth, and the map lights it up to the bias plus the surface's depth change
/// across [`TEXEL_REACH`] texels, tan θ each.
pub fn shadowed_tail(
    normal: DVec3,
    view: DVec3,
    light_travel: DVec3,
    bias: f64,
    texel_size: f64,
) -> f64 {
    let towards_camera = if normal.dot(view) > 0.0 {
        -normal
    } else {
        normal
    };
    let cos_light = towards_camera.dot(light_travel);
    if cos_light.is_nan() || cos_light <= 0.0 {
        return 0.0;
    }
    let sin_light = (1.0 - cos_light * cos_light).max(0.0).sqrt();
    let facing = (-towards_camera.dot(view)).max(MIN_FACING);
    (bias * cos_light + TEXEL_REACH * texel_size * sin_light) / facing
}

/// Whether the map holds the surface at `point` (facing the light at `cos_light` to its
/// normal): its light depth there within the bias and a texel's slope of the point's. A
/// surface that casts no shadow (or a map whose occluders a style reshaped) leaves the
/// fog in front of it as the map lights it.
pub fn map_holds(shadow: &ShadowMap, point: DVec3, cos_light: f64) -> bool {
    let sin_light = (1.0 - cos_light * cos_light).max(0.0).sqrt();
    let slope = TEXEL_REACH * shadow.texel_size * sin_light / cos_light.max(MIN_FACING);
    map_holds_within(shadow, point, slope)
}

/// Whether the map's light depth at `point` is within the bias and `slope` of the point's.
#[inline]
fn map_holds_within(shadow: &ShadowMap, point: DVec3, slope: f64) -> bool {
    let texel = shadow.texel_from_world.transform_point3(point);
    let size = shadow.size as f64;
    if !(texel.x >= 0.0 && texel.y >= 0.0 && texel.x < size && texel.y < size) {
        return false;
    }
    // Through u32, in range here: a float's conversion to usize takes a dozen instructions.
    let (x, y) = (texel.x as u32 as usize, texel.y as u32 as usize);
    let stored = shadow.depth[y * shadow.size as usize + x] as f64;
    (texel.z - stored).abs() <= shadow.bias + slope
}

/// Where the light of a view ray through `pixel`, from `t_start` to a surface at `t_end`,
/// ends: `t_end` less its [`shadowed_tail`] where the surface faces away from the sun and
/// the map holds it, never before `t_start`.
pub fn lit_end(
    samples: &DepthSamples,
    shadow: &ShadowMap,
    light_travel: DVec3,
    pixel: [f64; 2],
    ray: &Ray,
    t_start: f64,
    t_end: f64,
) -> f64 {
    let (gx, gy) = samples.sample_at(pixel);
    let Some(surface) = samples.surface(gx, gy) else {
        return t_end;
    };
    // Most rays end on a lit side (or, in the map, behind the far side of a solid), and
    // leave at one of the two tests that need no normal. The map's loose test turns away
    // no ray the exact one below would keep; the closed-form side, first order in the
    // slopes, differs from the exact plane's only where the light grazes the surface.
    if !samples.unlit_side_seen(&surface) {
        return t_end;
    }
    let end = ray.at(t_end);
    if !map_holds_within(shadow, end, TEXEL_REACH * shadow.texel_size / MIN_FACING) {
        return t_end;
    }
    let Some(normal) = samples.normal_of(&surface) else {
        return t_end;
    };
    let cos_light = normal.dot(light_travel);
    if !(normal.dot(ray.direction) * cos_light < 0.0 && map_holds(shadow, end, cos_light.abs())) {
        return t_end;
    }
    let tail = shadowed_tail(
        normal,
        ray.direction,
        light_travel,
        shadow.bias,
        shadow.texel_size,
    );
    (t_end - tail).max(t_start)
}

#[cfg(test)]
mod tests {
    use glam::{DMat4, Vec3};

    use super::*;
    use crate::scene::Camera;

    const WIDTH: u32 = 40;
    const HEIGHT: u32 = 24;

    fn camera() -> CameraModel {
        CameraModel::new(&Camera::pinhole_looking_at(
            Vec3::new(0.0, 0.0, 5.0),
            Vec3::new(3.0, 1.0, 0.0),
            30.0,
            WIDTH,
            HEIGHT,
        ))
    }

    /// Ray distances of `ss`² samples a pixel to the nearest of `planes` (normal, offset:
    /// n·x = offset) each sample's ray meets ahead, +∞ for none.
    fn distances(
        camera: &CameraModel,
        ss: u32,
        planes: &dyn Fn(f64, f64) -> Option<(DVec3, f64)>,
    ) -> Vec<f32> {
        let (w, h) = (WIDTH * ss, HEIGHT * ss);
        (0..h)
            .flat_map(|gy| (0..w).map(move |gx| (gx, gy)))
            .map(|(gx, gy)| {
                let (px, py) = ((gx as f64 + 0.5) / ss as f64, (gy as f64 + 0.5) / ss as f64);
                let ray = camera.ray(px, py);
                planes(px, py)
                    .map(|(n, offset)| (offset - n.dot(ray.origin)) / n.dot(ray.direction))
                    .filter(|t| *t > 0.0)
                    .map_or(f32::INFINITY, |t| t as f32)
            })
            .collect()
    }

    #[test]
    fn a_planes_normal_comes_from_the_samples_beside_each() {
        let camera = camera();
        let tilted = DVec3::new(0.2, -0.3, 1.0).normalize();
        for ss in [1, 2] {
            let distances = distances(&camera, ss, &|_, _| Some((tilted, 0.4)));
            let samples = DepthSamples::new(&camera, &distances, ss, DVec3::Z);
            let (w, h) = ((WIDTH * ss) as i64, (HEIGHT * ss) as i64);
            let mut found = 0;
            for gy in 0..h {
                for gx in 0..w {
                    let seen = distances[(gy * w + gx) as usize].is_finite();
                    match samples.normal(gx, gy) {
                        Some(normal) => {
                            found += 1;
                            assert!(seen, "({gx}, {gy}): a normal for background");
                            let alignment = normal.dot(tilted).abs();
                            assert!(alignment > 1.0 - 1e-5, "({gx}, {gy}) ss {ss}: {alignment}");
                        }
                        None => assert!(!seen, "({gx}, {gy}) ss {ss}: no normal on the plane"),
                    }
                }
            }
            assert!(
                found > (w * h) as usize / 2,
                "the view sees the plane: {found}"
            );
        }
    }

    #[test]
    fn depth_edges_take_the_neighbour_on_the_same_surface() {
        let camera = camera();
        let ground = (DVec3::Z, 0.0);
        // A wall in front of the ground left of pixel column 20, and a strip one pixel
        // wide in front of it at column 30.
        let distances = distances(&camera, 1, &|px, _| {
            if px < 20.0 {
                Some((DVec3::new(1.0, 0.2, 0.1).normalize(), 1.5))
            } else if (30.0..31.0).contains(&px) {
                Some((DVec3::X, 3.0))
            } else {
                Some(ground)
            }
        });
        let samples = DepthSamples::new(&camera, &distances, 1, DVec3::Z);
        for gy in [10, 20] {
            for gx in [19, 20, 21, 29, 31] {
                let normal = samples.normal(gx, gy).expect("a surface's normal");
                let expected = if gx < 20 {
                    DVec3::new(1.0, 0.2, 0.1).normalize()
                } else {
                    DVec3::Z
                };
                assert!(
                    normal.dot(expected).abs() > 1.0 - 1e-6,
                    "({gx}, {gy}): {normal}"
                );
            }
            assert_eq!(
                samples.normal(30, gy),
                None,
                "a strip one sample wide has no plane"
            );
        }
        let sky = distances.iter().position(|d| !d.is_finite());
        if let Some(i) = sky {
            let (gx, gy) = ((i as u32 % WIDTH) as i64, (i as u32 / WIDTH) as i64);
            assert_eq!(samples.normal(gx, gy), None);
        }
    }

    #[test]
    fn the_tail_reaches_back_to_where_the_bias_stops_lighting() {
        let (bias, texel) = (0.03, 0.02);
        // Looking down at a ground lit from below: the sliver is the bias, straight down.
        let up = DVec3::Z;
        let down = -DVec3::Z;
        assert!((shadowed_tail(up, down, up, bias, texel) - bias).abs() < 1e-15);
        assert_eq!(
            shadowed_tail(-up, down, up, bias, texel),
            shadowed_tail(up, down, up, bias, texel)
        );
        // Lit from above: no tail.
        assert_eq!(shadowed_tail(up, down, down, bias, texel), 0.0);
        assert_eq!(
            shadowed_tail(
                up,
                DVec3::X,
                DVec3::new(0.3, 0.0, -1.0).normalize(),
                bias,
                texel
            ),
            0.0
        );
        // Seen edge-on, the facing stops at MIN_FACING.
        let edge_on = DVec3::new(1.0, 0.0, -1e-9).normalize();
        let tail = shadowed_tail(up, edge_on, up, bias, texel);
        assert!((tail - bias / MIN_FACING).abs() < 1e-12, "{tail}");
        // Anywhere else: the point a tail before the end lies the bias and a texel's slope
        // behind the surface, along the light.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut unit = || {
            let mut next = || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
            };
            DVec3::new(next(), next(), next()).normalize()
        };
        let mut checked = 0;
        while checked < 200 {
            let (normal, view, light) = (unit(), unit(), unit());
            let towards_camera = if normal.dot(view) > 0.0 {
                -normal
            } else {
                normal
            };
            let cos_light = towards_camera.dot(light);
            let facing = -towards_camera.dot(view);
            if cos_light < 0.05 || facing < MIN_FACING {
                continue;
            }
            checked += 1;
            let tail = shadowed_tail(normal, view, light, bias, texel);
            let behind = tail * facing / cos_light;
            let tan = (1.0 - cos_light * cos_light).sqrt() / cos_light;
            let expected = bias + TEXEL_REACH * texel * tan;
            assert!(
                (behind - expected).abs() < 1e-12 * expected.max(1.0),
                "{behind} vs {expected}"
            );
        }
    }

    #[test]
    fn the_map_holds_a_surface_within_its_bias_and_slope() {
        let shadow = ShadowMap {
            size: 4,
            depth: [10.0, 10.0, 10.0, f32::INFINITY].repeat(4),
            ids: vec![1; 16],
            texel_from_world: DMat4::IDENTITY,
            texel_size: 1.0,
            bias: 1.5,
        };
        let facing = 1.0;
        assert!(map_holds(&shadow, DVec3::new(1.5, 1.5, 10.2), facing));
        assert!(map_holds(&shadow, DVec3::new(1.5, 1.5, 8.6), facing));
        assert!(!map_holds(&shadow, DVec3::new(1.5, 1.5, 12.0), facing));
        // A steep surface's depth changes across the texel: its slope widens the band.
        assert!(map_holds(&shadow, DVec3::new(1.5, 1.5, 12.0), 0.3));
        assert!(
            !map_holds(&shadow, DVec3::new(3.5, 1.5, 10.0), facing),
            "an empty texel"
        );
        assert!(
            !map_holds(&shadow, DVec3::new(-0.5, 1.5, 10.0), facing),
            "off the map"
        );
    }
}
