//! Projective rectification (`render.rectification`): the fast methods on a projectively
//! rectified map against the reference, where the view allows one; the error where it
//! does not; and what `auto` picks on the built-in scenes.

mod common;

use common::radiance_error;
use crepuscular::camera::CameraModel;
use crepuscular::epipolar::{EpipolarMap, RectifyDesc};
use crepuscular::render::FlatGeometry;
use crepuscular::scene::{Camera, Method, Projection, Rectification, Scene};
use crepuscular::shadow_map::ShadowMap;
use crepuscular::{builtin_scene, render_scene, Error, Layers, RenderControl, BUILTIN_SCENES};
use glam::Vec3;

const WIDTH: u32 = 192;
const HEIGHT: u32 = 108;

/// Views across the sun's azimuth at the shafts under each scene's subject (everything
/// but the ground), with the frustum clipped to the subject's depth range: shallow
/// frusta with the sun well off the image, where projective rectification is valid.
/// - "across": 24 mm from two subject radii, looking half a radius down the light;
/// - "across narrow": 50 mm from two and a half radii, a third of a radius down.
fn across_views(name: &str) -> Vec<(&'static str, Scene)> {
    let mut scene = builtin_scene(name).expect("built-in scene");
    let towards_sun = -scene.sun.direction.normalize();
    let (low, high) = scene
        .meshes
        .iter()
        .filter(|m| m.object_id != 1)
        .flat_map(|m| &m.positions)
        .fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p))),
        );
    let centre = 0.5 * (low + high);
    let radius = 0.5 * (high - low).length();
    let horizontal = Vec3::new(towards_sun.x, towards_sun.y, 0.0).normalize();
    let across = Vec3::new(-horizontal.y, horizontal.x, 0.0);
    [
        ("across", 0.5, 2.0, 24.0),
        ("across narrow", 0.3, 2.5, 50.0),
    ]
    .into_iter()
    .map(|(view, down_light, distance, focal)| {
        let target = centre - towards_sun * (down_light * radius);
        let target = Vec3::new(target.x, target.y, target.z.max(1.0));
        let eye = target + across * (distance * radius) + Vec3::new(0.0, 0.0, 0.5);
        scene.camera = Camera::pinhole_looking_at(eye, target, focal, WIDTH, HEIGHT);
        scene.camera.clip_start = (distance - 1.0) * radius;
        scene.render.max_distance = (distance + 1.0) * radius;
        (view, scene.clone())
    })
    .collect()
}

fn render_with(scene: &Scene, method: Method, rectification: Rectification) -> Layers {
    let mut scene = scene.clone();
    scene.render.method = method;
    scene.render.steps = 4096;
    scene.render.rectification = rectification;
    render_scene(&scene, &RenderControl::new()).expect("render succeeds")
}

/// The bounds the epipolar layout is held to (tests/fast_methods.rs): min-max 1%,
/// prefiltering at M = 32 2%, twice those on `plane`'s slits.
fn bound(scene: &str, method: Method) -> f64 {
    let base = if method == Method::MinMax { 0.01 } else { 0.02 };
    if scene == "plane" {
        2.0 * base
    } else {
        base
    }
}

/// The map `rectification` gives for the scene's view and method.
fn rectified(scene: &Scene, method: Method, rectification: Rectification) -> EpipolarMap {
    let camera = CameraModel::new(&scene.camera);
    let geometry = FlatGeometry::from_scene(scene);
    let shadow = ShadowMap::of_scene_geometry(scene, &camera, &geometry).unwrap();
    let desc = match method {
        Method::MinMax => RectifyDesc::min_max(scene.render.epipolar_slices),
        _ => RectifyDesc::prefiltered(scene.render.epipolar_slices),
    };
    EpipolarMap::rectify(
        &camera,
        &shadow,
        &geometry.view(),
        scene.sun.direction.as_dvec3(),
        scene.render.max_distance as f64,
        rectification,
        &desc,
    )
    .expect("a valid choice")
    .expect("a pinhole camera rectifies")
}

#[test]
fn fast_methods_on_the_projective_map_match_the_reference() {
    let mut failures = Vec::new();
    for name in BUILTIN_SCENES {
        for (view, scene) in across_views(name) {
            let reference = render_with(&scene, Method::Reference, Rectification::Epipolar);
            let visibility = reference.visibility.iter().map(|&v| v as f64).sum::<f64>()
                / reference.visibility.len() as f64;
            assert!(
                visibility < 0.9,
                "{name} {view}: mostly lit ({visibility:.3}), a weak test"
            );
            for method in [Method::MinMax, Method::Prefiltered] {
                assert!(rectified(&scene, method, Rectification::Projective).is_projective());
                let epipolar = radiance_error(
                    &render_with(&scene, method, Rectification::Epipolar),
                    &reference,
                );
                let projective = radiance_error(
                    &render_with(&scene, method, Rectification::Projective),
                    &reference,
                );
                println!(
                    "{name:>10} {view:<14} {:<12} epipolar {:.3}%  projective {:.3}%  (visibility {visibility:.3})",
                    method.name(),
                    epipolar * 100.0,
                    projective * 100.0
                );
                if projective > bound(name, method) {
                    failures.push(format!(
                        "{name} {view} {}: {:.3}%",
                        method.name(),
                        projective * 100.0
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "above the bound: {failures:?}");
}

fn expect_rectification_error(scene: &Scene, mentions: &str) {
    for method in [Method::MinMax, Method::Prefiltered] {
        let mut scene = scene.clone();
        scene.render.method = method;
        scene.render.rectification = Rectification::Projective;
        match render_scene(&scene, &RenderControl::new()) {
            Err(Error::InvalidInput { field, reason }) => {
                assert_eq!(field, "render.rectification");
                assert!(reason.contains(mentions), "{reason}");
            }
            other => panic!("expected an invalid-input error, got {:?}", other.err()),
        }
        // `auto` falls back to the epipolar layout on the same view.
        scene.render.rectification = Rectification::Auto;
        assert!(render_scene(&scene, &RenderControl::new()).is_ok());
    }
}

#[test]
fn forcing_projective_where_it_cannot_work_names_the_setting() {
    // The colonnade's default view looks into its low sun.
    let mut scene = builtin_scene("colonnade").expect("built-in scene");
    scene.camera.width = WIDTH;
    scene.camera.height = HEIGHT;
    scene.render.steps = 64;
    expect_rectification_error(&scene, "sun");
    // Looking down the light, with the sun at one's back: the anti-sun point is in view.
    let eye = Vec3::new(0.0, -4.0, 20.0);
    scene.camera = Camera::pinhole_looking_at(
        eye,
        eye + scene.sun.direction + Vec3::new(0.0, 0.0, -0.1),
        35.0,
        WIDTH,
        HEIGHT,
    );
    expect_rectification_error(&scene, "anti-sun");
    scene.camera.projection = Projection::orthographic(20.0);
    expect_rectification_error(&scene, "pinhole");
}

#[test]
fn occluder_operators_keep_the_epipolar_layout() {
    // A view on which `auto` rasterizes a projective map for the physical look.
    let (_, mut scene) = across_views("tree")
        .into_iter()
        .find(|(view, _)| *view == "across narrow")
        .expect("the narrow view");
    for method in [Method::MinMax, Method::Prefiltered] {
        assert!(rectified(&scene, method, Rectification::Auto).is_projective());
    }
    let physical = render_with(&scene, Method::Reference, Rectification::Epipolar);
    scene.style = serde_json::from_str(include_str!("../../examples/presets/holes-in-tree.json"))
        .expect("a valid preset");
    let reference = render_with(&scene, Method::Reference, Rectification::Epipolar);
    let holes = radiance_error(&physical, &reference);
    assert!(
        holes > 0.05,
        "the holes change the image by {holes:.3} only"
    );
    // The projective map is rasterized from the geometry, which has no holes: `auto`
    // resamples the shadow map they were cut into.
    for method in [Method::MinMax, Method::Prefiltered] {
        let fast = radiance_error(
            &render_with(&scene, method, Rectification::Auto),
            &reference,
        );
        println!(
            "{}: {:.3}% (the holes: {:.1}%)",
            method.name(),
            fast * 100.0,
            holes * 100.0
        );
        assert!(
            fast <= bound("tree", method),
            "{}: {fast:.4}",
            method.name()
        );
    }
    expect_rectification_error(&scene, "occluder operators");
}

#[test]
fn auto_picks_projective_only_for_shallow_valid_views() {
    let mut picked = Vec::new();
    for name in BUILTIN_SCENES {
        let default_view = builtin_scene(name).expect("built-in scene");
        let mut views = vec![("default", default_view)];
        views.extend(across_views(name));
        for (view, scene) in views {
            for method in [Method::MinMax, Method::Prefiltered] {
                let projective = rectified(&scene, method, Rectification::Auto).is_projective();
                println!(
                    "{name:>10} {view:<14} {:<12} auto: {}",
                    method.name(),
                    if projective { "projective" } else { "epipolar" }
                );
                picked.push((name, view, method, projective));
            }
        }
    }
    let count = |view: &str, method: Method| {
        picked
            .iter()
            .filter(|(_, v, m, p)| *v == view && *m == method && *p)
            .count()
    };
    // The default views reach from a near plane a few centimetres away to tens of metres:
    // their far columns would cover hundreds of texels.
    for method in [Method::MinMax, Method::Prefiltered] {
        assert_eq!(count("default", method), 0, "{}", method.name());
        assert_eq!(
            count("across narrow", method),
            BUILTIN_SCENES.len(),
            "{}",
            method.name()
        );
    }
    // The wider view's far plane is about 3.1 times as far as its near plane: sharp
    // enough for min-max's two samples per texel (prefiltering's one is borderline).
    assert_eq!(count("across", Method::MinMax), BUILTIN_SCENES.len());
}
