//! Which triangles block the sun and which the camera sees. A renderer's objects can be
//! hidden from shadow rays (Blender's Shadow visibility, shadow linking) yet still hide the
//! fog behind them from the camera, or hidden from the camera yet still cast shafts; a
//! frame then rasterizes its shadow map and its camera depth from different triangles.

use crate::error::{Error, Result};
use crate::render::Geometry;

/// A triangle's flag: it is in the sun's shadow map.
pub const BLOCKS_SUN: u8 = 1;
/// A triangle's flag: it is in the camera's depth.
pub const SEEN_BY_CAMERA: u8 = 2;
/// Both flags: what a triangle is without any.
pub const VISIBLE: u8 = BLOCKS_SUN | SEEN_BY_CAMERA;

/// The triangles (with their ids and cutout masks) of one of the two views.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleSubset {
    pub triangles: Vec<[u32; 3]>,
    pub object_ids: Vec<u32>,
    /// Empty where the geometry has no cutouts.
    pub triangle_masks: Vec<u32>,
}

impl TriangleSubset {
    fn of(geometry: &Geometry<'_>, visibility: &[u8], flag: u8) -> Self {
        let keep = |k: &usize| visibility[*k] & flag != 0;
        let kept = (0..visibility.len()).filter(keep);
        Self {
            triangles: kept.clone().map(|k| geometry.triangles[k]).collect(),
            object_ids: kept.clone().map(|k| geometry.object_ids[k]).collect(),
            triangle_masks: match &geometry.cutouts {
                Some(cutouts) => kept.map(|k| cutouts.triangle_masks[k]).collect(),
                None => Vec::new(),
            },
        }
    }

    /// `whole` with only these triangles (the same positions, origin and masks).
    pub fn view<'a>(&'a self, whole: &Geometry<'a>) -> Geometry<'a> {
        Geometry {
            triangles: &self.triangles,
            object_ids: &self.object_ids,
            cutouts: whole.cutouts.map(|cutouts| crate::cutout::Cutouts {
                triangle_masks: &self.triangle_masks,
                ..cutouts
            }),
            ..*whole
        }
    }
}

/// A geometry's triangles split by their visibility flags: those that block the sun and
/// those the camera sees.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VisibilitySplit {
    pub sun: TriangleSubset,
    pub camera: TriangleSubset,
}

impl VisibilitySplit {
    /// Splits `geometry` by `visibility`, one flag set per triangle ([`BLOCKS_SUN`],
    /// [`SEEN_BY_CAMERA`]); None where every triangle has both (nothing to split).
    /// `field` names the flags in errors.
    pub fn new(geometry: &Geometry<'_>, visibility: &[u8], field: &str) -> Result<Option<Self>> {
        if visibility.len() != geometry.triangles.len() {
            return Err(Error::invalid(
                field,
                format!(
                    "has {} entries but there are {} triangles (give one per triangle)",
                    visibility.len(),
                    geometry.triangles.len()
                ),
            ));
        }
        if let Some(k) = visibility.iter().position(|&flags| flags > VISIBLE) {
            return Err(Error::invalid(
                format!("{field}[{k}]"),
                format!(
                    "is {}; flags are {BLOCKS_SUN} (blocks the sun) and {SEEN_BY_CAMERA} \
                     (seen by the camera), so at most {VISIBLE}",
                    visibility[k]
                ),
            ));
        }
        if geometry.object_ids.len() != geometry.triangles.len() {
            return Ok(None); // the frame's validation names the ids
        }
        if visibility.iter().all(|&flags| flags == VISIBLE) {
            return Ok(None);
        }
        Ok(Some(Self {
            sun: TriangleSubset::of(geometry, visibility, BLOCKS_SUN),
            camera: TriangleSubset::of(geometry, visibility, SEEN_BY_CAMERA),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    fn geometry<'a>(
        positions: &'a [[f32; 3]],
        triangles: &'a [[u32; 3]],
        ids: &'a [u32],
    ) -> Geometry<'a> {
        Geometry {
            positions,
            triangles,
            object_ids: ids,
            origin: DVec3::ZERO,
            cutouts: None,
        }
    }

    #[test]
    fn splits_triangles_and_their_ids_by_flag() {
        let positions = [[0.0; 3]; 3];
        let triangles = [[0, 1, 2], [1, 2, 0], [2, 0, 1], [0, 2, 1]];
        let ids = [10, 11, 12, 13];
        let whole = geometry(&positions, &triangles, &ids);
        let split = VisibilitySplit::new(&whole, &[VISIBLE, BLOCKS_SUN, SEEN_BY_CAMERA, 0], "v")
            .unwrap()
            .unwrap();
        assert_eq!(split.sun.triangles, [[0, 1, 2], [1, 2, 0]]);
        assert_eq!(split.sun.object_ids, [10, 11]);
        assert_eq!(split.camera.triangles, [[0, 1, 2], [2, 0, 1]]);
        assert_eq!(split.camera.object_ids, [10, 12]);
        let view = split.camera.view(&whole);
        assert_eq!(view.triangles.len(), 2);
        assert_eq!(view.positions.len(), 3);
        assert!(VisibilitySplit::new(&whole, &[VISIBLE; 4], "v")
            .unwrap()
            .is_none());
    }

    #[test]
    fn bad_flags_are_named() {
        let positions = [[0.0; 3]; 3];
        let triangles = [[0, 1, 2], [1, 2, 0]];
        let whole = geometry(&positions, &triangles, &[0, 0]);
        let short = VisibilitySplit::new(&whole, &[VISIBLE], "triangle_visibility").unwrap_err();
        assert!(short.to_string().contains("triangle_visibility"), "{short}");
        let large = VisibilitySplit::new(&whole, &[VISIBLE, 4], "triangle_visibility").unwrap_err();
        assert!(
            large.to_string().contains("triangle_visibility[1]"),
            "{large}"
        );
    }
}
