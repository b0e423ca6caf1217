//! A style: the artist's departures from physically based scattering (papers 000/001 §4),
//! as one serializable, versioned value that a scene carries and a preset file holds.
//!
//! - Occluder manipulation acts on a copy of the shadow map before scattering, in this
//!   order: hole filling (2D morphology), silhouette enhancement (1D epipolar dilation or
//!   closure), hole creation (thresholded noise on chosen objects). Sizes are in scene
//!   units and converted with the map's texel size, so that the look does not change with
//!   the shadow-map resolution; `*_texels` overrides are there for experts.
//! - A transfer function recolours the `volume` layer after scattering, from the
//!   `visibility` and `depth` layers.
//! - `time` (seconds) drives everything animated: hole animation and TF key frames. Nothing
//!   else carries state between frames, so any frame renders on its own.
//!
//! The beauty's surface shadows never change: only the map used for scattering does.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::camera::CameraModel;
use crate::error::{Error, Result};
use crate::holes::{HoleNoise, HolesDesc};
use crate::layers::Layers;
use crate::morphology::{self, KernelShape, MorphologyDesc, MorphologyOp};
use crate::scene::parse_json_at;
use crate::shadow_map::ShadowMap;
use crate::silhouette::{self, Epipole, SilhouetteDesc, SilhouetteOp};
use crate::transfer_function::{self, ApplySettings, ProjectedPoint, TfTexture, TransferFunction};

/// One occluder operator of a style, resolved against a shadow map
/// ([`Style::occluder_operators`]).
#[derive(Clone, Debug)]
pub enum OccluderOperator {
    /// 2D morphology of the depth.
    HoleFilling(MorphologyDesc),
    /// 1D epipolar dilation or closure.
    Silhouettes {
        desc: SilhouetteDesc,
        epipole: Epipole,
    },
    /// Thresholded noise on chosen objects.
    HoleCreation(HoleNoise),
}

impl OccluderOperator {
    /// Applies the operator to `map` on the CPU.
    pub fn apply(&self, map: &mut ShadowMap) -> Result<()> {
        match self {
            OccluderOperator::HoleFilling(desc) => {
                map.depth = morphology::apply(&map.depth, map.size, desc)?;
            }
            OccluderOperator::Silhouettes { desc, epipole } => {
                map.depth = silhouette::apply(&map.depth, map.size, *epipole, desc)?;
            }
            OccluderOperator::HoleCreation(noise) => {
                noise.apply(&mut map.depth, &map.ids)?;
            }
        }
        Ok(())
    }
}

/// The style-preset version this build reads and writes.
pub const STYLE_VERSION: u32 = 1;

/// Everything that departs from the physically based look. The default is no departure.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Style {
    pub version: u32,
    /// Seconds (frame / fps): drives hole animation and TF key frames.
    pub time: f32,
    /// Hole filling: 2D morphology of the occluders, a closing by default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub closing: Option<HoleFilling>,
    /// Silhouette enhancement: occluders extruded away from the camera.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub silhouette: Option<Silhouette>,
    /// Hole creation in chosen objects. Its `time` is an offset added to the style's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holes: Option<HolesDesc>,
    /// A transfer function over (V̄, normalized depth).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tf: Option<TransferFunction>,
}

impl Default for Style {
    fn default() -> Self {
        Self {
            version: STYLE_VERSION,
            time: 0.0,
            closing: None,
            silhouette: None,
            holes: None,
            tf: None,
        }
    }
}

/// 2D morphology of the shadow map's occluders.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HoleFilling {
    /// `close` fills holes; `dilate`, `erode` and `open` are there too.
    pub operation: MorphologyOp,
    pub kernel: KernelShape,
    /// Kernel radius in scene units, measured across the light's direction.
    pub radius: f32,
    /// Expert override: the radius in shadow-map texels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius_texels: Option<f32>,
}

impl Default for HoleFilling {
    fn default() -> Self {
        Self {
            operation: MorphologyOp::Close,
            kernel: KernelShape::Disk,
            radius: 0.0,
            radius_texels: None,
        }
    }
}

/// 1D epipolar dilation (Eq. 3), optionally followed by an erosion along the same lines.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Silhouette {
    /// `dilate` extrudes; `close` extrudes, then erodes back what the camera would not see.
    pub operation: SilhouetteOp,
    /// Extrusion length in scene units, measured on the shadow map.
    pub length: f32,
    /// Expert override: the length in shadow-map texels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub length_texels: Option<f32>,
}

impl Default for Silhouette {
    fn default() -> Self {
        Self {
            operation: SilhouetteOp::Dilate,
            length: 0.0,
            length_texels: None,
        }
    }
}

fn check_size(field: &str, value: f32) -> Result<()> {
    if !(value.is_finite() && value >= 0.0) {
        return Err(Error::invalid(
            field,
            format!("{value} must be a finite size of at least 0"),
        ));
    }
    Ok(())
}

impl Style {
    /// Parses a style preset (JSON); unknown keys and wrong types name their path.
    pub fn from_json(text: &str) -> Result<Self> {
        let style: Style = parse_json_at("style", text)?;
        style.validate()?;
        Ok(style)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|err| format!("{{\"error\": \"{err}\"}}"))
    }

    /// Reads a preset file; its relative image paths are taken relative to the file.
    pub fn load(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|err| Error::io(path, err))?;
        let mut style = Self::from_json(&text).map_err(|err| match err {
            Error::SceneFormat(reason) => {
                Error::SceneFormat(format!("style preset {}: {reason}", path.display()))
            }
            other => other,
        })?;
        style.rebase_paths(path.parent().unwrap_or(std::path::Path::new("")));
        Ok(style)
    }

    /// Makes the relative file paths in this style relative to `base`, the directory of
    /// the file it was read from.
    pub fn rebase_paths(&mut self, base: &std::path::Path) {
        if let Some(tf) = &mut self.tf {
            tf.rebase_image_paths(base);
        }
    }

    /// Whether this is the physically based look: no operator and no TF.
    pub fn is_physical(&self) -> bool {
        !self.manipulates_occluders() && self.tf.is_none()
    }

    /// Whether any operator changes the shadow map.
    pub fn manipulates_occluders(&self) -> bool {
        self.closing.is_some() || self.silhouette.is_some() || self.holes.is_some()
    }

    pub fn validate(&self) -> Result<()> {
        if self.version != STYLE_VERSION {
            return Err(Error::invalid(
                "style.version",
                format!(
                    "style version {} is not supported (this build reads version {STYLE_VERSION})",
                    self.version
                ),
            ));
        }
        if !self.time.is_finite() {
            return Err(Error::invalid("style.time", "must be finite"));
        }
        if let Some(closing) = &self.closing {
            check_size("style.closing.radius", closing.radius)?;
            if let Some(texels) = closing.radius_texels {
                check_size("style.closing.radius_texels", texels)?;
            }
        }
        if let Some(silhouette) = &self.silhouette {
            check_size("style.silhouette.length", silhouette.length)?;
            if let Some(texels) = silhouette.length_texels {
                check_size("style.silhouette.length_texels", texels)?;
            }
        }
        if let Some(holes) = &self.holes {
            holes.validate()?;
        }
        if let Some(tf) = &self.tf {
            tf.validate()?;
        }
        Ok(())
    }

    /// The occluder operators that are on, in the order they apply, with their sizes in
    /// texels of `shadow` and everything else they need resolved, for any backend.
    pub fn occluder_operators(
        &self,
        shadow: &ShadowMap,
        camera: &CameraModel,
    ) -> Result<Vec<OccluderOperator>> {
        let texels = |world: f32| (world as f64 / shadow.texel_size) as f32;
        let mut operators = Vec::new();
        if let Some(closing) = &self.closing {
            let radius = closing.radius_texels.unwrap_or(texels(closing.radius));
            if radius > 0.0 {
                operators.push(OccluderOperator::HoleFilling(MorphologyDesc::new(
                    closing.operation,
                    closing.kernel,
                    radius,
                )));
            }
        }
        if let Some(silhouette) = &self.silhouette {
            let length = silhouette
                .length_texels
                .unwrap_or(texels(silhouette.length));
            if length > 0.0 {
                operators.push(OccluderOperator::Silhouettes {
                    desc: SilhouetteDesc {
                        op: silhouette.operation,
                        length_texels: length,
                    },
                    epipole: Epipole::of_camera(camera, &shadow.texel_from_world),
                });
            }
        }
        if let Some(holes) = &self.holes {
            let desc = HolesDesc {
                time: holes.time + self.time,
                ..holes.clone()
            };
            operators.push(OccluderOperator::HoleCreation(HoleNoise::for_map(
                &desc, shadow,
            )?));
        }
        Ok(operators)
    }

    /// The shadow map scattering sees: a manipulated copy when any operator is on.
    pub fn scattering_map(&self, shadow: &ShadowMap, camera: &CameraModel) -> Result<ShadowMap> {
        let mut map = shadow.clone();
        for operator in self.occluder_operators(shadow, camera)? {
            operator.apply(&mut map)?;
        }
        Ok(map)
    }

    /// Recolours `layers` with the transfer function, if there is one. `light_color` is
    /// the colour of the light the medium scatters (sun × albedo).
    pub fn apply_transfer_function(
        &self,
        layers: &mut Layers,
        camera: &CameraModel,
        light_color: [f32; 3],
    ) -> Result<()> {
        let Some((texture, settings)) = self.bake_transfer_function(layers, camera, light_color)?
        else {
            return Ok(());
        };
        transfer_function::apply_to_layers(layers, &texture, &settings)
    }

    /// The transfer function baked for this frame (its world constraints resolved against
    /// `layers`) with the settings that apply it, if there is one.
    pub fn bake_transfer_function(
        &self,
        layers: &Layers,
        camera: &CameraModel,
        light_color: [f32; 3],
    ) -> Result<Option<(TfTexture, ApplySettings)>> {
        let Some(tf) = &self.tf else {
            return Ok(None);
        };
        let mut tf = tf.clone();
        tf.resolve_world_constraints(|point| locate(layers, camera, point))?;
        let texture = tf.bake(self.time)?;
        Ok(Some((texture, tf.apply_settings(light_color))))
    }
}

/// Where a world point lands in the rendered layers: its pixel's V̄, and its own distance
/// along that pixel's ray; occluded when a surface lies clearly in front of it.
fn locate(layers: &Layers, camera: &CameraModel, point: [f32; 3]) -> ProjectedPoint {
    let world = DVec3::from(point.map(f64::from));
    let clip = camera.pixel_from_world() * world.extend(1.0);
    if clip.w <= 0.0 {
        return ProjectedPoint::OffScreen;
    }
    let (x, y) = (clip.x / clip.w, clip.y / clip.w);
    let (width, height) = (layers.width as f64, layers.height as f64);
    if !(x >= 0.0 && y >= 0.0 && x < width && y < height) {
        return ProjectedPoint::OffScreen;
    }
    let ray = camera.ray(x, y);
    let distance = (world - ray.origin).dot(ray.direction);
    let index = y as usize * layers.width as usize + x as usize;
    let surface = layers.depth[index] as f64;
    // A point on the surface it is pinned to must not count as hidden by it.
    if distance > surface * 1.01 + 1e-3 {
        return ProjectedPoint::Occluded;
    }
    ProjectedPoint::Visible {
        visibility: layers.visibility[index],
        depth: distance.min(surface) as f32,
    }
}
