//! The sun's orthographic shadow map, fitted to the part of the world that view rays
//! can reach, with object ids per texel.

use glam::{DMat4, DVec3, DVec4};

use crate::camera::CameraModel;
use crate::error::Result;
use crate::raster::{rasterize, DepthTarget, RasterDesc, Rasterizer, NO_OBJECT};
use crate::render::Geometry;
use crate::scene::{Extent, Medium, RenderSettings, Sun};

/// Bias, in texel widths, used when the settings give none.
pub const DEFAULT_BIAS_TEXELS: f64 = 1.5;

#[derive(Clone, Debug)]
pub struct ShadowMap {
    pub size: u32,
    /// Light depth of the nearest occluder per texel, +∞ where there is none.
    pub depth: Vec<f32>,
    /// Object id of that occluder, [`NO_OBJECT`] where there is none.
    pub ids: Vec<u32>,
    /// Maps a world point to (texel x, texel y, light depth, 1). Affine.
    pub texel_from_world: DMat4,
    /// World size of one texel along its larger side.
    pub texel_size: f64,
    /// A point is lit when its light depth is at most occluder depth + bias.
    pub bias: f64,
}

impl ShadowMap {
    /// The map of a whole scene description: its meshes, sun, medium and settings.
    pub fn of_scene(scene: &crate::scene::Scene, camera: &CameraModel) -> Result<Self> {
        Self::of_scene_geometry(
            scene,
            camera,
            &crate::render::FlatGeometry::from_scene(scene),
        )
    }

    /// [`ShadowMap::of_scene`] for callers that keep the scene's flattened geometry.
    pub fn of_scene_geometry(
        scene: &crate::scene::Scene,
        camera: &CameraModel,
        geometry: &crate::render::FlatGeometry,
    ) -> Result<Self> {
        Self::build(
            camera,
            &scene.sun,
            &scene.medium,
            &scene.render,
            &geometry.view(),
        )
    }

    pub fn build(
        camera: &CameraModel,
        sun: &Sun,
        medium: &Medium,
        settings: &RenderSettings,
        geometry: &Geometry,
    ) -> Result<Self> {
        let size = settings.shadow_map_size;
        let texel_from_world = fit(camera, sun, medium, settings.max_distance as f64, size);
        let target = rasterize(
            geometry,
            &texel_from_world,
            &RasterDesc::orthographic(size, size),
        )?;
        Ok(Self::from_target(settings, texel_from_world, target))
    }

    /// [`ShadowMap::build`] with the rasterization done by `rasterizer`, which must write
    /// object ids.
    pub fn build_with(
        camera: &CameraModel,
        sun: &Sun,
        medium: &Medium,
        settings: &RenderSettings,
        geometry: &Geometry,
        rasterizer: &dyn Rasterizer,
    ) -> Result<Self> {
        let size = settings.shadow_map_size;
        let texel_from_world = fit(camera, sun, medium, settings.max_distance as f64, size);
        let target = rasterizer.rasterize(
            geometry,
            &texel_from_world,
            &RasterDesc::orthographic(size, size),
        )?;
        Ok(Self::from_target(settings, texel_from_world, target))
    }

    fn from_target(
        settings: &RenderSettings,
        texel_from_world: DMat4,
        target: DepthTarget,
    ) -> Self {
        let size = target.width;
        let texel_size = texel_world_size(&texel_from_world);
        let bias = settings
            .shadow_bias
            .map(f64::from)
            .unwrap_or(DEFAULT_BIAS_TEXELS * texel_size);
        Self {
            size,
            depth: target.depth,
            ids: target.ids,
            texel_from_world,
            texel_size,
            bias,
        }
    }

    /// Visibility of the sun from a point given in texel space (see `texel_from_world`).
    /// Points outside the map have no known occluder and count as lit.
    #[inline]
    pub fn is_lit(&self, texel: DVec3) -> bool {
        let size = self.size as f64;
        if !(texel.x >= 0.0 && texel.y >= 0.0 && texel.x < size && texel.y < size) {
            return true;
        }
        let index = texel.y as usize * self.size as usize + texel.x as usize;
        texel.z <= self.depth[index] as f64 + self.bias
    }

    pub fn occluder_id(&self, x: u32, y: u32) -> Option<u32> {
        let id = self.ids[(y * self.size + x) as usize];
        (id != NO_OBJECT).then_some(id)
    }
}

/// An orthonormal light basis: rows are the map's x and y axes and the travel direction.
pub fn light_from_world(sun: &Sun) -> DMat4 {
    let forward = sun.direction.as_dvec3().normalize();
    let helper = if forward.z.abs() < 0.9 {
        DVec3::Z
    } else {
        DVec3::X
    };
    let right = helper.cross(forward).normalize();
    let up = forward.cross(right);
    DMat4::from_cols(
        DVec4::new(right.x, up.x, forward.x, 0.0),
        DVec4::new(right.y, up.y, forward.y, 0.0),
        DVec4::new(right.z, up.z, forward.z, 0.0),
        DVec4::W,
    )
}

/// Chooses the map's footprint: the light-space bounds of everything a view ray of the
/// whole frame can reach (the frustum up to `max_distance`; a window's map is the frame's),
/// narrowed to the medium's box if it has one.
fn fit(camera: &CameraModel, sun: &Sun, medium: &Medium, max_distance: f64, size: u32) -> DMat4 {
    let light = light_from_world(sun);
    // The camera's own position too: the fast methods rectify rays from its projection,
    // and a slice's stretch before the near plane, off the map, would read as unoccluded
    // and leak light into every ray of a dense medium (seen at the map's edge: 60% off).
    let apex = camera.world_from_camera.transform_point3(DVec3::ZERO);
    let reach: Vec<DVec3> = camera
        .frame_frustum_corners(max_distance.max(camera.clip_start * 2.0))
        .into_iter()
        .chain([apex])
        .map(|p| light.transform_point3(p))
        .collect();
    let mut bounds = Bounds::of(&reach);
    if let Extent::Box { world_from_cube } = &medium.extent {
        let cube = world_from_cube.as_dmat4();
        let corners: Vec<DVec3> = (0..8)
            .map(|i| {
                let corner = DVec3::new(
                    if i & 1 == 0 { -1.0 } else { 1.0 },
                    if i & 2 == 0 { -1.0 } else { 1.0 },
                    if i & 4 == 0 { -1.0 } else { 1.0 },
                );
                light.transform_point3(cube.transform_point3(corner))
            })
            .collect();
        // A box that no view ray reaches leaves the frame without fog: the frustum's
        // bounds then, not the box's, which may lie too far off for the map's matrix (a box
        // 10³⁰ m away overflowed it).
        if let Some(both) = bounds.intersect(&Bounds::of(&corners)) {
            bounds = both;
        }
    }
    // A texel of margin so that rays on the frustum's boundary still sample inside.
    let extent = (bounds.max - bounds.min).max(DVec3::splat(1e-6));
    let margin = extent / size as f64;
    let min = bounds.min - margin;
    let max = bounds.max + margin;
    let scale_x = size as f64 / (max.x - min.x);
    let scale_y = size as f64 / (max.y - min.y);
    let texel_from_light = DMat4::from_cols(
        DVec4::new(scale_x, 0.0, 0.0, 0.0),
        DVec4::new(0.0, scale_y, 0.0, 0.0),
        DVec4::new(0.0, 0.0, 1.0, 0.0),
        DVec4::new(-min.x * scale_x, -min.y * scale_y, -min.z, 1.0),
    );
    texel_from_light * light
}

fn texel_world_size(texel_from_world: &DMat4) -> f64 {
    let x = texel_from_world.row(0).truncate().length();
    let y = texel_from_world.row(1).truncate().length();
    1.0 / x.min(y)
}

#[derive(Clone, Copy, Debug)]
struct Bounds {
    min: DVec3,
    max: DVec3,
}

impl Bounds {
    fn of(points: &[DVec3]) -> Self {
        points.iter().fold(
            Bounds {
                min: DVec3::INFINITY,
                max: DVec3::NEG_INFINITY,
            },
            |b, &p| Bounds {
                min: b.min.min(p),
                max: b.max.max(p),
            },
        )
    }

    fn intersect(&self, other: &Bounds) -> Option<Bounds> {
        let min = self.min.max(other.min);
        let max = self.max.min(other.max);
        (min.x < max.x && min.y < max.y).then_some(Bounds {
            min,
            max: DVec3::new(max.x, max.y, max.z.max(min.z)),
        })
    }
}
