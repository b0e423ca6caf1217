//! Scene-building helpers shared by the integration tests.
#![allow(dead_code)]

use crepuscular::scene::{
    Camera, Extent, Medium, Mesh, PhaseModel, Projection, RenderSettings, Scene, SensorFit, Sun,
    SCENE_VERSION,
};
use glam::{Mat4, Vec3, Vec4};

/// Camera-to-world for a camera at `eye` looking along `forward` with world +Z up.
pub fn look_along(eye: Vec3, forward: Vec3) -> Mat4 {
    let back = -forward.normalize();
    let right = Vec3::Z.cross(back).normalize();
    let up = back.cross(right);
    Mat4::from_cols(
        right.extend(0.0),
        up.extend(0.0),
        back.extend(0.0),
        Vec4::new(eye.x, eye.y, eye.z, 1.0),
    )
}

/// An axis-aligned rectangle at height `z` covering [x0, x1] × [y0, y1].
pub fn horizontal_quad(object_id: u32, x0: f32, x1: f32, y0: f32, y1: f32, z: f32) -> Mesh {
    Mesh {
        name: format!("quad{object_id}"),
        object_id,
        world_from_object: Mat4::IDENTITY,
        positions: vec![[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]],
        triangles: vec![[0, 1, 2], [0, 2, 3]],
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
        },
        medium,
        meshes,
        render,
    }
}

pub fn pinhole(world_from_camera: Mat4, focal_length: f32, width: u32, height: u32) -> Camera {
    Camera {
        world_from_camera,
        projection: Projection::Perspective {
            focal_length,
            sensor_width: 36.0,
            sensor_height: 24.0,
            sensor_fit: SensorFit::Auto,
            shift_x: 0.0,
            shift_y: 0.0,
        },
        clip_start: 0.05,
        clip_end: 1.0e4,
        width,
        height,
    }
}

pub fn medium(extinction: f32, anisotropy: f32) -> Medium {
    Medium {
        extinction,
        albedo: Vec3::new(0.9, 0.8, 0.7),
        anisotropy,
        phase: PhaseModel::HenyeyGreenstein,
        extent: Extent::Unbounded,
    }
}

pub fn settings(shadow_map_size: u32, steps: u32, max_distance: f32) -> RenderSettings {
    RenderSettings {
        shadow_map_size,
        steps,
        max_distance,
        ..RenderSettings::default()
    }
}

pub fn relative_error(got: f64, expected: f64) -> f64 {
    (got - expected).abs() / expected.abs().max(1e-30)
}
