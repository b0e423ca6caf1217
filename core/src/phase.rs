//! Phase functions: the angular distribution of light scattered in the medium.

use std::f64::consts::PI;

use crate::scene::{Medium, PhaseModel};

/// Henyey–Greenstein, normalized over the sphere. `cos_theta` is the cosine between the
/// light's travel direction and the scattered direction (positive `g` scatters forward).
pub fn henyey_greenstein(g: f64, cos_theta: f64) -> f64 {
    let g2 = g * g;
    let denominator = 1.0 + g2 - 2.0 * g * cos_theta;
    (1.0 - g2) / (4.0 * PI * denominator * denominator.sqrt())
}

pub fn isotropic() -> f64 {
    1.0 / (4.0 * PI)
}

/// The medium's phase function for light travelling along `light_travel` that leaves
/// towards the camera, i.e. against the view direction `view_direction` (both unit).
pub fn evaluate(medium: &Medium, light_travel: glam::DVec3, view_direction: glam::DVec3) -> f64 {
    match medium.phase {
        PhaseModel::Isotropic => isotropic(),
        PhaseModel::HenyeyGreenstein => {
            henyey_greenstein(medium.anisotropy as f64, light_travel.dot(-view_direction))
        }
    }
}
