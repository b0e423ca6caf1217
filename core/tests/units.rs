//! Scene units and placement: a scene scaled about the origin, with its extinction divided
//! by the same factor, has the same optical depths everywhere, so every method must render
//! the same radiance, and the same depths times the factor. Scenes from USD stages in
//! centimetres and from Blender in metres differ in just this way; any length compared
//! with a fixed constant (an epsilon, a bias, a step) would break it. A scene moved far
//! from the world's origin must render as it does near it.

use crepuscular::holes::HolesDesc;
use crepuscular::scene::{Extent, Method, Projection, Rectification, Scene};
use crepuscular::silhouette::SilhouetteOp;
use crepuscular::style::{HoleFilling, Silhouette};
use crepuscular::transfer_function::{
    ColorStop, DepthRange, GradientShape, TfLayer, TfMode, TransferFunction,
};
use crepuscular::{builtin_scene, render_scene, Layers, RenderControl, BUILTIN_SCENES};
use glam::{Mat4, Vec3};

const WIDTH: u32 = 160;
const HEIGHT: u32 = 90;

/// `scene` scaled by `factor` about the origin: every length, every placement, the reach
/// and the clip distances; extinction, per unit length, divided by it.
fn scaled(scene: &Scene, factor: f32) -> Scene {
    let mut scene = scene.clone();
    place(&mut scene, Mat4::from_scale(Vec3::splat(factor)));
    // The camera's rotation stays a rotation: only its position moves.
    let camera = &mut scene.camera;
    camera.world_from_camera.w_axis = (camera.world_from_camera.w_axis.truncate() * factor)
        .extend(camera.world_from_camera.w_axis.w);
    camera.clip_start *= factor;
    camera.clip_end *= factor;
    if let Projection::Orthographic { ortho_scale, .. } = &mut camera.projection {
        *ortho_scale *= factor;
    }
    scene.medium.extinction /= factor;
    scene.render.max_distance *= factor;
    scene.render.shadow_bias = scene.render.shadow_bias.map(|bias| bias * factor);
    // The occluder operators' sizes and a transfer function's depth range are in scene
    // units too.
    let style = &mut scene.style;
    if let Some(tf) = &mut style.tf {
        tf.depth_range.near *= factor;
        tf.depth_range.far *= factor;
    }
    if let Some(closing) = &mut style.closing {
        closing.radius *= factor;
    }
    if let Some(silhouette) = &mut style.silhouette {
        silhouette.length *= factor;
    }
    if let Some(holes) = &mut style.holes {
        holes.frequency /= factor;
        holes.pivot = holes.pivot.map(|coordinate| coordinate * factor);
    }
    scene
}

/// Every mesh and the box of `scene` transformed by `world_from_world`.
fn place(scene: &mut Scene, world_from_world: Mat4) {
    for mesh in &mut scene.meshes {
        mesh.world_from_object = world_from_world * mesh.world_from_object;
    }
    if let Extent::Box { world_from_cube } = &mut scene.medium.extent {
        *world_from_cube = world_from_world * *world_from_cube;
    }
}

fn render(scene: &Scene, method: Method) -> Layers {
    let mut scene = scene.clone();
    scene.render.method = method;
    render_scene(&scene, &RenderControl::new()).expect("render succeeds")
}

/// Mean absolute difference of two layers over the mean magnitude of the first, with the
/// second's values divided by `unit` first.
fn relative_difference(expected: &[f32], actual: &[f32], unit: f64) -> f64 {
    assert_eq!(expected.len(), actual.len());
    let (mut difference, mut total) = (0.0f64, 0.0f64);
    for (&e, &a) in expected.iter().zip(actual) {
        difference += (e as f64 - a as f64 / unit).abs();
        total += (e as f64).abs();
    }
    difference / total.max(f64::MIN_POSITIVE)
}

/// How far, relative, a scaled scene's radiance and depths may move: rounding alone. Before
/// prefiltering's keys were made free of units, its frames moved by up to 0.26%
/// (colonnade at 100×); every method now moves by at most 1e-6.
const BOUND: f64 = 1e-4;

/// Each method's layers at `factor` against its own at scale 1: radiance and opacity
/// within [`BOUND`], depths too once divided by the factor.
fn assert_unit_free(label: &str, scene: &Scene) {
    for method in [Method::Reference, Method::MinMax, Method::Prefiltered] {
        let base = render(scene, method);
        for factor in [0.01, 100.0] {
            let layers = render(&scaled(scene, factor), method);
            let volume = relative_difference(&base.volume, &layers.volume, 1.0);
            let depth = relative_difference(&base.depth, &layers.depth, factor as f64);
            eprintln!(
                "{label} {method:?} ×{factor}: volume {:.4}% depth {:.2e}",
                100.0 * volume,
                depth
            );
            assert!(
                volume <= BOUND,
                "{label}, {method:?}, scaled by {factor}: volume differs by {:.4}%",
                100.0 * volume
            );
            assert!(
                depth <= BOUND,
                "{label}, {method:?}, scaled by {factor}: depth differs by {depth:.2e}"
            );
        }
    }
}

fn small(name: &str) -> Scene {
    let mut scene = builtin_scene(name).expect("built-in scene");
    scene.camera.width = WIDTH;
    scene.camera.height = HEIGHT;
    scene.render.steps = 512;
    scene
}

#[test]
fn built_in_scenes_render_the_same_in_any_unit() {
    for name in BUILTIN_SCENES {
        assert_unit_free(name, &small(name));
    }
}

#[test]
fn box_media_other_layouts_and_set_biases_render_the_same_in_any_unit() {
    let mut boxed = small("tree");
    boxed.medium.extinction = 0.3;
    boxed.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(0.5, 0.0, 2.5))
            * Mat4::from_scale(Vec3::new(5.0, 4.0, 2.5)),
    };
    assert_unit_free("tree in a box", &boxed);
    let mut orthographic = small("colonnade");
    orthographic.camera.projection = Projection::orthographic(20.0);
    orthographic.render.shadow_bias = Some(0.05);
    assert_unit_free("orthographic colonnade", &orthographic);
    let mut projective = small("plane");
    projective.render.rectification = Rectification::Projective;
    assert_unit_free("plane rectified projectively", &projective);
}

/// That `styled` renders more than 0.5% away from its scene without the style (a style that
/// did nothing would not move it at all), so that comparing it across units tests the
/// operators' sizes.
fn assert_styled(label: &str, styled: &Scene) {
    let plain = Scene {
        style: Default::default(),
        ..styled.clone()
    };
    let change = relative_difference(
        &render(&plain, Method::Reference).volume,
        &render(styled, Method::Reference).volume,
        1.0,
    );
    eprintln!(
        "{label}: the style changes the frame by {:.2}%",
        100.0 * change
    );
    assert!(
        change > 0.005,
        "{label}: the style changes the frame by {change:.2e}"
    );
}

#[test]
fn styles_sized_in_scene_units_render_the_same_in_any_unit() {
    let mut closed = small("tree");
    closed.style.closing = Some(HoleFilling {
        radius: 0.8,
        ..HoleFilling::default()
    });
    closed.style.silhouette = Some(Silhouette {
        operation: SilhouetteOp::Close,
        length: 1.5,
        length_texels: None,
    });
    assert_styled("tree, closed and extruded", &closed);
    assert_unit_free("tree, closed and extruded", &closed);
    let mut holed = small("colonnade");
    holed.style.holes = Some(HolesDesc {
        frequency: 0.05,
        pivot: [1.0, -2.0, 0.5],
        objects: vec![2, 3],
        ..HolesDesc::default()
    });
    assert_styled("colonnade with holes", &holed);
    assert_unit_free("colonnade with holes", &holed);
    // Colour by depth: blue near, orange far, over a range in scene units.
    let stop = |position: f32, color: [f32; 4]| ColorStop { position, color };
    let mut graded = small("torus");
    graded.style.tf = Some(TransferFunction::new(
        TfMode::Color,
        DepthRange {
            near: 5.0,
            far: 40.0,
        },
        vec![TfLayer::Gradient {
            opacity: 1.0,
            blend: Default::default(),
            shape: GradientShape::Linear {
                from: [0.5, 0.0],
                to: [0.5, 1.0],
            },
            stops: vec![
                stop(0.0, [0.2, 0.4, 1.0, 1.0]),
                stop(1.0, [1.0, 0.6, 0.2, 1.0]),
            ],
        }],
    ));
    assert_styled("torus coloured by depth", &graded);
    assert_unit_free("torus coloured by depth", &graded);
}

/// `scene` moved by `offset`: the camera, every mesh and the box.
fn moved(scene: &Scene, offset: Vec3) -> Scene {
    let mut scene = scene.clone();
    let shift = Mat4::from_translation(offset);
    scene.camera.world_from_camera = shift * scene.camera.world_from_camera;
    place(&mut scene, shift);
    scene
}

/// A scene moved 100 km renders as it does at the world's origin: its geometry is
/// rasterized relative to the camera, not in f32 world coordinates, which at 100 km lie
/// 8 mm apart (colonnade's frame moved by 1.7%). The camera's position is first put on
/// a 1/64 m grid, so that the scene format's own f32 translations hold it exactly when
/// moved; the built-in meshes sit at the origin.
#[test]
fn scenes_far_from_the_world_origin_render_as_near_it() {
    for name in BUILTIN_SCENES {
        let mut scene = small(name);
        let eye = scene.camera.world_from_camera.w_axis;
        scene.camera.world_from_camera.w_axis =
            ((eye.truncate() * 64.0).round() / 64.0).extend(1.0);
        for method in [Method::Reference, Method::MinMax, Method::Prefiltered] {
            let base = render(&scene, method);
            let layers = render(&moved(&scene, Vec3::new(1e5, -7e4, 32.0)), method);
            let volume = relative_difference(&base.volume, &layers.volume, 1.0);
            let depth = relative_difference(&base.depth, &layers.depth, 1.0);
            eprintln!(
                "{name} {method:?} 100 km away: volume {:.4}% depth {depth:.2e}",
                100.0 * volume
            );
            assert!(
                volume <= BOUND && depth <= BOUND,
                "{name}, {method:?}, 100 km away: volume differs by {:.4}%, depth by {depth:.2e}",
                100.0 * volume
            );
        }
    }
}
