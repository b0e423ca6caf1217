//! The sun as a disc. A path tracer lights a point through the part of the sun's disc
//! that no occluder hides, so a shadow softens over a penumbra as wide as the occluder's
//! distance times the disc's angle. The shadow-map methods model a point sun: a frame
//! under a disc is rendered once per direction, spread evenly over the disc's solid angle,
//! and the passes' layers are averaged, which converges to the disc's light as the
//! directions grow in number. The transfer function runs once, on the average.

use glam::Vec3;
use rayon::prelude::*;

use crate::control::RenderControl;
use crate::error::Result;
use crate::layers::Layers;
use crate::render::{apply_transfer_function_timed, Frame, StageTimes};
use crate::scene::Sun;
use crate::style::Style;

/// The most directions a frame may take over the sun's disc.
pub const MAX_SUN_DISC_SAMPLES: u32 = 64;

/// The golden angle, which turns each direction of the spiral from the last so that any
/// number of them covers the disc evenly (Vogel's spiral).
const GOLDEN_ANGLE: f32 = 2.399_963_2;

/// Whether `samples` keeps a point sun (for leaving the setting out of scene files).
pub fn is_point_sun(samples: &u32) -> bool {
    *samples == 1
}

/// `samples` unit directions over a disc of `angular_diameter` radians around
/// `direction`, each at the centre of an equal share of the disc's area (Vogel's spiral:
/// the k-th at radius √((k + ½) / n) of the disc's, turned by the golden angle).
pub fn disc_directions(direction: Vec3, angular_diameter: f32, samples: u32) -> Vec<Vec3> {
    let centre = direction.normalize();
    let (across, other) = centre.any_orthonormal_pair();
    let radius = 0.5 * angular_diameter;
    (0..samples)
        .map(|k| {
            let r = radius * ((k as f32 + 0.5) / samples as f32).sqrt();
            let (sin, cos) = (k as f32 * GOLDEN_ANGLE).sin_cos();
            let offset = r.tan() * (cos * across + sin * other);
            (centre + offset).normalize()
        })
        .collect()
}

/// `render` of `frame`, once per direction over its sun's disc where
/// `render.sun_disc_samples` is above 1 and the disc has a size, with the layers
/// averaged; else `render` of the frame itself. Passes get no transfer function; it is
/// applied here, once.
pub fn by_sun_direction(
    frame: &Frame,
    control: &RenderControl,
    render: impl Fn(&Frame, &RenderControl) -> Result<(Layers, StageTimes)>,
) -> Result<(Layers, StageTimes)> {
    let samples = frame.settings.sun_disc_samples;
    if samples <= 1 || frame.sun.angular_diameter <= 0.0 {
        return render(frame, control);
    }
    let style = Style {
        tf: None,
        ..frame.style.clone()
    };
    let render_pass = |direction: Vec3| {
        let sun = Sun {
            direction,
            ..frame.sun.clone()
        };
        let pass = Frame {
            sun: &sun,
            style: &style,
            ..*frame
        };
        render(&pass, control)
    };
    let directions = disc_directions(frame.sun.direction, frame.sun.angular_diameter, samples);
    let (mut layers, mut times) = render_pass(directions[0])?;
    for &direction in &directions[1..] {
        let (pass, pass_times) = render_pass(direction)?;
        times.accumulate(&pass_times);
        add_pass(&mut layers, &pass);
    }
    scale(&mut layers, 1.0 / samples as f32);
    apply_transfer_function_timed(frame, &mut layers, &mut times)?;
    Ok((layers, times))
}

/// Adds a pass's radiance, opacity and visibility to the sum; the depth is every pass's.
fn add_pass(sum: &mut Layers, pass: &Layers) {
    sum.volume
        .par_iter_mut()
        .zip(pass.volume.par_iter())
        .for_each(|(total, value)| *total += value);
    sum.visibility
        .par_iter_mut()
        .zip(pass.visibility.par_iter())
        .for_each(|(total, value)| *total += value);
}

fn scale(layers: &mut Layers, factor: f32) {
    layers
        .volume
        .par_iter_mut()
        .for_each(|value| *value *= factor);
    layers
        .visibility
        .par_iter_mut()
        .for_each(|value| *value *= factor);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_cover_the_disc_evenly_around_the_sun() {
        let sun = Vec3::new(0.3, -0.2, -1.0);
        let diameter = 4.0_f32.to_radians();
        for samples in [2, 7, 16, 64] {
            let found = disc_directions(sun, diameter, samples);
            assert_eq!(found.len(), samples as usize);
            let centre = sun.normalize();
            let mut mean = Vec3::ZERO;
            let mut inner = 0;
            for direction in &found {
                assert!((direction.length() - 1.0).abs() < 1e-6);
                let angle = direction.dot(centre).clamp(-1.0, 1.0).acos();
                assert!(angle <= 0.5 * diameter + 1e-6, "{angle} outside the disc");
                // Half the disc's area lies within 1/√2 of its radius.
                if angle < 0.5 * diameter / 2.0_f32.sqrt() {
                    inner += 1;
                }
                mean += *direction;
            }
            let spread = (mean / samples as f32 - centre).length();
            assert!(
                spread < 0.25 * diameter,
                "{samples}: off centre by {spread}"
            );
            assert_eq!(inner, samples as usize / 2, "{samples}");
        }
        // The same directions every time: frames are deterministic.
        assert_eq!(
            disc_directions(sun, diameter, 9),
            disc_directions(sun, diameter, 9)
        );
    }
}
