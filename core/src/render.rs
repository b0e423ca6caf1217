//! The per-frame pipeline: geometry → depth maps → scattering → layers.

use crate::control::RenderControl;
use crate::error::{Error, Result};
use crate::layers::Layers;
use crate::scene::{Camera, Medium, RenderSettings, Scene, Sun};

/// World-space triangles, borrowed so that hosts can pass their buffers without copies.
#[derive(Clone, Copy, Debug)]
pub struct Geometry<'a> {
    pub positions: &'a [[f32; 3]],
    pub triangles: &'a [[u32; 3]],
    /// One object id per triangle.
    pub object_ids: &'a [u32],
}

/// How a renderer's depth pass measures distance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum DepthKind {
    /// Distance along the camera's view axis (Blender's and Cycles' Z pass).
    #[default]
    Planar,
    /// Distance along each pixel's view ray.
    RayDistance,
}

/// A renderer-supplied camera depth at the camera's resolution, rows top to bottom.
/// Values at or beyond `clip_end`, and +∞, are background.
#[derive(Clone, Copy, Debug)]
pub struct CameraDepth<'a> {
    pub values: &'a [f32],
    pub kind: DepthKind,
}

/// Everything one frame needs, borrowed.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    pub camera: &'a Camera,
    pub sun: &'a Sun,
    pub medium: &'a Medium,
    pub settings: &'a RenderSettings,
    pub geometry: Geometry<'a>,
    pub camera_depth: Option<CameraDepth<'a>>,
}

/// World-space geometry flattened from a scene's meshes.
#[derive(Clone, Debug, Default)]
pub struct FlatGeometry {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    pub object_ids: Vec<u32>,
}

impl FlatGeometry {
    pub fn from_scene(scene: &Scene) -> Self {
        let mut flat = FlatGeometry::default();
        for mesh in &scene.meshes {
            let base = flat.positions.len() as u32;
            flat.positions.extend(mesh.positions.iter().map(|&p| {
                mesh.world_from_object
                    .transform_point3(glam::Vec3::from(p))
                    .to_array()
            }));
            flat.triangles.extend(
                mesh.triangles
                    .iter()
                    .map(|t| [t[0] + base, t[1] + base, t[2] + base]),
            );
            flat.object_ids
                .extend(std::iter::repeat_n(mesh.object_id, mesh.triangles.len()));
        }
        flat
    }

    pub fn view(&self) -> Geometry<'_> {
        Geometry {
            positions: &self.positions,
            triangles: &self.triangles,
            object_ids: &self.object_ids,
        }
    }
}

/// Renders a validated scene description.
pub fn render_scene(scene: &Scene, control: &RenderControl) -> Result<Layers> {
    scene.validate()?;
    let geometry = FlatGeometry::from_scene(scene);
    render(
        &Frame {
            camera: &scene.camera,
            sun: &scene.sun,
            medium: &scene.medium,
            settings: &scene.render,
            geometry: geometry.view(),
            camera_depth: None,
        },
        control,
    )
}

/// Renders one frame from borrowed inputs, validating them first.
pub fn render(frame: &Frame, control: &RenderControl) -> Result<Layers> {
    frame.validate()?;
    control.check()?;
    Err(Error::invalid("render.method", "not implemented yet"))
}

impl Frame<'_> {
    pub fn validate(&self) -> Result<()> {
        self.camera.validate()?;
        self.sun.validate()?;
        self.medium.validate()?;
        self.settings.validate()?;
        Ok(())
    }
}
