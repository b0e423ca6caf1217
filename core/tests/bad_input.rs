//! Bad input yields an error that names the offending field, never a panic.

mod common;

use common::*;
use crepuscular::render::{CameraDepth, DepthKind, FlatGeometry, Frame};
use crepuscular::scene::{
    ExactRayEnds, PixelWindow, Scene, MAX_IMAGE_SIZE, MAX_SHADOW_MAP_SIZE, MAX_SUPERSAMPLING,
};
use crepuscular::{render, render_scene, Error, RenderControl};
use glam::{Mat4, Vec3};

fn valid_scene() -> Scene {
    let camera = pinhole(Vec3::new(0.0, 0.0, 2.0), Vec3::X, 35.0, 32, 18);
    scene(
        camera,
        Vec3::new(0.2, 0.0, -1.0),
        medium(0.1, 0.2),
        vec![horizontal_quad(1, -50.0, 50.0, -50.0, 50.0, 0.0)],
        settings(64, 16, 30.0),
    )
}

fn field_of(result: Result<impl std::fmt::Debug, Error>) -> String {
    match result {
        Err(Error::InvalidInput { field, .. }) => field,
        other => panic!("expected an invalid-input error, got {other:?}"),
    }
}

fn check(mutate: impl FnOnce(&mut Scene), expected_field: &str) {
    let mut scene = valid_scene();
    mutate(&mut scene);
    assert_eq!(field_of(scene.validate()), expected_field);
    assert_eq!(
        field_of(render_scene(&scene, &RenderControl::new())),
        expected_field
    );
    // The JSON path reports the same field.
    match Scene::from_json(&scene.to_json()) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, expected_field),
        Err(Error::SceneFormat(message)) => assert!(
            message.contains("number") || message.contains("null"),
            "{message}"
        ),
        other => panic!("expected an error, got {other:?}"),
    }
}

#[test]
fn the_valid_scene_renders() {
    render_scene(&valid_scene(), &RenderControl::new()).expect("valid scene renders");
}

#[test]
fn nan_in_matrices_is_named() {
    check(
        |s| s.camera.world_from_camera.x_axis.y = f32::NAN,
        "camera.world_from_camera",
    );
    check(
        |s| s.meshes[0].world_from_object.w_axis.x = f32::INFINITY,
        "meshes[0].world_from_object",
    );
    check(
        |s| s.camera.world_from_camera = Mat4::ZERO,
        "camera.world_from_camera",
    );
}

#[test]
fn sizes_out_of_range_are_named() {
    check(|s| s.camera.width = 0, "camera.width");
    check(|s| s.camera.height = 0, "camera.height");
    check(|s| s.camera.pixel_aspect = 0.0, "camera.pixel_aspect");
    check(|s| s.camera.pixel_aspect = -2.0, "camera.pixel_aspect");
    check(|s| s.camera.pixel_aspect = f32::NAN, "camera.pixel_aspect");
    let window = |x, y, width, height| {
        Some(PixelWindow {
            x,
            y,
            width,
            height,
        })
    };
    let (w, h) = (valid_scene().camera.width, valid_scene().camera.height);
    check(
        move |s| s.camera.window = window(0, 0, 0, 1),
        "camera.window",
    );
    check(
        move |s| s.camera.window = window(1, 0, w, 1),
        "camera.window",
    );
    check(
        move |s| s.camera.window = window(0, h, 1, 1),
        "camera.window",
    );
    check(
        move |s| s.camera.window = window(u32::MAX, 0, 2, 1),
        "camera.window",
    );
    check(
        |s| s.render.shadow_map_size = MAX_SHADOW_MAP_SIZE + 1,
        "render.shadow_map_size",
    );
    check(|s| s.render.steps = 0, "render.steps");
    check(|s| s.render.max_distance = 0.0, "render.max_distance");
    check(
        |s| s.camera.clip_end = s.camera.clip_start,
        "camera.clip_end",
    );
    check(|s| s.render.downsample = 3, "render.downsample");
    for tolerance in [-0.01, 1.5, f32::NAN] {
        check(
            move |s| s.render.adaptive_tolerance = tolerance,
            "render.adaptive_tolerance",
        );
    }
    check(|s| s.render.bases = 7, "render.bases");
    check(|s| s.render.bases = 66, "render.bases");
    check(|s| s.render.epipolar_slices = 1, "render.epipolar_slices");
    // Each within its range, together more camera depth than a frame may take (64 GiB).
    check(
        |s| {
            (s.camera.width, s.camera.height) = (MAX_IMAGE_SIZE, MAX_IMAGE_SIZE);
            s.render.supersampling = MAX_SUPERSAMPLING;
        },
        "render.supersampling",
    );
    let mut both = valid_scene();
    both.render.downsample = 2;
    both.render.supersampling = 2;
    assert_eq!(
        field_of(render_scene(&both, &RenderControl::new())),
        "render.downsample"
    );
}

#[test]
fn degenerate_light_and_medium_are_named() {
    check(|s| s.sun.direction = Vec3::ZERO, "sun.direction");
    check(
        |s| s.sun.direction = Vec3::new(f32::NAN, 0.0, -1.0),
        "sun.direction",
    );
    check(|s| s.medium.extinction = -1.0, "medium.extinction");
    check(|s| s.medium.anisotropy = 1.0, "medium.anisotropy");
    check(|s| s.sun.angular_diameter = 3.2, "sun.angular_diameter");
}

#[test]
fn empty_scene_and_bad_indices_are_named() {
    check(|s| s.meshes.clear(), "meshes");
    check(|s| s.meshes[0].triangles.clear(), "meshes");
    check(
        |s| s.meshes[0].triangles[1] = [0, 1, 99],
        "meshes[0].triangles[1]",
    );
    check(
        |s| s.meshes[0].positions[2][1] = f32::NAN,
        "meshes[0].positions[2]",
    );
}

#[test]
fn unknown_json_keys_are_named_with_their_path() {
    let json = valid_scene().to_json().replacen(
        "\"clip_start\"",
        "\"clip_strat\": 1.0, \"clip_start\"",
        1,
    );
    match Scene::from_json(&json) {
        Err(Error::SceneFormat(message)) => {
            assert!(
                message.contains("clip_strat") && message.contains("camera"),
                "{message}"
            )
        }
        other => panic!("expected a format error, got {other:?}"),
    }
    let json = valid_scene()
        .to_json()
        .replacen("\"version\": 1", "\"version\": 99", 1);
    assert_eq!(field_of(Scene::from_json(&json)), "version");
    assert!(matches!(
        Scene::from_json("{ not json"),
        Err(Error::SceneFormat(_))
    ));
}

#[test]
fn camera_depth_is_checked() {
    let scene = valid_scene();
    let geometry = FlatGeometry::from_scene(&scene);
    let frame = |values: &'static [f32]| Frame {
        camera: &scene.camera,
        sun: &scene.sun,
        medium: &scene.medium,
        settings: &scene.render,
        geometry: geometry.view(),
        camera_geometry: None,
        camera_depth: Some(CameraDepth {
            values,
            kind: DepthKind::Planar,
        }),
        style: &scene.style,
    };
    let short: &'static [f32] = &[1.0; 10];
    assert_eq!(
        field_of(render(&frame(short), &RenderControl::new())),
        "camera_depth"
    );
    let mut with_nan = vec![5.0f32; 32 * 18];
    with_nan[40] = f32::NAN;
    let with_nan: &'static [f32] = Box::leak(with_nan.into_boxed_slice());
    match render(&frame(with_nan), &RenderControl::new()) {
        Err(Error::InvalidInput { field, reason }) => {
            assert_eq!(field, "camera_depth");
            assert!(reason.contains("(8, 1)"), "{reason}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_cancelled_render_stops_with_cancelled() {
    let control = RenderControl::new();
    control.cancel();
    assert!(matches!(
        render_scene(&valid_scene(), &control),
        Err(Error::Cancelled)
    ));
}

#[test]
fn an_unknown_rectification_is_named_with_its_path() {
    let json = valid_scene().to_json();
    assert!(
        json.contains("\"rectification\": \"auto\""),
        "the default is written"
    );
    let json = json.replacen(
        "\"rectification\": \"auto\"",
        "\"rectification\": \"linear\"",
        1,
    );
    match Scene::from_json(&json) {
        Err(Error::SceneFormat(message)) => assert!(
            message.contains("render.rectification") && message.contains("linear"),
            "{message}"
        ),
        other => panic!("expected a format error, got {other:?}"),
    }
}

#[test]
fn exact_ray_ends_read_names_and_the_old_flags_and_name_what_they_refuse() {
    let json = valid_scene().to_json();
    let default = "\"exact_ray_ends\": \"auto\"";
    assert!(json.contains(default), "the default is written");
    for (given, read) in [
        ("\"auto\"", ExactRayEnds::Auto),
        ("\"on\"", ExactRayEnds::On),
        ("\"off\"", ExactRayEnds::Off),
        ("true", ExactRayEnds::On),
        ("false", ExactRayEnds::Off),
    ] {
        let scene =
            Scene::from_json(&json.replacen(default, &format!("\"exact_ray_ends\": {given}"), 1))
                .expect("a known setting");
        assert_eq!(scene.render.exact_ray_ends, read, "{given}");
        let again = Scene::from_json(&scene.to_json()).expect("round trip");
        assert_eq!(again.render.exact_ray_ends, read, "{given} written back");
    }
    for given in ["\"always\"", "1", "null"] {
        let json = json.replacen(default, &format!("\"exact_ray_ends\": {given}"), 1);
        match Scene::from_json(&json) {
            Err(Error::SceneFormat(message)) => assert!(
                message.contains("render.exact_ray_ends") && message.contains("\"auto\", \"on\""),
                "{given}: {message}"
            ),
            other => panic!("{given}: expected a format error, got {other:?}"),
        }
    }
    for (text, read) in [("auto", ExactRayEnds::Auto), ("true", ExactRayEnds::On)] {
        assert_eq!(text.parse::<ExactRayEnds>().expect(text), read);
    }
    let refused = "sometimes".parse::<ExactRayEnds>().unwrap_err().to_string();
    assert!(
        refused.contains("render.exact_ray_ends") && refused.contains("sometimes"),
        "{refused}"
    );
}

/// A reader that stops early (`crepuscular scene export tree | head -1`) ends the command
/// as it ends other Unix tools, by SIGPIPE, not with a panic on standard error.
#[cfg(target_os = "linux")]
#[test]
fn a_reader_that_stops_early_ends_the_command_quietly() {
    use std::io::{BufRead, BufReader};
    use std::os::unix::process::ExitStatusExt;
    use std::process::{Command, Stdio};

    // Megabytes of JSON: the command is still writing when the reader goes.
    let mut child = Command::new(env!("CARGO_BIN_EXE_crepuscular"))
        .args(["scene", "export", "tree"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first_line = String::new();
    let mut reader = BufReader::new(child.stdout.take().unwrap());
    reader.read_line(&mut first_line).unwrap();
    assert_eq!(first_line.trim(), "{");
    drop(reader);
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(output.status.signal(), Some(libc::SIGPIPE), "{stderr}");
}
