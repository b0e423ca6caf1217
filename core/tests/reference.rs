//! The reference ray march against closed-form and independently integrated cases.

mod common;

use common::*;
use crepuscular::camera::CameraModel;
use crepuscular::phase::henyey_greenstein;
use crepuscular::scene::{Extent, Method, Scene};
use crepuscular::{render_scene, Layers, RenderControl};
use glam::{DVec3, Mat4, Vec3};

fn render(scene: &Scene) -> Layers {
    render_scene(scene, &RenderControl::new()).expect("render succeeds")
}

/// σs · p · E for one ray of `scene`, per RGB channel.
fn source_term(scene: &Scene, direction: DVec3) -> DVec3 {
    let g = scene.medium.anisotropy as f64;
    let travel = scene.sun.direction.as_dvec3().normalize();
    let phase = henyey_greenstein(g, travel.dot(-direction));
    scene.medium.albedo.as_dvec3()
        * scene.medium.extinction as f64
        * phase
        * scene.sun.irradiance().as_dvec3()
}

fn pixel_ray(scene: &Scene, x: u32, y: u32) -> crepuscular::camera::Ray {
    CameraModel::new(&scene.camera).ray(x as f64 + 0.5, y as f64 + 0.5)
}

#[test]
fn without_occluders_radiance_is_the_closed_form() {
    let camera = pinhole(
        Vec3::new(0.0, 0.0, 2.0),
        Vec3::new(1.0, 0.2, -0.15),
        30.0,
        48,
        32,
    );
    let ground = horizontal_quad(1, -500.0, 500.0, -500.0, 500.0, 0.0);
    for extinction in [1e-4, 0.08, 2.0, 60.0] {
        let scene = scene(
            camera.clone(),
            Vec3::new(0.1, 0.05, -1.0),
            medium(extinction, 0.6),
            vec![ground.clone()],
            settings(512, 64, 40.0),
        );
        let layers = render(&scene);
        let mut background = 0;
        for y in 0..32 {
            for x in 0..48 {
                let ray = pixel_ray(&scene, x, y);
                let i = (y * 48 + x) as usize;
                let surface = layers.depth[i] as f64;
                // The depth layer against the analytic ground hit (raster snapping allows 1e-3).
                let ground_hit = if ray.direction.z < 0.0 {
                    -ray.origin.z / ray.direction.z
                } else {
                    f64::INFINITY
                };
                if ground_hit < 100.0 {
                    // Vertices snap to 1/256 pixel (0.025 rad per pixel here), which moves a
                    // grazing ground hit by t·δθ / sin(grazing angle).
                    let snap = ground_hit * (0.025 / 512.0) / -ray.direction.z;
                    let error = (surface - ground_hit).abs();
                    assert!(
                        error < 1e-5 * ground_hit + snap,
                        "depth ({x}, {y}): {surface} vs {ground_hit}"
                    );
                } else if !ground_hit.is_finite() {
                    background += 1;
                    assert_eq!(surface, 40.0);
                }
                let t_start = scene.camera.clip_start as f64 * ray.distance_per_depth;
                let s = surface.min(40.0) - t_start;
                let sigma = extinction as f64;
                let expected =
                    source_term(&scene, ray.direction) * (-(-sigma * s).exp_m1() / sigma);
                let got = layers.volume_rgba(x, y);
                for c in 0..3 {
                    let error = relative_error(got[c] as f64, expected[c]);
                    assert!(
                        error < 1e-4,
                        "σt={extinction} ({x}, {y}) channel {c}: {} vs {} ({error:e})",
                        got[c],
                        expected[c]
                    );
                }
                let alpha = -(-sigma * s).exp_m1();
                assert!((got[3] as f64 - alpha).abs() < 1e-6);
                assert_eq!(layers.visibility[i], 1.0);
            }
        }
        assert!(
            background > 0 && background < 48 * 32,
            "the view mixes sky and ground"
        );
    }
}

#[test]
fn a_half_space_occluder_cuts_rays_where_its_shadow_begins() {
    // A roof over x > 0 shadows the half-space below it; rays from x = −5 cross into it.
    let camera = pinhole(
        Vec3::new(-5.0, 0.0, 2.0),
        Vec3::new(1.0, 0.0, 0.0),
        100.0,
        64,
        16,
    );
    let roof = horizontal_quad(2, 0.0, 1000.0, -1000.0, 1000.0, 10.0);
    let scene = scene(
        camera,
        Vec3::new(0.0, 0.0, -1.0),
        medium(0.1, 0.3),
        vec![roof],
        settings(4096, 16384, 20.0),
    );
    let layers = render(&scene);
    for y in 0..16 {
        for x in 0..64 {
            let ray = pixel_ray(&scene, x, y);
            let i = (y * 64 + x) as usize;
            let t_start = scene.camera.clip_start as f64 * ray.distance_per_depth;
            let t_cut = 5.0 / ray.direction.x;
            // V̄ weights visibility by the transmittance to the camera.
            let sigma = 0.1;
            let visible =
                (-sigma * (t_cut - t_start)).exp_m1() / (-sigma * (20.0 - t_start)).exp_m1();
            assert!(
                (layers.visibility[i] as f64 - visible).abs() < 1e-3,
                "V̄ ({x}, {y}): {} vs {visible}",
                layers.visibility[i]
            );
            let expected = source_term(&scene, ray.direction)
                * (-(-sigma * (t_cut - t_start)).exp_m1() / sigma);
            let got = layers.volume_rgba(x, y);
            for c in 0..3 {
                let error = relative_error(got[c] as f64, expected[c]);
                assert!(error < 1e-3, "({x}, {y}) channel {c}: {error:e}");
            }
        }
    }
}

/// Independent slab test: the parameter range of a ray inside the box [lo, hi].
fn slab(origin: DVec3, direction: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let mut near = f64::NEG_INFINITY;
    let mut far = f64::INFINITY;
    for axis in 0..3 {
        let t0 = (lo[axis] - origin[axis]) / direction[axis];
        let t1 = (hi[axis] - origin[axis]) / direction[axis];
        near = near.max(t0.min(t1));
        far = far.min(t0.max(t1));
    }
    (near < far).then_some((near, far))
}

/// The fog box of the box tests, from corner to corner, and the views into it: from
/// outside and from inside, fog of 0.35 over a ground.
const BOX_CORNERS: (DVec3, DVec3) = (DVec3::new(-4.0, -3.0, 1.0), DVec3::new(4.0, 3.0, 5.0));
const BOX_SIGMA: f64 = 0.35;

fn box_views(steps: u32) -> [(&'static str, Scene); 2] {
    let world_from_cube = Mat4::from_translation(Vec3::new(0.0, 0.0, 3.0))
        * Mat4::from_scale(Vec3::new(4.0, 3.0, 2.0));
    let ground = horizontal_quad(1, -300.0, 300.0, -300.0, 300.0, 0.0);
    let view = |eye: Vec3, look: Vec3, focal_length: f32| {
        let mut medium = medium(BOX_SIGMA as f32, 0.4);
        medium.extent = Extent::Box { world_from_cube };
        scene(
            pinhole(eye, look, focal_length, 24, 16),
            Vec3::new(0.4, -0.3, -1.0),
            medium,
            vec![ground.clone()],
            settings(1024, steps, 60.0),
        )
    };
    [
        (
            "outside",
            view(
                Vec3::new(-12.0, 1.0, 3.5),
                Vec3::new(1.0, -0.05, -0.05),
                50.0,
            ),
        ),
        (
            "inside",
            view(Vec3::new(0.5, -0.5, 2.5), Vec3::new(1.0, 0.3, -0.1), 24.0),
        ),
    ]
}

/// Calls `visit(x, y, ray, a, b)` for each pixel whose ray has a stretch [a, b] inside the
/// box and before its surface; the other pixels must be empty, and most rays must cross.
fn for_each_box_pixel(
    name: &str,
    scene: &Scene,
    layers: &Layers,
    mut visit: impl FnMut(u32, u32, crepuscular::camera::Ray, f64, f64),
) {
    let (lo, hi) = BOX_CORNERS;
    let mut inside_box = 0;
    for y in 0..16 {
        for x in 0..24 {
            let ray = pixel_ray(scene, x, y);
            let t_start = scene.camera.clip_start as f64 * ray.distance_per_depth;
            let t_end = (layers.depth[(y * 24 + x) as usize] as f64).min(60.0);
            match slab(ray.origin, ray.direction, lo, hi)
                .map(|(a, b)| (a.max(t_start), b.min(t_end)))
                .filter(|(a, b)| b > a)
            {
                Some((a, b)) => {
                    inside_box += 1;
                    visit(x, y, ray, a, b);
                }
                None => assert_eq!(
                    layers.volume_rgba(x, y),
                    [0.0; 4],
                    "{name} ({x}, {y}) misses the box"
                ),
            }
        }
    }
    assert!(inside_box > 24 * 16 / 2, "{name}: most rays cross the box");
}

/// Each RGB channel of `got` within `bound` of `expected`, relatively.
fn assert_channels_within(label: &str, got: [f32; 4], expected: DVec3, bound: f64) {
    for c in 0..3 {
        let error = relative_error(got[c] as f64, expected[c]);
        assert!(
            error < bound,
            "{label} channel {c}: {} vs {} ({error:e})",
            got[c],
            expected[c]
        );
    }
}

#[test]
fn box_medium_matches_the_integral_with_attenuated_sunlight() {
    let sigma = BOX_SIGMA;
    let (lo, hi) = BOX_CORNERS;
    for (name, scene) in box_views(4096) {
        let towards_sun = -scene.sun.direction.as_dvec3().normalize();
        let layers = render(&scene);
        for_each_box_pixel(name, &scene, &layers, |x, y, ray, a, b| {
            let integrand = |t: f64| {
                let p = ray.origin + ray.direction * t;
                let (_, exit) = slab(p, towards_sun, lo, hi).expect("inside the box");
                (-sigma * exit.max(0.0)).exp() * (-sigma * (t - a)).exp()
            };
            let n = 20_000;
            let h = (b - a) / n as f64;
            let mut sum = integrand(a) + integrand(b);
            for k in 1..n {
                sum += integrand(a + k as f64 * h) * if k % 2 == 1 { 4.0 } else { 2.0 };
            }
            let expected = source_term(&scene, ray.direction) * (sum * h / 3.0);
            let got = layers.volume_rgba(x, y);
            assert_channels_within(&format!("{name} ({x}, {y})"), got, expected, 1e-3);
            assert!((got[3] as f64 - (1.0 - (-sigma * (b - a)).exp())).abs() < 1e-6);
        });
    }
}

/// A sun that casts no shadows (`attenuated_by_medium` false, as Cycles lights fog with a
/// lamp whose Cast Shadow is off): its light reaches every point of the box undimmed, so a
/// ray's radiance is the open-fog closed form over its stretch inside the box, and brighter
/// than with the sunlight attenuated wherever the ray crosses fog.
#[test]
fn a_sun_unattenuated_by_the_medium_lights_the_box_as_open_fog() {
    let sigma = BOX_SIGMA;
    for (name, mut scene) in box_views(256) {
        let attenuated = render(&scene);
        scene.sun.attenuated_by_medium = false;
        let layers = render(&scene);
        let mut sums = [0.0; 2];
        for_each_box_pixel(name, &scene, &layers, |x, y, ray, a, b| {
            let opacity = -(-sigma * (b - a)).exp_m1();
            let expected = source_term(&scene, ray.direction) * (opacity / sigma);
            let got = layers.volume_rgba(x, y);
            let label = format!("{name} ({x}, {y})");
            assert_channels_within(&label, got, expected, 1e-4);
            assert!((got[3] as f64 - opacity).abs() < 1e-6, "{label}");
            assert_eq!(layers.visibility[(y * 24 + x) as usize], 1.0, "{label}");
            let dimmed = attenuated.volume_rgba(x, y)[1] as f64;
            assert!(dimmed <= got[1] as f64 * 1.0001, "{label}: {dimmed}");
            sums[0] += dimmed;
            sums[1] += got[1] as f64;
        });
        assert!(sums[0] < 0.8 * sums[1], "{name}: attenuated {sums:?}");
    }
}

/// A ground lit from below, seen from above: all the fog above it lies in its shadow, so
/// every method's layers are dark, and their opacity the open fog's over each ray. The
/// shadow map's bias lit the fog within a texel or two above the ground, seen at a slant
/// as moiré (0.3–1% of the lit level). Where the ground casts no shadow, the fog is lit
/// as open fog all the way to it.
#[test]
fn fog_over_a_ground_lit_from_below_is_dark_by_every_method() {
    let sigma = 0.1;
    for (label, sun) in SUNS_BELOW {
        for method in [Method::Reference, Method::MinMax, Method::Prefiltered] {
            let mut scene = ground_lit_from_below(sun, method);
            let layers = render(&scene);
            // The fast methods' own residue in shadow: prefiltering's truncated series
            // (a few 10⁻⁴ of the light), min-max's resampled map.
            let per_ray = match method {
                Method::Reference => 1e-6,
                Method::MinMax => 1e-4,
                Method::Prefiltered => 2e-3,
            };
            let (mut lit_open_fog, mut seen) = (0.0, 0.0);
            let (width, height) = (scene.camera.width, scene.camera.height);
            for y in 0..height {
                for x in 0..width {
                    let ray = pixel_ray(&scene, x, y);
                    let i = (y * width + x) as usize;
                    let t_start = scene.camera.clip_start as f64 * ray.distance_per_depth;
                    let t_end = (layers.depth[i] as f64).min(60.0);
                    let opacity = -(-sigma * (t_end - t_start)).exp_m1();
                    let unshadowed = source_term(&scene, ray.direction)[0] * opacity / sigma;
                    let got = layers.volume_rgba(x, y);
                    lit_open_fog += unshadowed;
                    seen += got[0] as f64;
                    let at = format!("{label} {method:?} ({x}, {y})");
                    assert!(
                        (got[3] as f64 - opacity).abs() < 1e-5,
                        "{at}: alpha {}",
                        got[3]
                    );
                    // A ray that ends in the fog at the max distance, just above the
                    // ground, ends on no surface: the bias's sliver stays at its end.
                    let bound = if layers.depth[i] < 60.0 {
                        per_ray
                    } else {
                        1e-3
                    };
                    assert!(
                        got[0] as f64 <= bound * unshadowed,
                        "{at}: {} of {unshadowed}",
                        got[0]
                    );
                    let visibility = layers.visibility[i] as f64;
                    assert!(visibility <= 10.0 * bound, "{at}: V̄ {visibility}");
                }
            }
            assert!(
                seen <= 1e-5 * lit_open_fog,
                "{label} {method:?}: {seen} of {lit_open_fog}"
            );
            scene.meshes[0].blocks_sun = false;
            let unblocked = render(&scene);
            let open: f64 = unblocked.volume.chunks(4).map(|v| v[0] as f64).sum();
            assert!(
                relative_error(open, lit_open_fog) < 1e-3,
                "{label} {method:?}: open fog {open} vs {lit_open_fog}"
            );
        }
    }
}

#[test]
fn henyey_greenstein_integrates_to_one_over_the_sphere() {
    for g in [-0.9, 0.0, 0.5, 0.95] {
        let n = 200_000;
        let h = 2.0 / n as f64;
        let f = |k: usize| henyey_greenstein(g, -1.0 + k as f64 * h);
        let mut sum = f(0) + f(n);
        for k in 1..n {
            sum += f(k) * if k % 2 == 1 { 4.0 } else { 2.0 };
        }
        let integral = 2.0 * std::f64::consts::PI * sum * h / 3.0;
        assert!((integral - 1.0).abs() < 1e-6, "g = {g}: {integral}");
    }
}

/// The fast methods' fallback walks a ray texel by texel and integrates each lit part in
/// closed form: the limit of the march as its steps grow. Every 97th pixel of each
/// built-in scene's default view, over its first 30 m, against the march at 2¹⁶ steps,
/// in unbounded fog and in a `box` of it, where each lit part is attenuated through the
/// box and a ray that misses the box keeps the fraction of it that is lit.
#[test]
fn the_texel_walk_is_the_limit_of_the_march() {
    use crepuscular::reference::Marcher;
    use crepuscular::render::FlatGeometry;
    use crepuscular::shadow_map::ShadowMap;
    let in_a_box = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(0.5, -0.5, 3.0))
            * Mat4::from_rotation_z(0.4)
            * Mat4::from_scale(Vec3::new(5.0, 4.0, 3.0)),
    };
    for name in crepuscular::BUILTIN_SCENES {
        for (fog, extent) in [("unbounded", Extent::Unbounded), ("box", in_a_box.clone())] {
            let mut scene = crepuscular::builtin_scene(name).expect("built-in scene");
            scene.camera.width = 160;
            scene.camera.height = 90;
            scene.medium.extinction = 0.2;
            scene.medium.extent = extent;
            let camera = CameraModel::new(&scene.camera);
            let geometry = FlatGeometry::from_scene(&scene);
            let shadow = ShadowMap::of_scene_geometry(&scene, &camera, &geometry).unwrap();
            let marcher = Marcher::new(&shadow, &scene.sun, &scene.medium, 1 << 16);
            let (mut worst, mut worst_scattering, mut partly_lit) = (0.0f64, 0.0f64, 0);
            for pixel in (0..160 * 90).step_by(97) {
                let ray = camera.ray((pixel % 160) as f64 + 0.5, (pixel / 160) as f64 + 0.5);
                let walked = marcher.march_fallback(&ray, 0.1, 30.0);
                let marched = marcher.march(&ray, 0.1, 30.0);
                assert!((walked.alpha - marched.alpha).abs() < 1e-12);
                worst = worst.max((walked.visibility - marched.visibility).abs());
                worst_scattering = worst_scattering
                    .max((walked.scattering - marched.scattering).abs() / marched.alpha.max(1e-3));
                if (0.01..0.99).contains(&marched.visibility) {
                    partly_lit += 1;
                }
            }
            let label = format!("{name} in {fog} fog");
            println!(
                "{label}: largest visibility difference {worst:.2e}, scattering {worst_scattering:.2e}, {partly_lit} rays partly lit"
            );
            assert!(partly_lit >= 10, "{label}: too few partly lit rays to test");
            assert!(worst < 2e-3, "{label}: visibility {worst}");
            assert!(
                worst_scattering < 2e-3,
                "{label}: scattering {worst_scattering}"
            );
        }
    }
}

/// The shadow map covers the camera itself, not only its frustum from the near plane on:
/// the fast methods rectify rays from the camera's projection, and a stretch of a slice
/// off the map reads as unoccluded. In a dense medium under `plane`'s roof, with the camera
/// at the map's edge, that leaked light into every ray (36% off in one such view).
#[test]
fn the_shadow_map_covers_the_camera() {
    use crepuscular::render::FlatGeometry;
    use crepuscular::shadow_map::ShadowMap;
    let mut scene = crepuscular::builtin_scene("plane").expect("built-in scene");
    let eye = Vec3::new(-1.5, 10.7, 1.6);
    scene.camera = crepuscular::scene::Camera::pinhole_looking_at(
        eye,
        eye + Vec3::new(0.13, -0.99, -0.04),
        18.0,
        192,
        108,
    );
    scene.sun.direction = Vec3::new(0.32, 0.04, -0.95);
    scene.medium.extinction = 0.6;
    scene.render.max_distance = 12.0;
    let camera = CameraModel::new(&scene.camera);
    let shadow =
        ShadowMap::of_scene_geometry(&scene, &camera, &FlatGeometry::from_scene(&scene)).unwrap();
    let texel = shadow.texel_from_world.transform_point3(eye.as_dvec3());
    let size = shadow.size as f64;
    assert!(
        (0.0..size).contains(&texel.x) && (0.0..size).contains(&texel.y),
        "the camera's texel {texel:?} is off the {size}² map"
    );
    let render_with = |method| {
        let mut scene = scene.clone();
        scene.render.method = method;
        scene.render.steps = 4096;
        render(&scene)
    };
    let reference = render_with(crepuscular::scene::Method::Reference);
    let fast = render_with(crepuscular::scene::Method::Prefiltered);
    let (diff, total) = fast.volume.chunks(4).zip(reference.volume.chunks(4)).fold(
        (0.0f64, 0.0f64),
        |(d, t), (f, r)| {
            let (f, r) = (
                f[..3].iter().sum::<f32>() as f64,
                r[..3].iter().sum::<f32>() as f64,
            );
            (d + (f - r).abs(), t + r)
        },
    );
    println!("prefiltered error {:.2}%", 100.0 * diff / total);
    assert!(diff / total < 0.03, "{:.2}%", 100.0 * diff / total);
}
