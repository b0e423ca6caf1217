//! Styles through the whole pipeline: occluder operators with every method, transfer
//! functions on the rendered layers, and style presets as files.

use std::path::Path;

use crepuscular::camera::CameraModel;
use crepuscular::scene::{Method, Scene};
use crepuscular::shadow_map::ShadowMap;
use crepuscular::silhouette::SilhouetteOp;
use crepuscular::style::{HoleFilling, Silhouette};
use crepuscular::transfer_function::{DepthRange, TfLayer, TfMode, TransferFunction};
use crepuscular::{builtin_scene, render_scene, Error, Layers, RenderControl, Style};
use glam::DVec3;

const WIDTH: u32 = 240;
const HEIGHT: u32 = 135;

fn scene(name: &str, method: Method) -> Scene {
    let mut scene = builtin_scene(name).expect("built-in scene");
    scene.camera.width = WIDTH;
    scene.camera.height = HEIGHT;
    scene.render.method = method;
    scene.render.steps = 512;
    scene
}

fn render(scene: &Scene, style: &Style) -> Layers {
    let mut scene = scene.clone();
    scene.style = style.clone();
    render_scene(&scene, &RenderControl::new()).expect("render succeeds")
}

fn closing(radius: f32) -> Style {
    Style {
        closing: Some(HoleFilling {
            radius,
            ..HoleFilling::default()
        }),
        ..Style::default()
    }
}

fn presets() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/presets")
}

/// The torus' hole is 1.4 m across its axis (major radius 2, minor 0.6): a closing at
/// least that wide fills it in the scattering map, a narrower one leaves it open.
#[test]
fn closing_fills_the_torus_hole_only_when_wide_enough() {
    let scene = scene("torus", Method::Prefiltered);
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
    let centre = shadow
        .texel_from_world
        .transform_point3(DVec3::new(0.0, 0.0, 5.0));
    let at_centre =
        |map: &ShadowMap| map.depth[centre.y as usize * map.size as usize + centre.x as usize];
    // Through the hole the sun sees the ground, metres below the ring.
    let open = at_centre(&shadow);
    let ring = shadow
        .texel_from_world
        .transform_point3(DVec3::new(0.0, 0.0, 5.0))
        .z as f32;
    assert!(
        open > ring + 1.0,
        "the hole is open: {open} vs the ring at {ring}"
    );
    let narrow = closing(0.5).scattering_map(&shadow, &camera).unwrap();
    assert_eq!(at_centre(&narrow), open, "a 0.5 m closing keeps it");
    let wide = closing(1.6).scattering_map(&shadow, &camera).unwrap();
    assert!(
        (at_centre(&wide) - ring).abs() < 1.0,
        "a 1.6 m closing fills it at the ring's depth: {} vs {ring}",
        at_centre(&wide)
    );
    // The beauty's map is a different object: untouched.
    assert_eq!(at_centre(&shadow), open);
}

/// With every method, a closing wider than the hole takes the hole's shaft away: V̄ on
/// the rays that saw it drops to the level of the ring's shadow around it, while a
/// narrower closing leaves it.
#[test]
fn closing_removes_the_shaft_with_every_method() {
    for method in Method::ALL {
        let scene = scene("torus", method);
        let physical = render(&scene, &Style::default());
        let wide = render(&scene, &closing(1.6));
        let narrow = render(&scene, &closing(0.5));
        let shaft: Vec<usize> = (0..physical.visibility.len())
            .filter(|&i| physical.visibility[i] - wide.visibility[i] > 0.02)
            .collect();
        assert!(
            shaft.len() > physical.visibility.len() / 200,
            "{method:?}: the hole's shaft covers {} pixels",
            shaft.len()
        );
        let mean = |layers: &Layers| {
            shaft
                .iter()
                .map(|&i| layers.visibility[i] as f64)
                .sum::<f64>()
                / shaft.len() as f64
        };
        let (before, filled, kept) = (mean(&physical), mean(&wide), mean(&narrow));
        assert!(before - filled > 0.05, "{method:?}: V̄ {before} → {filled}");
        assert!(
            (before - kept).abs() < 0.2 * (before - filled),
            "{method:?}: the narrow closing changed V̄ {before} → {kept}"
        );
        // Camera depth, and so what the beauty shows, never changes.
        assert_eq!(physical.depth, wide.depth);
    }
}

/// Mean absolute difference between horizontally and vertically adjacent pixels'
/// radiance, relative to the mean radiance: dimming the shafts alone does not change it.
fn edge_contrast(layers: &Layers) -> f64 {
    let (w, h) = (layers.width as usize, layers.height as usize);
    let luminance = |i: usize| {
        let v = &layers.volume[4 * i..4 * i + 3];
        0.2126 * v[0] as f64 + 0.7152 * v[1] as f64 + 0.0722 * v[2] as f64
    };
    let mean = (0..w * h).map(luminance).sum::<f64>() / (w * h) as f64;
    let mut total = 0.0;
    for y in 0..h - 1 {
        for x in 0..w - 1 {
            let i = y * w + x;
            total +=
                (luminance(i) - luminance(i + 1)).abs() + (luminance(i) - luminance(i + w)).abs();
        }
    }
    total / ((w - 1) * (h - 1)) as f64 / mean
}

#[test]
fn silhouettes_harden_shafts_and_leave_what_the_camera_sees() {
    let scene = scene("colonnade", Method::Prefiltered);
    let physical = render(&scene, &Style::default());
    let extruded = render(
        &scene,
        &Style {
            silhouette: Some(Silhouette {
                operation: SilhouetteOp::Close,
                length: 4.0,
                ..Silhouette::default()
            }),
            ..Style::default()
        },
    );
    assert_eq!(physical.depth, extruded.depth, "surfaces keep their depth");
    let mean_visibility = |l: &Layers| {
        l.visibility.iter().map(|&v| v as f64).sum::<f64>() / l.visibility.len() as f64
    };
    assert!(mean_visibility(&extruded) < mean_visibility(&physical));
    let (before, after) = (edge_contrast(&physical), edge_contrast(&extruded));
    assert!(
        after > 1.2 * before,
        "edge contrast {before:.3e} → {after:.3e}"
    );
}

#[test]
fn holes_open_only_the_chosen_objects() {
    let scene = scene("tree", Method::Prefiltered);
    let physical = render(&scene, &Style::default());
    let style: Style =
        Style::load(&presets().join("holes-in-tree.json")).expect("the preset loads");
    let holed = render(&scene, &style);
    let mean = |l: &Layers| {
        l.visibility.iter().map(|&v| v as f64).sum::<f64>() / l.visibility.len() as f64
    };
    let brighter = (0..holed.pixel_count())
        .filter(|&i| holed.visibility[i] > physical.visibility[i] + 0.02)
        .count();
    assert!(
        brighter > holed.pixel_count() / 100,
        "leaves let more light through on {brighter} pixels"
    );
    assert!(mean(&holed) > mean(&physical));
    // An id no mesh carries changes nothing.
    let mut elsewhere = style.clone();
    elsewhere.holes.as_mut().unwrap().objects = vec![999];
    assert_eq!(render(&scene, &elsewhere).volume, physical.volume);
    // Animated: another time gives other holes; the same time the same frame.
    let later = Style {
        time: 20.0,
        ..style.clone()
    };
    assert_ne!(render(&scene, &later).visibility, holed.visibility);
    assert_eq!(render(&scene, &style).volume, holed.volume);
}

fn tf(mode: TfMode, layers: Vec<TfLayer>) -> Style {
    Style {
        tf: Some(TransferFunction::new(
            mode,
            DepthRange {
                near: 0.0,
                far: 60.0,
            },
            layers,
        )),
        ..Style::default()
    }
}

#[test]
fn an_identity_transfer_function_reproduces_the_physical_render() {
    let scene = scene("torus", Method::Prefiltered);
    let physical = render(&scene, &Style::default());
    let white = TfLayer::Solid {
        opacity: 1.0,
        blend: Default::default(),
        color: [1.0, 1.0, 1.0, 1.0],
    };
    let identity = render(&scene, &tf(TfMode::Monochrome, vec![white]));
    assert_eq!(identity.volume, physical.volume);
    // A red TF in colour mode keeps alpha (attenuation) and recolours the light.
    let red = TfLayer::Solid {
        opacity: 1.0,
        blend: Default::default(),
        color: [1.0, 0.0, 0.0, 1.0],
    };
    let recoloured = render(&scene, &tf(TfMode::Color, vec![red]));
    for (r, p) in recoloured.volume.chunks(4).zip(physical.volume.chunks(4)) {
        assert_eq!(r[3], p[3]);
        assert_eq!(r[1], 0.0);
        assert!((r[0] - p[0]).abs() <= 1e-5 * p[0].abs().max(1.0));
    }
}

#[test]
fn a_constraint_on_a_point_off_screen_is_named() {
    let scene = scene("torus", Method::Prefiltered);
    let text = r#"{"version": 1, "tf": {"depth_range": {"near": 0, "far": 60}, "layers": [
        {"kind": "diffusion", "constraints": [
            {"position": [0.5, 0.5], "color": [1, 0, 0, 1], "world_point": [0, 0, -500]}
        ]}]}}"#;
    let mut styled = scene.clone();
    styled.style = Style::from_json(text).expect("a valid style");
    let err = render_scene(&styled, &RenderControl::new()).unwrap_err();
    let message = err.to_string();
    assert!(
        message.contains("style.tf.layers[0].constraints[0].world_point"),
        "{message}"
    );
}

#[test]
fn presets_round_trip_and_bad_ones_name_the_field() {
    let mut count = 0;
    for entry in std::fs::read_dir(presets()).expect("examples/presets") {
        let path = entry.unwrap().path();
        let style = Style::load(&path).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
        assert!(
            !style.is_physical(),
            "{} departs from physics",
            path.display()
        );
        assert_eq!(Style::from_json(&style.to_json()).unwrap(), style);
        count += 1;
    }
    assert!(count >= 4);
    let cases = [
        (
            r#"{"version": 1, "closing": {"radiuss": 1}}"#,
            "style.closing",
        ),
        (
            r#"{"version": 1, "closing": {"radius": -1}}"#,
            "style.closing.radius",
        ),
        (
            r#"{"version": 1, "silhouette": {"length": 1e40}}"#,
            "style.silhouette.length",
        ),
        (r#"{"version": 2}"#, "style.version"),
        (
            r#"{"version": 1, "holes": {"octaves": 0}}"#,
            "style.holes.octaves",
        ),
        (
            r#"{"version": 1, "tf": {"depth_range": {"near": 5, "far": 1}}}"#,
            "style.tf.depth_range.far",
        ),
        (r#"{"version": 1, "colour": {}}"#, "colour"),
    ];
    for (text, field) in cases {
        let err = Style::from_json(text).expect_err(text);
        assert!(err.to_string().contains(field), "{text}: {err}");
    }
    let missing = Style::load(Path::new("no/such/preset.json")).unwrap_err();
    assert!(matches!(missing, Error::Io { .. }));
}
