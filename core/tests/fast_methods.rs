//! Fast methods against the reference at 4096 steps on the same shadow map: the mean
//! absolute error of volume RGB divided by the mean reference radiance.

mod common;

use common::{
    camera_inside_a_fog_box, dilated_roof_in_a_thin_box, radiance_error, small_fog_box_far_off,
};
use crepuscular::camera::CameraModel;
use crepuscular::scene::{Camera, ExactRayEnds, Extent, Mesh, Method, Projection, Scene};
use crepuscular::silhouette::SilhouetteOp;
use crepuscular::style::{Silhouette, Style};
use crepuscular::{
    builtin_scene, render_scene, render_scene_timed, Layers, RenderControl, BUILTIN_SCENES,
};
use glam::{Mat4, Vec3};

const WIDTH: u32 = 192;
const HEIGHT: u32 = 108;

/// The default view, one with the sun inside the image, and one looking sideways to it.
fn views(name: &str) -> Vec<(&'static str, Scene)> {
    views_at(name, WIDTH, HEIGHT)
}

fn views_at(name: &str, width: u32, height: u32) -> Vec<(&'static str, Scene)> {
    let mut scene = builtin_scene(name).expect("built-in scene");
    scene.camera.width = width;
    scene.camera.height = height;
    let eye = scene.camera.world_from_camera.w_axis.truncate();
    let focal = 24.0;
    let towards_sun = -scene.sun.direction.normalize();
    // Look at the subject (everything but the ground) from its shadow, 1.5 m above the
    // ground, aiming a little off the sun so that the sun sits inside the frame behind it.
    let (low, high) = scene
        .meshes
        .iter()
        .filter(|m| m.object_id != 1)
        .flat_map(|m| &m.positions)
        .fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p))),
        );
    let subject = 0.5 * (low + high);
    let shadow_eye = subject - towards_sun * ((subject.z - 1.5) / towards_sun.z).max(3.0);
    let off_axis = towards_sun.cross(Vec3::Z).normalize_or(Vec3::X) * 0.3;
    let sun_view = Camera::pinhole_looking_at(
        shadow_eye,
        shadow_eye + towards_sun + off_axis,
        focal,
        width,
        height,
    );
    let side = Vec3::new(-towards_sun.y, towards_sun.x, -0.15).normalize();
    let side_view = Camera::pinhole_looking_at(eye, eye + side, focal, width, height);
    let mut orthographic = scene.camera.clone();
    orthographic.projection = Projection::orthographic(24.0);
    let with_camera = |camera: Camera| Scene {
        camera,
        ..scene.clone()
    };
    vec![
        ("default", scene.clone()),
        ("sun in view", with_camera(sun_view)),
        ("sideways", with_camera(side_view)),
        ("orthographic", with_camera(orthographic)),
    ]
}

fn render_with(scene: &Scene, method: Method, steps: u32) -> Layers {
    let mut scene = scene.clone();
    scene.render.method = method;
    scene.render.steps = steps;
    render_scene(&scene, &RenderControl::new()).expect("render succeeds")
}

/// (relative mean absolute error, mean reference radiance).
fn error(fast: &Layers, reference: &Layers) -> (f64, f64) {
    error_where(fast, reference, |_| true)
}

/// The error over the pixels `keep` selects by index.
fn error_where(fast: &Layers, reference: &Layers, keep: impl Fn(usize) -> bool) -> (f64, f64) {
    let (mut diff, mut total, mut count) = (0.0f64, 0.0f64, 0usize);
    for (i, (f, r)) in fast
        .volume
        .chunks(4)
        .zip(reference.volume.chunks(4))
        .enumerate()
    {
        if !keep(i) {
            continue;
        }
        count += 1;
        for c in 0..3 {
            diff += (f[c] as f64 - r[c] as f64).abs();
            total += r[c] as f64;
        }
    }
    (diff / total, total / (3 * count.max(1)) as f64)
}

/// Pixels within `radius` of where the sun appears in the image, if it does.
fn near_sun(scene: &Scene, radius: f64) -> Option<impl Fn(usize) -> bool> {
    let camera = CameraModel::new(&scene.camera);
    let towards_sun = -scene.sun.direction.as_dvec3().normalize();
    let clip = camera.pixel_from_world() * towards_sun.extend(0.0);
    let (x, y) = (clip.x / clip.w, clip.y / clip.w);
    let width = scene.camera.width as usize;
    (clip.w > 0.0 && x >= 0.0 && y >= 0.0 && x < width as f64 && y < scene.camera.height as f64)
        .then_some(move |i: usize| {
            let (px, py) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
            (px - x).abs() <= radius && (py - y).abs() <= radius
        })
}

fn assert_finite(layers: &Layers) {
    assert!(layers
        .volume
        .iter()
        .chain(&layers.visibility)
        .chain(&layers.depth)
        .all(|v| v.is_finite()));
}

/// The bound is 1% on torus, tree and colonnade. It sets none for min-max on
/// `plane`, whose slits are a few texels wide: there resampling the shadow map along
/// slices moves edges by up to half a sample, measured at 1.7% on its darkest view.
fn minmax_bound(scene: &str) -> f64 {
    if scene == "plane" {
        0.02
    } else {
        0.01
    }
}

#[test]
fn minmax_matches_the_reference() {
    let mut failures = Vec::new();
    for name in BUILTIN_SCENES {
        for (view, scene) in views(name) {
            let reference = render_with(&scene, Method::Reference, 4096);
            let fast = render_with(&scene, Method::MinMax, 4096);
            assert_finite(&fast);
            let (relative, mean) = error(&fast, &reference);
            println!(
                "{name:>10} {view:<12} error {:.3}% (mean radiance {mean:.4})",
                relative * 100.0
            );
            assert!(mean > 0.0, "{name} {view}: the view shows no scattering");
            if relative > minmax_bound(name) {
                failures.push(format!("{name} {view}: {:.3}%", relative * 100.0));
            }
            // Around the sun, where rectification is least precise, the same bound holds.
            let block = scene.render.epipole_block as f64;
            if let Some(keep) = near_sun(&scene, 2.5 * block) {
                let (near, _) = error_where(&fast, &reference, keep);
                println!("{name:>10} {view:<12} near the sun {:.3}%", near * 100.0);
                if near > minmax_bound(name) {
                    failures.push(format!("{name} {view} near the sun: {:.3}%", near * 100.0));
                }
            } else {
                assert_ne!(view, "sun in view", "{name}: the sun is not in the image");
            }
        }
    }
    assert!(failures.is_empty(), "above the bound: {failures:?}");
}

/// A `box` medium, where the sunlight's attenuation varies along the rays: min-max
/// integrates it exactly (bound 1%); prefiltering cuts rays into pieces of bounded optical
/// depth (bound 2%; one average per ray measured 1.4–5.3% here, 11% in the Blender
/// fidelity scene). The box aligned with the axes has torus's sun, with no x component,
/// grazing its x walls: rays entering through them read the fog up to twice as bright
/// (min-max 5.3% off, prefiltering 1.6% at 384×216) until each stretch between the
/// sunward depth's kinks took its line from the middle.
#[test]
fn fast_methods_match_the_reference_in_a_box_medium() {
    for (view, mut scene) in views("torus").into_iter().take(3) {
        scene.medium.extinction = 0.3;
        scene.medium.extent = Extent::Box {
            world_from_cube: Mat4::from_translation(Vec3::new(0.5, -0.5, 3.0))
                * Mat4::from_rotation_z(0.4)
                * Mat4::from_scale(Vec3::new(5.0, 4.0, 3.0)),
        };
        let reference = render_with(&scene, Method::Reference, 4096);
        assert_fast_methods_match(&format!("box {view:<12}"), &scene, &reference);
    }
    for (view, mut scene) in views("torus").into_iter().take(1) {
        scene.medium.extinction = 0.2;
        scene.medium.extent = Extent::Box {
            world_from_cube: Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0))
                * Mat4::from_scale(Vec3::new(3.5, 3.8, 4.0)),
        };
        let reference = render_with(&scene, Method::Reference, 4096);
        assert_fast_methods_match(&format!("aligned box {view:<12}"), &scene, &reference);
    }
}

/// A box of fog lit through a slotted roof, as in the Blender test against Cycles, the
/// box some 10 m from the camera: 0.14% off. Before the transmittance weights started at
/// the box, every ray here was declined as too imprecise and walked (exact, at 4× the
/// time); with even weights in pieces of 0.25 optical depth it was 2.9% off, at 0.1 1.2%;
/// with transmittance weights in pieces of 0.1 of the view ray's optical depth 0.30%,
/// and in pieces over which the sunlight's optical depth changes by 0.1 0.66%.
#[test]
fn fast_methods_match_the_reference_in_a_box_under_a_slotted_roof() {
    let scene = box_under_a_slotted_roof();
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_fast_methods_within("box under a slotted roof", &scene, &reference, 0.0025);
}

/// The same box lit by a sun that casts no shadows but for the roof (as a Blender lamp
/// whose Cast Shadow is off lights fog under a roof whose Casts Shafts is On): its light
/// is not dimmed in the box, so each ray's weights are the view ray's transmittance alone.
#[test]
fn fast_methods_match_the_reference_under_a_sun_the_box_does_not_dim() {
    let mut scene = box_under_a_slotted_roof();
    scene.sun.attenuated_by_medium = false;
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_fast_methods_within("box not dimming the sun", &scene, &reference, 0.0025);
    let mut dimmed = scene.clone();
    dimmed.sun.attenuated_by_medium = true;
    let dimmed = render_with(&dimmed, Method::Reference, 4096);
    let brighter = radiance_error(&dimmed, &reference);
    assert!(
        brighter > 0.1,
        "the sunlight's attenuation changes the frame by {brighter}"
    );
}

fn box_under_a_slotted_roof() -> Scene {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    let quad = |name: &str, object_id, x0: f32, x1: f32| Mesh {
        name: name.to_string(),
        object_id,
        world_from_object: Mat4::IDENTITY,
        positions: vec![
            [x0, -5.0, 6.0],
            [x1, -5.0, 6.0],
            [x1, 5.0, 6.0],
            [x0, 5.0, 6.0],
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        uvs: None,
        alpha_mask: None,
        blocks_sun: true,
        seen_by_camera: true,
    };
    scene.meshes = vec![quad("roof_a", 1, -6.0, 0.0), quad("roof_b", 2, 0.6, 1.6)];
    scene.camera = Camera::pinhole_looking_at(
        Vec3::new(-9.0, -7.0, 3.5),
        Vec3::new(0.0, 0.0, 2.2),
        50.0,
        2 * WIDTH,
        2 * HEIGHT,
    );
    scene.sun.direction = Vec3::new(0.35, 0.2, -1.0).normalize();
    scene.medium.extinction = 0.35;
    scene.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(0.0, 0.0, 2.5))
            * Mat4::from_scale(Vec3::new(4.0, 3.0, 2.5)),
    };
    scene.render.shadow_map_size = 2048;
    scene.render.max_distance = 60.0;
    scene
}

/// A box of fog 10 cm across, through a long lens from 15 m, a shadow edge of the torus
/// crossing it. The shadow map covers the box alone, so the camera's epipole lies about
/// 150,000 texels off the map: slices rectified from the epipole asked for gigabytes (a
/// box 1 cm across, terabytes) and the process aborted. Slices start where they enter
/// the map, whose diagonal bounds their length.
#[test]
fn a_small_box_of_fog_far_from_the_camera_matches_the_reference() {
    let mut scene = builtin_scene("torus").expect("built-in scene");
    (scene.camera.width, scene.camera.height) = (WIDTH, HEIGHT);
    small_fog_box_far_off(&mut scene);
    let reference = render_with(&scene, Method::Reference, 4096);
    let visibility: Vec<f32> = reference
        .visibility
        .iter()
        .zip(reference.volume.chunks(4))
        .filter(|(_, volume)| volume[3] > 0.01)
        .map(|(&v, _)| v)
        .collect();
    // The box fills a good part of the frame, partly in shadow.
    assert!(visibility.len() > (WIDTH * HEIGHT / 10) as usize);
    assert!(visibility.iter().any(|&v| v < 0.1) && visibility.iter().any(|&v| v > 0.9));
    assert_fast_methods_match("small box far off", &scene, &reference);
    let samples_bound = 2.0 * std::f64::consts::SQRT_2 * scene.render.shadow_map_size as f64;
    for method in [Method::MinMax, Method::Prefiltered] {
        scene.render.method = method;
        let (_, times) = render_scene_timed(&scene, &RenderControl::new()).expect("renders");
        let slices = 8192.0;
        assert!(
            times.rectified_bytes as f64 <= 4.0 * slices * (samples_bound + 1.0),
            "{}: {} bytes rectified",
            method.name(),
            times.rectified_bytes
        );
    }
}

/// A camera inside a box of fog, under `plane`'s slotted roof, looking up the shafts, its
/// clip plane 2 m out, without the near-plane correction. A box cuts rays into pieces, so
/// the stretch before the clip plane, averaged in, would weigh on the first piece alone
/// rather than on the whole ray: 0.84% off the reference here (0.07% now), and a fuzzed
/// view with its camera in a shaft 9.4% (0.94%). In a box that stretch is always
/// subtracted.
#[test]
fn a_camera_inside_a_box_subtracts_the_stretch_before_its_clip_plane() {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    (scene.camera.width, scene.camera.height) = (WIDTH, HEIGHT);
    camera_inside_a_fog_box(&mut scene);
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_methods_within(
        "camera inside a box, near plane uncorrected",
        &scene,
        &reference,
        [(Method::MinMax, 0.01), (Method::Prefiltered, 0.003)],
    );
}

/// Min-max within 1% and prefiltering within 2% of `reference`, a render of `scene`.
fn assert_fast_methods_match(label: &str, scene: &Scene, reference: &Layers) {
    assert_fast_methods_within(label, scene, reference, 0.02);
}

/// Min-max within 1% and prefiltering within `prefiltered_bound` of `reference`.
fn assert_fast_methods_within(
    label: &str,
    scene: &Scene,
    reference: &Layers,
    prefiltered_bound: f64,
) {
    assert_methods_within(
        label,
        scene,
        reference,
        [
            (Method::MinMax, 0.01),
            (Method::Prefiltered, prefiltered_bound),
        ],
    );
}

/// Each method within its bound of `reference`, with finite layers.
fn assert_methods_within(
    label: &str,
    scene: &Scene,
    reference: &Layers,
    bounds: [(Method, f64); 2],
) {
    for (method, bound) in bounds {
        assert_method_within(label, scene, reference, method, bound);
    }
}

/// `method` within `bound` of `reference`, with finite layers.
fn assert_method_within(
    label: &str,
    scene: &Scene,
    reference: &Layers,
    method: Method,
    bound: f64,
) {
    let fast = render_with(scene, method, 4096);
    assert_finite(&fast);
    let (relative, mean) = error(&fast, reference);
    println!(
        "{label} {:<11} error {:.3}% (mean radiance {mean:.4})",
        method.name(),
        relative * 100.0
    );
    assert!(mean > 0.0);
    assert!(
        relative <= bound,
        "{label}, {}: {:.3}%",
        method.name(),
        relative * 100.0
    );
}

/// Views whose rays cross only a few shadow-map texels, which rectified lookups resolve
/// to a sample, while near the camera an occluder's key changes fastest along a slice:
/// - looking up at `plane`'s slotted roof from a metre below it, under a high sun
///   (prefiltering was off by 10% on the light through the slits);
/// - from inside `tree`'s crown looking down through dense fog, where rays end on leaves
///   close by (min-max was 1.9% off);
/// - orthographic, looking up out of a `box` of fog towards the sun, where only the
///   stretch inside the box scatters (prefiltering was 9.5% off);
/// - orthographic, looking down at `tree` 18° off the light's travel (prefiltering read
///   7% too dark at the ends of rays on lit ground).
///
/// Both methods walk such rays texel by texel and integrate them exactly
/// (`SHORT_RAY_TEXELS`); prefiltering also declines rays whose pieces inside a box cross
/// fewer than `SHORT_STRETCH_TEXELS`.
#[test]
fn rays_too_short_for_rectified_lookups_are_integrated_exactly() {
    let mut under_roof = builtin_scene("plane").expect("built-in scene");
    // Between two slits (this view once looked up at the roof past its last slit, where
    // all its light was the shadow bias's sliver under the roof).
    let eye = Vec3::new(-1.0, -7.5, 4.0);
    under_roof.camera =
        Camera::pinhole_looking_at(eye, eye + Vec3::new(0.13, -0.39, 0.91), 18.0, WIDTH, HEIGHT);
    under_roof.sun.direction = Vec3::new(-0.06, 0.1, -0.99);
    let mut in_crown = builtin_scene("tree").expect("built-in scene");
    let eye = Vec3::new(0.93, -0.61, 7.55);
    in_crown.camera = Camera::pinhole_looking_at(
        eye,
        eye + Vec3::new(-0.44, 0.18, -0.88),
        35.0,
        WIDTH,
        HEIGHT,
    );
    in_crown.sun.direction = Vec3::new(0.42, -0.13, -0.9);
    in_crown.medium.extinction = 0.6;
    // Orthographic, looking up out of a layer of fog 10° off the sun: each ray is long, but
    // its stretch inside the box crosses a few texels, and prefiltering read it 35% dark.
    let mut out_of_fog = builtin_scene("colonnade").expect("built-in scene");
    let eye = Vec3::new(-2.73, 12.76, 5.38);
    out_of_fog.camera = Camera::orthographic_looking_at(
        eye,
        eye + Vec3::new(-0.17, -0.09, 0.98),
        21.0,
        WIDTH,
        HEIGHT,
    );
    out_of_fog.sun.direction = Vec3::new(0.22, -0.02, -0.97);
    out_of_fog.medium.extinction = 0.2;
    out_of_fog.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(2.5, 2.4, 3.6))
            * Mat4::from_scale(Vec3::new(11.0, 7.0, 3.0)),
    };
    // Orthographic, looking down at `tree` 18° off the light's travel with the sun behind
    // the camera: most rays cross fewer than 64 texels (32 left them 3.9% off) before they
    // end on lit ground, closing in on the ground's key over the last of them, and
    // prefiltering read 7% too dark with 16.
    let mut down_the_light = builtin_scene("tree").expect("built-in scene");
    let eye = Vec3::new(0.65, 1.58, 4.12);
    down_the_light.camera = Camera::orthographic_looking_at(
        eye,
        eye + Vec3::new(0.175, -0.052, -0.983),
        24.1,
        WIDTH,
        HEIGHT,
    );
    down_the_light.sun.direction = Vec3::new(0.008, 0.212, -0.977);
    for (name, scene) in [
        ("under the roof", under_roof),
        ("in the crown", in_crown),
        ("out of fog", out_of_fog),
        ("down the light", down_the_light),
    ] {
        let reference = render_with(&scene, Method::Reference, 4096);
        assert_fast_methods_match(&format!("short rays {name:<14}"), &scene, &reference);
    }
}

/// Orthographic, 6.7° off the light's travel with the sun behind the camera (a fuzzed view
/// of `plane`): every ray is lit, but closes in on the ground it ends on over many texels
/// in key, and prefiltering read 0.81–0.95 of the light (9.2% off). Rays that near the
/// light's direction are walked exactly (`ALONG_THE_LIGHT_SIN`).
#[test]
fn rays_nearly_along_the_light_are_integrated_exactly() {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    let eye = Vec3::new(-8.23, 12.73, 7.47);
    scene.camera = Camera::orthographic_looking_at(
        eye,
        eye - Vec3::new(0.165, -0.706, 0.688),
        11.05,
        WIDTH,
        HEIGHT,
    );
    scene.sun.direction = Vec3::new(-0.063, 0.728, -0.682);
    scene.medium.extinction = 0.01;
    scene.render.max_distance = 30.0;
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_fast_methods_within("along the light", &scene, &reference, 0.01);
}

/// With `exact_ray_ends`, the stretch before a ray's end where the shadow map closes in on
/// it is integrated exactly: an orthographic view of `tree` 12° off the light's travel with
/// the sun behind the camera, its rays 10 m longer than those the short-ray rule walks
/// (`SHORT_RAY_TEXELS`) and too far off the light to be walked as along it, end on lit ground
/// after closing in on it over many texels. Prefiltering read them 2.2% dark without, 0.1%
/// with (1.1% without since rays lit all along are exact). The default view of `plane`,
/// whose rays graze its ground, read 1.9% against 0.6%; since rays end their light before
/// the unlit side of the slotted roof (`crepuscular::shadowed_end`), 0.9% against 0.6%.
/// `plane` seen orthographically in a fog box read 4.9% against 1.7% before rays shadowed
/// all along were exact; now 1.3% and 1.4%. In those two both must merely stay within the
/// bound. The default, `auto`, is the rule in the box and the lookups in the open.
#[test]
fn exact_ray_ends_integrate_rays_closing_in_on_the_ground_exactly() {
    let light = Vec3::new(0.008, 0.212, -0.977).normalize();
    let view =
        glam::Quat::from_axis_angle(light.cross(Vec3::X).normalize(), 12f32.to_radians()) * light;
    let target = Vec3::new(0.65, 1.58, 4.12) + view * 4.0;
    let eye = target - view * 14.0;
    let mut off_the_light = builtin_scene("tree").expect("built-in scene");
    off_the_light.camera = Camera::orthographic_looking_at(eye, eye + view, 24.1, WIDTH, HEIGHT);
    off_the_light.sun.direction = light;
    let plane = views("plane");
    let view = |name: &str| {
        let (_, scene) = plane
            .iter()
            .find(|(view, _)| *view == name)
            .expect("a test view");
        scene.clone()
    };
    let grazing = view("default");
    // Seen orthographically in a 75 m deep box of fog (as `bench --fog-box` confines it),
    // rays end on surfaces that are nearly their own occluders, in their last box piece.
    let mut in_a_box = view("orthographic");
    in_a_box.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(0.0, 5.0, 3.06))
            * Mat4::from_scale(Vec3::new(15.0, 37.5, 3.06)),
    };
    for (name, scene, bound, must_halve) in [
        ("12° off the light", off_the_light, 0.01, true),
        ("plane", grazing, 0.01, false),
        ("plane in a box", in_a_box, 0.02, false),
    ] {
        let with = |setting| {
            let mut scene = scene.clone();
            scene.render.exact_ray_ends = setting;
            render_with(&scene, Method::Prefiltered, 4096)
        };
        let reference = render_with(&scene, Method::Reference, 4096);
        let unexact = with(ExactRayEnds::Off);
        let looked_up = error(&unexact, &reference).0;
        let fast = with(ExactRayEnds::On);
        assert_finite(&fast);
        let auto = if scene.medium.extent == Extent::Unbounded {
            &unexact
        } else {
            &fast
        };
        assert!(
            with(ExactRayEnds::Auto) == *auto,
            "{name}: auto is not the setting its medium picks"
        );
        let exact_ends = error(&fast, &reference).0;
        println!(
            "exact ray ends {name:<18} {:.3}% (looked up to the end {:.3}%)",
            exact_ends * 100.0,
            looked_up * 100.0
        );
        let within = if must_halve {
            exact_ends < 0.5 * looked_up
        } else {
            looked_up <= bound
        };
        assert!(
            within && exact_ends <= bound,
            "{name}: {:.3}% with exact ends, {:.3}% without",
            exact_ends * 100.0,
            looked_up * 100.0
        );
    }
}

/// An orthographic camera's rays start all along their slices, and in a dense medium the
/// transmittance weights far along a slice have decayed, or ended at their depth cap:
/// differences of stored prefix sums there are mostly rounding, or nothing.
/// Such rays are walked exactly (`CONDITION_LIMIT`); without, colonnade was 17% off at
/// σ = 0.6 /m, tree 4.3% at 1.5 /m. (At 1.5 /m most of tree's and torus's rays are now
/// walked for crossing few texels within their first optical depth, `LOOKUP_DEPTH`.)
#[test]
fn rays_too_far_along_a_slice_are_integrated_exactly() {
    for (name, extinction) in [("colonnade", 0.6), ("tree", 1.5), ("torus", 1.5)] {
        let (_, mut scene) = views(name)
            .into_iter()
            .find(|(view, _)| *view == "orthographic")
            .expect("an orthographic view");
        scene.medium.extinction = extinction;
        let reference = render_with(&scene, Method::Reference, 4096);
        assert_method_within(
            &format!("{name:>10} orthographic at σ = {extinction}:"),
            &scene,
            &reference,
            Method::Prefiltered,
            0.02,
        );
    }
}

/// An orthographic view level under `plane`'s roof in fog of 0.6 /m (fuzzed): its rays
/// start along their slices, some a few optical depths past where the slice's weights
/// begin to decay, and those weights stopped falling at their depth cap. Past the cap
/// each sample weighed as much as the first there, so a ray starting 4.5 optical depths
/// in gave the 40 optical depths of its far end, lit beyond the roof, an eighth of its
/// weight: the shadowed band under the roof read 0.1 of visibility where it sees 0.005,
/// and the frame 5.1% bright (min-max 0.46%). Samples past the cap now weigh nothing: a
/// lookup ends there, and one that starts there is walked.
#[test]
fn rays_starting_along_a_slice_take_no_weight_past_its_depth_cap() {
    let scene = fuzzed_plane(
        [
            0.435_738_66,
            0.900_073_2,
            0.0,
            0.0,
            0.085_388_47,
            -0.041_337_81,
            0.995_489_8,
            0.0,
            0.896_013_7,
            -0.433_773_4,
            -0.094_868_36,
            0.0,
            9.901_531,
            -7.001_888,
            1.562_632,
            1.0,
        ],
        Projection::orthographic(19.980_977),
        Vec3::new(0.485_342, -0.506_192_85, -0.712_889_86),
        (0.6, 0.201_141),
    );
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_fast_methods_match(
        "plane orthographic under its roof at σ = 0.6:",
        &scene,
        &reference,
    );
}

/// `plane` at twice the tests' size seen from `world_from_camera` (column-major) through
/// `projection`, lit along `sun`, in open fog of (extinction, anisotropy) out to 70 m:
/// the fuzzed views.
fn fuzzed_plane(
    world_from_camera: [f32; 16],
    projection: Projection,
    sun: Vec3,
    (extinction, anisotropy): (f32, f32),
) -> Scene {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    scene.camera = Camera {
        world_from_camera: Mat4::from_cols_array(&world_from_camera),
        projection,
        clip_start: 0.1,
        clip_end: 1000.0,
        width: 2 * WIDTH,
        height: 2 * HEIGHT,
        pixel_aspect: 1.0,
        window: None,
    };
    scene.sun.direction = sun;
    scene.medium.extinction = extinction;
    scene.medium.anisotropy = anisotropy;
    scene.render.max_distance = 70.0;
    scene
}

/// Dense fog seen towards the sun: a ray's light comes from its first optical depth or
/// so, which near the sun crosses few texels however long the ray runs. Over so few
/// texels the prefiltered step's ringing and texel-sized errors near the camera do not
/// average out: `colonnade` read 3.9% off with prefiltering (2.7% with min-max) at
/// σ = 0.6 /m and 9.4% (4.9%) at 1.5 /m. Rays crossing fewer than `SHORT_STRETCH_TEXELS`
/// within their first `LOOKUP_DEPTH` are walked exactly.
#[test]
fn rays_in_dense_fog_count_only_their_first_optical_depth() {
    for extinction in [0.6, 1.5] {
        let mut scene = builtin_scene("colonnade").expect("built-in scene");
        scene.camera.width = 2 * WIDTH;
        scene.camera.height = 2 * HEIGHT;
        scene.render.adaptive_tolerance = 0.0;
        scene.medium.extinction = extinction;
        let reference = render_with(&scene, Method::Reference, 4096);
        assert_methods_within(
            &format!("colonnade at σ = {extinction}"),
            &scene,
            &reference,
            [(Method::MinMax, 0.02), (Method::Prefiltered, 0.02)],
        );
    }
}

/// More slices than the default, thinner than the sampled rays' spacing (fuzzed: `plane`
/// in dense fog, looking level across its ground with the sun behind): slices between the
/// border's sampled rays, and bands whose rays of one speed had been sampled along part of
/// their slices, had warps that held none of the keys their rays read, and read them half
/// lit. With 2,048 to 8,192 slices prefiltering was 6.0–26% off the reference (and 18%
/// with 4,096 at 1152×648); 1.4–1.5% now, as with the default's 1,024.
#[test]
fn slices_thinner_than_the_sampling_keep_their_keys() {
    let mut scene = fuzzed_plane(
        [
            0.973_901_7,
            0.226_970_27,
            0.0,
            0.0,
            0.007_722_92,
            -0.033_138_107,
            0.999_420_94,
            0.0,
            0.226_838_84,
            -0.973_337_7,
            -0.034_026_13,
            0.0,
            2.555_832_3,
            -4.833_460_5,
            2.290_027_4,
            1.0,
        ],
        Projection::pinhole(50.0),
        Vec3::new(-0.668_568_6, 0.534_366_9, -0.517_173_1),
        (0.6, -0.463_120_5),
    );
    scene.render.supersampling = 2;
    scene.render.near_plane_correction = false;
    let reference = render_with(&scene, Method::Reference, 4096);
    for slices in [0, 2048, 4096, 8192] {
        scene.render.epipolar_slices = slices;
        assert_method_within(
            &format!("plane in dense fog, {slices} slices:"),
            &scene,
            &reference,
            Method::Prefiltered,
            0.02,
        );
    }
}

/// `plane` seen from `world_from_camera` (column-major) at twice the tests' size, lit
/// along `sun`, in open fog of `extinction`, its roof's slots changed by a silhouette
/// operator of the given length: the fuzzed views from under the roof.
fn plane_under_its_roof(
    world_from_camera: [f32; 16],
    sun: Vec3,
    extinction: f32,
    (operation, length): (SilhouetteOp, f32),
) -> Scene {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    scene.camera.width = 2 * WIDTH;
    scene.camera.height = 2 * HEIGHT;
    scene.camera.world_from_camera = Mat4::from_cols_array(&world_from_camera);
    scene.sun.direction = sun;
    scene.medium.extinction = extinction;
    scene.style = Style {
        silhouette: Some(Silhouette {
            operation,
            length,
            ..Silhouette::default()
        }),
        ..Style::default()
    };
    scene
}

/// Dense fog seen from under a roof closed by a silhouette closing, looking out level
/// with the ground (fuzzed): a ray's light comes from past the roof's shadow, a few
/// optical depths out. Between two bands an octave apart, the blend of their averages,
/// whose weights decay as e^(−σt) of rays up to √2 faster or slower, read 54% off the
/// reference (+49% signed); with bands a third of an octave apart, 16% (+5%), the rest the
/// series' residue on rays that the roof leaves nearly dark (M = 64 halved it). Lookups
/// darker than `DARK_LOOKUP_VISIBILITY` are integrated exactly: 2.6% (+1.2%).
#[test]
fn dense_fog_from_under_a_closed_roof_keeps_its_light() {
    let mut scene = plane_under_its_roof(
        [
            0.484_350_17,
            -0.874_874_2,
            0.0,
            0.0,
            -0.035_138_45,
            -0.019_453_44,
            0.999_193_1,
            0.0,
            -0.874_168_3,
            -0.483_959_35,
            -0.040_164_01,
            0.0,
            -12.693_304,
            -6.577_117_6,
            0.320_010_2,
            1.0,
        ],
        Vec3::new(-0.387_404_26, -0.790_223_1, -0.474_831_94),
        0.2,
        (SilhouetteOp::Close, 0.4),
    );
    scene.render.supersampling = 2;
    let reference = render_with(&scene, Method::Reference, 4096);
    let fast = render_with(&scene, Method::Prefiltered, 4096);
    assert_finite(&fast);
    let (relative, mean) = error(&fast, &reference);
    let sum = |layers: &Layers| -> f64 {
        layers
            .volume
            .chunks(4)
            .map(|p| p[..3].iter().map(|&v| v as f64).sum::<f64>())
            .sum()
    };
    let bias = sum(&fast) / sum(&reference) - 1.0;
    println!(
        "dense fog under a closed roof: prefiltered error {:.2}%, bias {:+.2}% (mean radiance {mean:.4})",
        relative * 100.0,
        bias * 100.0
    );
    assert!(mean > 0.0);
    assert!(relative <= 0.05, "{:.2}%", relative * 100.0);
    assert!(bias.abs() <= 0.03, "bias {:+.2}%", bias * 100.0);
}

/// Denser fog (0.6 /m) under the slotted roof, looking level towards the sun through an
/// 85 mm lens, the roof's slots narrowed by a silhouette dilation (fuzzed): the shafts let
/// through 0.02–0.3% of the light, and the series' residue of about 0.5% of visibility
/// made the frame 36% off the reference (min-max 5.8%). Such dark lookups are integrated
/// exactly instead.
#[test]
fn nearly_dark_rays_in_dense_fog_are_integrated_exactly() {
    let mut scene = plane_under_its_roof(
        [
            0.922_434_2,
            0.386_154_3,
            0.0,
            0.0,
            -0.005_140_479,
            0.012_279_427,
            0.999_911_4,
            0.0,
            0.386_120_1,
            -0.922_352_5,
            0.013_311_982,
            0.0,
            5.878_086,
            -13.085_41,
            1.421_141,
            1.0,
        ],
        Vec3::new(0.093_502_84, -0.849_399_9, -0.519_400_6),
        0.6,
        (SilhouetteOp::Dilate, 0.3),
    );
    scene.camera.projection = Projection::pinhole(85.0);
    scene.medium.anisotropy = 0.208_648_26;
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_methods_within(
        "nearly dark rays in dense fog:",
        &scene,
        &reference,
        [(Method::MinMax, 0.1), (Method::Prefiltered, 0.05)],
    );
}

/// `plane`'s roof dilated along the view rays, in a thin fog box
/// ([`dilated_roof_in_a_thin_box`]): the series' smooth step read the rays passing just by
/// a slat about half lit all along its extrusion, and the frame 8.1% dark (min-max 0.41%).
/// Lookups whose weight lies mostly about the ray's key are integrated exactly instead.
#[test]
fn rays_beside_extruded_occluders_are_integrated_exactly() {
    let mut scene = builtin_scene("plane").expect("built-in scene");
    (scene.camera.width, scene.camera.height) = (2 * WIDTH, 2 * HEIGHT);
    dilated_roof_in_a_thin_box(&mut scene);
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_methods_within(
        "rays beside extruded occluders:",
        &scene,
        &reference,
        [(Method::MinMax, 0.01), (Method::Prefiltered, 0.01)],
    );
}

/// Inside `colonnade`, every surface within 5.3 m, in thin fog (0.01 /m) under a sun 50°
/// up (fuzzed): light reaches a corner of the frame only, through gaps that let through
/// under 3% of it, and the frame is nearly black. The dark-lookup rule does not apply in
/// thin open fog by itself, and prefiltering's residue (0.008–0.01 of visibility on rays
/// the reference has fully shadowed) read 18.7% off. The frame's probe finds it dark, and
/// its dark lookups are walked: 4.6% (min-max 1.9%) of a mean radiance of 2·10⁻⁶. Four
/// fifths of that light was the bias's sliver in front of the columns' unlit sides, which
/// rays now end before (`crepuscular::shadowed_end`): of the 4.5·10⁻⁷ left, in 300 of the
/// 83,000 pixels, the methods' error is as large as before in radiance (about 9·10⁻⁸ a
/// pixel), 19% and 10%.
#[test]
fn a_nearly_dark_frame_in_thin_fog_walks_its_dark_lookups() {
    let mut scene = builtin_scene("colonnade").expect("built-in scene");
    scene.camera.width = 2 * WIDTH;
    scene.camera.height = 2 * HEIGHT;
    scene.camera.world_from_camera = Mat4::from_cols_array(&[
        -0.834_497_7,
        -0.551_011_5,
        0.0,
        0.0,
        0.018_185_76,
        -0.027_542_03,
        0.999_455_2,
        0.0,
        -0.550_711_3,
        0.834_043,
        0.033_004_32,
        0.0,
        1.602_176_6,
        6.193_858,
        5.213_435,
        1.0,
    ]);
    scene.camera.projection = Projection::pinhole(85.0);
    scene.sun.direction = Vec3::new(0.096_583_98, 0.630_425_7, -0.770_217_5);
    scene.medium.extinction = 0.01;
    scene.medium.anisotropy = -0.366_523_62;
    scene.render.max_distance = 12.0;
    scene.render.near_plane_correction = false;
    let reference = render_with(&scene, Method::Reference, 4096);
    assert_methods_within(
        "a nearly dark frame in thin fog:",
        &scene,
        &reference,
        [(Method::MinMax, 0.12), (Method::Prefiltered, 0.22)],
    );
}

/// A sun below the horizon: its light travels upward, and the ground is the occluder of
/// nearly every ray that ends on it, which a lookup reads about half lit there (fuzzed
/// views read 14–947% off the reference). `auto` integrates those ends exactly, as `on`.
/// Since rays end their light before the ground's unlit side (`crepuscular::shadowed_end`),
/// the lookups no longer meet the sliver the bias lit there, and the two need only agree
/// within half a point (`tree` 0.69% and 0.53%; it was 0.6% against 1.9%). `plane`'s
/// frame is black now but for a mean radiance of 10⁻⁵ (1.5·10⁻⁴ before, the rest the
/// sliver), where both read half of it off: there they need only agree.
#[test]
fn light_from_below_integrates_ray_ends_exactly() {
    for name in ["tree", "plane"] {
        let mut scene = builtin_scene(name).expect("built-in scene");
        scene.camera.width = 2 * WIDTH;
        scene.camera.height = 2 * HEIGHT;
        let mut direction = scene.sun.direction;
        direction.z = direction.z.abs().max(0.3);
        scene.sun.direction = direction;
        let reference = render_with(&scene, Method::Reference, 4096);
        let auto = render_with(&scene, Method::Prefiltered, 4096);
        scene.render.exact_ray_ends = ExactRayEnds::On;
        let on = render_with(&scene, Method::Prefiltered, 4096);
        assert_eq!(
            auto.volume, on.volume,
            "{name}: auto is on under light from below"
        );
        scene.render.exact_ray_ends = ExactRayEnds::Off;
        let off = render_with(&scene, Method::Prefiltered, 4096);
        assert_finite(&auto);
        let ((relative, mean), (without, _)) = (error(&auto, &reference), error(&off, &reference));
        println!(
            "{name:>10} lit from below: prefiltered error {:.2}% ({:.2}% with ray ends looked up; mean radiance {mean:.5})",
            relative * 100.0,
            without * 100.0
        );
        assert!(mean > 0.0);
        if name != "plane" {
            assert!(relative <= 0.1, "{name}: {:.2}%", relative * 100.0);
        }
        assert!(relative <= without + 0.005, "{name}");
    }
}

/// Plain bilinear upsampling of samples taken at the same pixels, ignoring depth.
fn bilinear(low: &Layers, width: u32, height: u32, factor: u32) -> Vec<f32> {
    let mut out = vec![0.0f32; (width * height * 4) as usize];
    let half = (factor / 2) as f32;
    let axis = |p: u32, count: u32| {
        let u = ((p as f32 - half) / factor as f32).max(0.0);
        let a = (u.floor() as u32).min(count - 1);
        (a, (a + 1).min(count - 1), u - a as f32)
    };
    for y in 0..height {
        let (y0, y1, fy) = axis(y, low.height);
        for x in 0..width {
            let (x0, x1, fx) = axis(x, low.width);
            for c in 0..4 {
                let at = |i: u32, j: u32| low.volume[((j * low.width + i) * 4 + c) as usize];
                out[((y * width + x) * 4 + c) as usize] = (1.0 - fy)
                    * ((1.0 - fx) * at(x0, y0) + fx * at(x1, y0))
                    + fy * ((1.0 - fx) * at(x0, y1) + fx * at(x1, y1));
            }
        }
    }
    out
}

fn mean_abs_difference(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() as f64)
        .sum::<f64>()
        / a.len() as f64
}

#[test]
fn depth_aware_upsampling_beats_bilinear_at_edges() {
    use crepuscular::upsample::{joint_bilateral, samples_of};
    for name in ["tree", "colonnade"] {
        let (_, scene) = views(name).remove(0);
        let full = render_with(&scene, Method::MinMax, 1024);
        let factor = 4;
        let low = samples_of(&full, factor);
        let joint = joint_bilateral(&low, &full.depth, None, WIDTH, HEIGHT, factor).unwrap();
        let joint_error = mean_abs_difference(&joint.volume, &full.volume);
        let bilinear_error =
            mean_abs_difference(&bilinear(&low, WIDTH, HEIGHT, factor), &full.volume);
        println!("{name}: joint-bilateral {joint_error:.5}, bilinear {bilinear_error:.5}");
        assert!(
            joint_error < 0.8 * bilinear_error,
            "{name}: {joint_error} vs {bilinear_error}"
        );
    }
}

/// Torus's default view in a dense box of fog whose silhouette crosses the image against
/// the background: there the layers jump where no depth does.
fn torus_in_a_dense_box() -> Scene {
    let (_, mut scene) = views("torus").remove(0);
    scene.medium.extinction = 0.6;
    scene.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(1.5, -1.0, 2.5))
            * Mat4::from_rotation_z(0.6)
            * Mat4::from_scale(Vec3::new(3.0, 2.5, 2.0)),
    };
    scene
}

/// At a fog box's silhouette the samples either side sit at the same depth, so depth alone
/// blends lit fog out over the background. With an opacity guide (the exact opacity where
/// the samples' opacities spread) the pixels there blend radiance per unit opacity, and
/// the upsampled layers come several times closer to the full-resolution ones.
#[test]
fn an_opacity_guide_keeps_a_fog_box_silhouette_sharp() {
    use crepuscular::upsample::{joint_bilateral, opacity_guide, samples_of};
    let scene = torus_in_a_dense_box();
    let full = render_with(&scene, Method::Reference, 256);
    let (width, height) = (full.width, full.height);
    let exact = |x: u32, y: u32| full.volume[((y * width + x) * 4 + 3) as usize];
    for factor in [2, 4] {
        let low = samples_of(&full, factor);
        let guide = opacity_guide(&low, width, height, factor, exact)
            .unwrap()
            .expect("a silhouette");
        let guided =
            joint_bilateral(&low, &full.depth, Some(&guide), width, height, factor).unwrap();
        let depth_only = joint_bilateral(&low, &full.depth, None, width, height, factor).unwrap();
        let (guided_error, _) = error(&guided, &full);
        let (depth_only_error, _) = error(&depth_only, &full);
        let exact_pixels = guide.iter().filter(|&&o| o >= 0.0).count();
        println!(
            "1/{factor}: guided {:.3}%, depth only {:.3}%, {exact_pixels} exact opacities",
            guided_error * 100.0,
            depth_only_error * 100.0
        );
        assert_finite(&guided);
        assert!(exact_pixels > 0 && exact_pixels < guide.len() / 4);
        assert!(
            guided_error < 0.5 * depth_only_error,
            "1/{factor}: {guided_error} vs {depth_only_error}"
        );
    }
}

/// The frame's own opacity guide: a reduced frame of the dense box stays close to the
/// full-resolution frame, and its opacity is exact wherever the guide gave it.
#[test]
fn downsampled_evaluation_in_a_fog_box_stays_close_to_full_resolution() {
    let mut scene = torus_in_a_dense_box();
    scene.render.adaptive_tolerance = 0.0;
    let full = render_with(&scene, Method::Prefiltered, 256);
    // Depth alone, 1.5% and 5.2%.
    for (factor, bound) in [(2, 0.01), (4, 0.035)] {
        let mut reduced = scene.clone();
        reduced.render.downsample = factor;
        let up = render_with(&reduced, Method::Prefiltered, 256);
        assert_finite(&up);
        let (relative, _) = error(&up, &full);
        println!("dense box 1/{factor}: error {:.3}%", relative * 100.0);
        assert!(relative < bound, "1/{factor}: {relative}");
    }
}

#[test]
fn downsampled_evaluation_stays_close_to_full_resolution() {
    for name in BUILTIN_SCENES {
        let (_, scene) = views(name).remove(0);
        let full = render_with(&scene, Method::MinMax, 1024);
        for factor in [2, 4] {
            let mut reduced = scene.clone();
            reduced.render.downsample = factor;
            let up = render_with(&reduced, Method::MinMax, 1024);
            assert_finite(&up);
            assert_eq!(up.depth, full.depth, "the depth layer stays exact");
            let (relative, _) = error(&up, &full);
            println!("{name} 1/{factor}: error {:.3}%", relative * 100.0);
            assert!(
                relative < if factor == 2 { 0.03 } else { 0.06 },
                "{name} 1/{factor}: {relative}"
            );
        }
    }
}

/// Adaptive shading (the default) against shading every pixel, both fast methods, every
/// view: its interpolation moves the mean by at most 0.2% of the mean radiance and the
/// mean visibility by at most 0.002, where each pixel between shaded ones is interpolated
/// only when its neighbours agree within 1%. At 1920×1080 the built-in default views move
/// by at most 0.02%; at this size the same features span fewer pixels.
#[test]
fn adaptive_shading_stays_close_to_shading_every_pixel() {
    for name in BUILTIN_SCENES {
        for (view, scene) in views(name) {
            for method in [Method::MinMax, Method::Prefiltered] {
                let adaptive = render_with(&scene, method, 1024);
                let mut every = scene.clone();
                every.render.adaptive_tolerance = 0.0;
                let every = render_with(&every, method, 1024);
                assert_finite(&adaptive);
                assert_eq!(adaptive.depth, every.depth, "the depth layer stays exact");
                let (relative, _) = error(&adaptive, &every);
                let visibility = mean_abs_difference(&adaptive.visibility, &every.visibility);
                println!(
                    "{name:>10} {view:<12} {:<11} adaptive against every pixel {:.4}%, V̄ {visibility:.5}",
                    method.name(),
                    relative * 100.0
                );
                assert!(relative <= 0.002, "{name} {view} {method:?}: {relative}");
                assert!(
                    visibility <= 0.002,
                    "{name} {view} {method:?}: {visibility}"
                );
            }
        }
    }
}

/// The prefiltered method: at M = 32 it meets the bounds (2%, 4% on `plane`) in
/// every view, and its error falls as M grows in every view that it looks up. A view whose
/// rays all cross too few texels (`plane` sideways) is walked exactly at any M; at least
/// three views of each scene must show the trend.
#[test]
fn prefiltered_error_falls_with_more_bases() {
    let mut failures = Vec::new();
    for name in BUILTIN_SCENES {
        let mut trends = 0;
        for (view, scene) in views(name) {
            let reference = render_with(&scene, Method::Reference, 4096);
            let bound = if name == "plane" { 0.04 } else { 0.02 };
            let errors: Vec<f64> = [8, 32, 64]
                .iter()
                .map(|&bases| {
                    let mut scene = scene.clone();
                    scene.render.bases = bases;
                    let fast = render_with(&scene, Method::Prefiltered, 4096);
                    assert_finite(&fast);
                    // Around the sun, where slices crowd, the same bound holds at M = 32.
                    let block = scene.render.epipole_block as f64;
                    if let Some(keep) = near_sun(&scene, 2.5 * block).filter(|_| bases == 32) {
                        let (near, _) = error_where(&fast, &reference, keep);
                        println!(
                            "{name:>10} {view:<12} M=32 near the sun {:.3}%",
                            near * 100.0
                        );
                        if near > bound {
                            failures
                                .push(format!("{name} {view} near the sun: {:.3}%", near * 100.0));
                        }
                    }
                    error(&fast, &reference).0
                })
                .collect();
            println!(
                "{name:>10} {view:<12} M=8 {:.2}%  M=32 {:.2}%  M=64 {:.2}%",
                errors[0] * 100.0,
                errors[1] * 100.0,
                errors[2] * 100.0
            );
            let walked = errors[0] == errors[1] && errors[1] == errors[2];
            if !walked {
                trends += 1;
                if !(errors[0] > errors[1] && errors[1] >= 0.95 * errors[2]) {
                    failures.push(format!(
                        "{name} {view}: error does not fall with M: {errors:?}"
                    ));
                }
            }
            if errors[1] > bound {
                failures.push(format!(
                    "{name} {view}: {:.2}% at M = 32, above {:.0}%",
                    errors[1] * 100.0,
                    bound * 100.0
                ));
            }
        }
        if trends < 3 {
            failures.push(format!("{name}: only {trends} views looked up"));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// The ray-marched block around an on-screen sun is a fixed number of pixels, so small
/// test images hide much of the near-sun region in it. At 3× the size, where the sun is in
/// view the error stays within the same bounds. One warp per slice once measured 1.8%,
/// 2.9% and 4.0% on colonnade's default view at 1×, 2× and 4× the size.
#[test]
fn prefiltered_error_holds_with_more_pixels_near_the_sun() {
    let mut failures = Vec::new();
    for (name, wanted) in [
        ("colonnade", "default"),
        ("colonnade", "sun in view"),
        ("tree", "sun in view"),
    ] {
        let (view, scene) = views_at(name, 3 * WIDTH, 3 * HEIGHT)
            .into_iter()
            .find(|(view, _)| *view == wanted)
            .expect("the view exists");
        let reference = render_with(&scene, Method::Reference, 4096);
        let fast = render_with(&scene, Method::Prefiltered, 4096);
        assert_finite(&fast);
        let (error, _) = error(&fast, &reference);
        println!("{name:>10} {view:<12} at 3×: {:.2}%", error * 100.0);
        if error > 0.02 {
            failures.push(format!("{name} {view} at 3×: {:.2}%", error * 100.0));
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// A nearly black frame: `plane` in fog of 0.6 /m under a dilated silhouette (a fuzzed
/// view, mean radiance 1.5·10⁻⁵, visibility 6·10⁻⁵). Its rays see less light before an
/// optical depth of 10, where exact walks stop, than the e^−10 after it; prefiltering,
/// which walks such dark rays, read 14% dark. In a frame the probe finds nearly dark, a
/// walk that is still dark there goes on to e^−20.
#[test]
fn nearly_black_rays_keep_the_light_from_far_along() {
    let mut scene = Scene::from_json(include_str!("data/nearly_black_plane.json")).unwrap();
    scene.camera.width = 192;
    scene.camera.height = 108;
    let reference = render_with(&scene, Method::Reference, 4096);
    let (relative, mean) = error(&render_with(&scene, Method::Prefiltered, 4096), &reference);
    println!(
        "prefiltered: {:.2}% (mean radiance {mean:.2e})",
        relative * 100.0
    );
    assert!(mean < 1e-4, "the view is nearly black: {mean}");
    assert!(relative < 0.03, "prefiltered: {relative}");
}

/// Non-square pixels: a 2:1 anamorphic squeeze, and pixels twice as tall as wide. The
/// epipolar lines, the adaptive lattices and the rectification's slices are laid out in
/// pixel coordinates, which then stretch the view unevenly; the fast methods keep the
/// bounds they keep on square pixels, with the sun in the view and without.
#[test]
fn non_square_pixels_keep_the_fast_methods_within_bounds() {
    for name in ["tree", "colonnade"] {
        for (view, mut scene) in views_at(name, 2 * WIDTH, 2 * HEIGHT) {
            if !matches!(view, "default" | "sun in view") {
                continue;
            }
            for aspect in [2.0, 0.5] {
                scene.camera.pixel_aspect = aspect;
                // About as many square units across as before.
                scene.camera.width = (2.0 * WIDTH as f32 / aspect) as u32;
                let reference = render_with(&scene, Method::Reference, 4096);
                assert_methods_within(
                    &format!("{name:>10} {view}, pixels {aspect}:1"),
                    &scene,
                    &reference,
                    [(Method::MinMax, 0.01), (Method::Prefiltered, 0.02)],
                );
            }
        }
    }
}

/// A window (a render region) renders the frame's pixels within it: the same rays and a
/// shadow map fitted to the whole frame, so the reference's pixels are the frame's (a map
/// fitted to the narrower view was sharper: colonnade's window read 2.4% off its frame),
/// and the fast methods keep their bounds, through anamorphic pixels too. (Their slices
/// are laid over the window, so they differ from the frame's by their own error.)
#[test]
fn a_window_renders_the_frames_pixels() {
    for name in ["tree", "colonnade"] {
        let mut scene = builtin_scene(name).expect("built-in scene");
        scene.camera.width = 2 * WIDTH;
        scene.camera.height = 2 * HEIGHT;
        scene.camera.pixel_aspect = 1.5;
        let (x, y, width, height) = (61, 37, 173, 101);
        let whole = render_with(&scene, Method::Reference, 1024);
        let mut windowed = scene.clone();
        windowed.camera.window = Some(crepuscular::scene::PixelWindow {
            x,
            y,
            width,
            height,
        });
        let part = render_with(&windowed, Method::Reference, 1024);
        assert_eq!((part.width, part.height), (width, height));
        let (mut difference, mut total) = (0.0, 0.0);
        for row in 0..height {
            for column in 0..width {
                let a = part.volume_rgba(column, row);
                let b = whole.volume_rgba(column + x, row + y);
                difference += (0..4).map(|c| (a[c] - b[c]).abs() as f64).sum::<f64>();
                total += (0..4).map(|c| b[c] as f64).sum::<f64>();
            }
        }
        assert!(difference / total < 1e-5, "{name}: {}", difference / total);
        assert_methods_within(
            &format!("{name:>10} window"),
            &windowed,
            &part,
            [(Method::MinMax, 0.01), (Method::Prefiltered, 0.02)],
        );
    }
}
