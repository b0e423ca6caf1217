//! Scene-building helpers shared by the integration tests.
#![allow(dead_code)]

use crepuscular::scene::{
    Camera, Extent, Medium, Mesh, Method, PhaseModel, Projection, RenderSettings, Scene, Sun,
    SCENE_VERSION,
};
use crepuscular::silhouette::SilhouetteOp;
use crepuscular::style::Silhouette;
use crepuscular::{Layers, Style};
use glam::{Mat4, Vec3};

/// An axis-aligned rectangle at height `z` covering [x0, x1] × [y0, y1].
pub fn horizontal_quad(object_id: u32, x0: f32, x1: f32, y0: f32, y1: f32, z: f32) -> Mesh {
    Mesh {
        name: format!("quad{object_id}"),
        object_id,
        world_from_object: Mat4::IDENTITY,
        positions: vec![[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
        uvs: None,
        alpha_mask: None,
        blocks_sun: true,
        seen_by_camera: true,
    }
}

pub fn scene(
    camera: Camera,
    sun_direction: Vec3,
    medium: Medium,
    meshes: Vec<Mesh>,
    render: RenderSettings,
) -> Scene {
    Scene {
        version: SCENE_VERSION,
        camera,
        sun: Sun {
            direction: sun_direction,
            color: Vec3::new(1.0, 0.9, 0.8),
            strength: 3.0,
            angular_diameter: 0.0,
            attenuated_by_medium: true,
        },
        medium,
        meshes,
        render,
        style: Style::default(),
    }
}

/// A pinhole camera at `eye` looking along `forward` with the world's +Z up.
pub fn pinhole(eye: Vec3, forward: Vec3, focal_length: f32, width: u32, height: u32) -> Camera {
    Camera::pinhole_looking_at(eye, eye + forward, focal_length, width, height)
}

pub fn medium(extinction: f32, anisotropy: f32) -> Medium {
    Medium {
        extinction,
        channel_extinction: None,
        albedo: Vec3::new(0.9, 0.8, 0.7),
        anisotropy,
        phase: PhaseModel::HenyeyGreenstein,
        extent: Extent::Unbounded,
    }
}

/// Settings of the reference march.
pub fn settings(shadow_map_size: u32, steps: u32, max_distance: f32) -> RenderSettings {
    RenderSettings {
        method: Method::Reference,
        shadow_map_size,
        steps,
        max_distance,
        ..RenderSettings::default()
    }
}

pub fn relative_error(got: f64, expected: f64) -> f64 {
    (got - expected).abs() / expected.abs().max(1e-30)
}

/// Mean absolute error of volume RGB over the mean reference radiance.
pub fn radiance_error(fast: &Layers, reference: &Layers) -> f64 {
    let (mut diff, mut total) = (0.0f64, 0.0f64);
    for (f, r) in fast.volume.chunks(4).zip(reference.volume.chunks(4)) {
        for c in 0..3 {
            diff += (f[c] as f64 - r[c] as f64).abs();
            total += r[c] as f64;
        }
    }
    diff / total
}

/// `torus` (any size) turned on a box of fog 10 cm across (σ = 3 /m) that a shadow edge of
/// its ring crosses, seen through an 1800 mm lens from 15 m: the shadow map covers the box
/// alone, and the camera's epipole lies far off it.
pub fn small_fog_box_far_off(torus: &mut Scene) {
    let centre = Vec3::new(1.0, -2.5, 3.5);
    let eye = centre + 15.0 * (Vec3::new(9.0, -8.0, 9.0) - centre).normalize();
    let (width, height) = (torus.camera.width, torus.camera.height);
    torus.camera = Camera::pinhole_looking_at(eye, centre, 1800.0, width, height);
    torus.medium.extinction = 3.0;
    torus.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(centre) * Mat4::from_scale(Vec3::splat(0.05)),
    };
}

/// `plane` (any size) with its camera inside a box of fog (σ = 0.2 /m) under the slotted
/// roof, looking up the shafts, its clip plane 2 m out, without the near-plane correction.
pub fn camera_inside_a_fog_box(plane: &mut Scene) {
    let eye = Vec3::new(0.0, -14.0, 1.6);
    let (width, height) = (plane.camera.width, plane.camera.height);
    plane.camera =
        Camera::pinhole_looking_at(eye, eye + Vec3::new(0.0, 0.95, 0.3), 50.0, width, height);
    plane.camera.clip_start = 2.0;
    plane.render.near_plane_correction = false;
    plane.medium.extinction = 0.2;
    plane.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(0.0, 5.0, 2.5))
            * Mat4::from_scale(Vec3::new(10.0, 25.0, 2.5)),
    };
}

/// `plane` (any size) under its roof, the slots narrowed by a silhouette dilation of 0.3,
/// in a box of thin fog (0.01 /m) seen through an orthographic camera looking up at it
/// (fuzzed): the dilation extrudes the slats along the view rays, so rays passing just by
/// one stay within a texel's depth of its extrusion for the rest of their way through the
/// box.
pub fn dilated_roof_in_a_thin_box(plane: &mut Scene) {
    plane.camera.world_from_camera = Mat4::from_cols_array(&[
        0.465_467_8,
        -0.885_064_8,
        0.0,
        0.0,
        -0.644_266_4,
        -0.338_828_6,
        0.685_650_04,
        0.0,
        -0.606_844_7,
        -0.319_148,
        -0.727_931_3,
        0.0,
        0.296_318_14,
        0.866_831_6,
        6.698_793_6,
        1.0,
    ]);
    plane.camera.projection = Projection::orthographic(14.520_387);
    plane.sun.direction = Vec3::new(-0.290_757_3, -0.571_725_3, -0.767_196_4);
    plane.medium.extinction = 0.01;
    plane.medium.anisotropy = -0.201_797_83;
    plane.medium.extent = Extent::Box {
        world_from_cube: Mat4::from_translation(Vec3::new(4.383_855, 0.348_009, 1.903_674))
            * Mat4::from_scale(Vec3::new(3.412_813, 10.885_553, 4.293_938)),
    };
    plane.render.max_distance = 30.0;
    plane.style = Style {
        silhouette: Some(Silhouette {
            operation: SilhouetteOp::Dilate,
            length: 0.3,
            ..Silhouette::default()
        }),
        ..Style::default()
    };
}

/// Fog of 0.1 /m over a wide ground, seen from 6 m up at a slant, under a sun whose light
/// travels along `sun` (upward: from below the ground), rendered by `method` with every
/// pixel shaded, to 60 m. All the fog above the ground lies in its shadow.
pub fn ground_lit_from_below(sun: Vec3, method: Method) -> Scene {
    let camera = pinhole(
        Vec3::new(0.0, 0.0, 6.0),
        Vec3::new(1.0, 0.3, -0.45),
        24.0,
        64,
        36,
    );
    let ground = horizontal_quad(1, -500.0, 500.0, -500.0, 500.0, 0.0);
    scene(
        camera,
        sun,
        medium(0.1, 0.3),
        vec![ground],
        RenderSettings {
            method,
            // Adaptive shading blends shaded neighbours' opacity.
            adaptive_tolerance: 0.0,
            ..settings(1024, 1024, 60.0)
        },
    )
}

/// The three suns below the horizon [`ground_lit_from_below`] is seen under, named.
pub const SUNS_BELOW: [(&str, Vec3); 3] = [
    ("steep", Vec3::new(0.3, 0.1, 1.0)),
    ("grazing", Vec3::new(-0.2, 0.9, 0.15)),
    ("behind the camera", Vec3::new(1.0, 0.3, 0.45)),
];
