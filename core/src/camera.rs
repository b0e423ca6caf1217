//! Camera rays and the camera's raster projection, following Blender's view-plane rules
//! (sensor fit, lens shift in units of the fitted sensor dimension, non-square pixels).
//!
//! Pixel coordinates are continuous: (0, 0) is the top-left corner of the image and
//! (width, height) the bottom-right one, so pixel (x, y) has its centre at (x + ½, y + ½).

use glam::{DMat4, DVec3, DVec4};

#[cfg(test)]
use crate::scene::PixelWindow;
use crate::scene::{Camera, Projection, SensorFit};

/// A view ray in world space. `direction` has unit length.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: DVec3,
    pub direction: DVec3,
    /// Ray length per unit of planar depth (distance along the view axis).
    pub distance_per_depth: f64,
}

impl Ray {
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + self.direction * t
    }
}

/// Camera-space ray origin and unnormalized direction as `v[0] + px·v[1] + py·v[2]`; the
/// direction's length is the ray's `distance_per_depth`, and `world_from_camera` maps both
/// to the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayTerms {
    pub origin: [DVec3; 3],
    pub direction: [DVec3; 3],
}

impl RayTerms {
    pub fn at(&self, px: f64, py: f64) -> (DVec3, DVec3) {
        let affine = |v: &[DVec3; 3]| v[0] + v[1] * px + v[2] * py;
        (affine(&self.origin), affine(&self.direction))
    }
}

/// A camera prepared for ray generation and rasterization.
#[derive(Clone, Debug)]
pub struct CameraModel {
    pub world_from_camera: DMat4,
    pub camera_from_world: DMat4,
    pub width: u32,
    pub height: u32,
    pub clip_start: f64,
    pub clip_end: f64,
    perspective: bool,
    /// View-plane units per pixel across and down (at unit depth for perspective, scene
    /// units for ortho); they differ by the pixel aspect.
    plane_per_pixel: [f64; 2],
    /// View-plane coordinates of the image's top-left corner.
    plane_origin: [f64; 2],
    /// The whole frame's corners in the image's pixel coordinates, (x0, y0, x1, y1): the
    /// image's own where it has no window.
    frame: [f64; 4],
}

impl CameraModel {
    pub fn new(camera: &Camera) -> Self {
        let width = camera.width as f64;
        let height = camera.height as f64;
        let (perspective, plane_size, fit, shift_x, shift_y) = match camera.projection {
            Projection::Perspective {
                focal_length,
                sensor_width,
                sensor_height,
                sensor_fit,
                shift_x,
                shift_y,
            } => {
                // Blender applies sensor_width unless the fit is explicitly vertical.
                let sensor = if sensor_fit == SensorFit::Vertical {
                    sensor_height
                } else {
                    sensor_width
                };
                (
                    true,
                    sensor as f64 / focal_length as f64,
                    sensor_fit,
                    shift_x,
                    shift_y,
                )
            }
            Projection::Orthographic {
                ortho_scale,
                sensor_fit,
                shift_x,
                shift_y,
            } => (false, ortho_scale as f64, sensor_fit, shift_x, shift_y),
        };
        // As Blender's view plane: the fit compares the sides in square units, and the
        // height, the shift's unit where it is fitted, counts in pixel widths.
        let aspect = camera.pixel_aspect as f64;
        let height_in_widths = height / aspect;
        let fitted = match fit {
            SensorFit::Horizontal => width,
            SensorFit::Vertical => height_in_widths,
            SensorFit::Auto => width.max(height_in_widths),
        };
        let across = plane_size / fitted;
        let plane_per_pixel = [across, across / aspect];
        let plane_origin = [
            (-0.5 * width + shift_x as f64 * fitted) * across,
            (0.5 * height_in_widths + shift_y as f64 * fitted) * across,
        ];
        // A window is the frame's view plane from its top-left pixel, at the frame's pixels.
        let (mut plane_origin, mut size) = (plane_origin, (camera.width, camera.height));
        let mut frame = [0.0, 0.0, width, height];
        if let Some(window) = camera.window {
            let (x, y) = (window.x as f64, window.y as f64);
            plane_origin[0] += x * plane_per_pixel[0];
            plane_origin[1] -= y * plane_per_pixel[1];
            size = (window.width, window.height);
            frame = [-x, -y, width - x, height - y];
        }
        let world_from_camera = camera.world_from_camera.as_dmat4();
        Self {
            world_from_camera,
            camera_from_world: world_from_camera.inverse(),
            width: size.0,
            height: size.1,
            clip_start: camera.clip_start as f64,
            clip_end: camera.clip_end as f64,
            perspective,
            plane_per_pixel,
            plane_origin,
            frame,
        }
    }

    pub fn is_perspective(&self) -> bool {
        self.perspective
    }

    /// Camera-space point on the view plane for continuous pixel coordinates.
    fn plane_point(&self, px: f64, py: f64) -> [f64; 2] {
        [
            self.plane_origin[0] + px * self.plane_per_pixel[0],
            self.plane_origin[1] - py * self.plane_per_pixel[1],
        ]
    }

    /// [`Ray::distance_per_depth`] of [`CameraModel::ray`] without the rest of the ray:
    /// converting a depth buffer needs only this, per sample.
    #[inline]
    pub fn distance_per_depth(&self, px: f64, py: f64) -> f64 {
        if self.perspective {
            let [x, y] = self.plane_point(px, py);
            DVec3::new(x, y, -1.0).length()
        } else {
            1.0
        }
    }

    /// The world-space ray through continuous pixel coordinates. Inlined: called apart,
    /// it handed its ray back through the stack, in pieces the caller's wider loads then
    /// waited on.
    #[inline]
    pub fn ray(&self, px: f64, py: f64) -> Ray {
        let [x, y] = self.plane_point(px, py);
        let (origin_cam, dir_cam) = if self.perspective {
            (DVec3::ZERO, DVec3::new(x, y, -1.0))
        } else {
            (DVec3::new(x, y, 0.0), DVec3::NEG_Z)
        };
        let distance_per_depth = dir_cam.length();
        Ray {
            origin: self.world_from_camera.transform_point3(origin_cam),
            direction: self
                .world_from_camera
                .transform_vector3(dir_cam)
                .normalize(),
            distance_per_depth,
        }
    }

    /// Ray generation as affine functions of continuous pixel coordinates, in camera
    /// space, for backends that generate rays themselves.
    pub fn ray_terms(&self) -> RayTerms {
        let [x0, y0] = self.plane_origin;
        let [sx, sy] = self.plane_per_pixel;
        let (dx, dy) = (DVec3::new(sx, 0.0, 0.0), DVec3::new(0.0, -sy, 0.0));
        if self.perspective {
            RayTerms {
                origin: [DVec3::ZERO; 3],
                direction: [DVec3::new(x0, y0, -1.0), dx, dy],
            }
        } else {
            RayTerms {
                origin: [DVec3::new(x0, y0, 0.0), dx, dy],
                direction: [DVec3::NEG_Z, DVec3::ZERO, DVec3::ZERO],
            }
        }
    }

    /// World position of the camera (for orthographic cameras, the view-plane centre).
    pub fn position(&self) -> DVec3 {
        self.world_from_camera.transform_point3(DVec3::ZERO)
    }

    /// Maps a world point to (pixel x · w, pixel y · w, planar depth, w), where w is the
    /// planar depth for perspective cameras and 1 for orthographic ones. Linear, so that
    /// triangles can be clipped in this space before the division.
    pub fn pixel_from_world(&self) -> DMat4 {
        let [ix, iy] = self.plane_per_pixel.map(|s| 1.0 / s);
        let [x0, y0] = self.plane_origin;
        // Camera space has the view direction along −Z, so planar depth is −z.
        let pixel_from_camera = if self.perspective {
            // px = (x/(−z) − x0)/ppx, py = (y0 − y/(−z))/ppy; multiplied through by w = −z.
            DMat4::from_cols(
                DVec4::new(ix, 0.0, 0.0, 0.0),
                DVec4::new(0.0, -iy, 0.0, 0.0),
                DVec4::new(x0 * ix, -y0 * iy, -1.0, -1.0),
                DVec4::new(0.0, 0.0, 0.0, 0.0),
            )
        } else {
            DMat4::from_cols(
                DVec4::new(ix, 0.0, 0.0, 0.0),
                DVec4::new(0.0, -iy, 0.0, 0.0),
                DVec4::new(0.0, 0.0, -1.0, 0.0),
                DVec4::new(-x0 * ix, y0 * iy, 0.0, 1.0),
            )
        };
        pixel_from_camera * self.camera_from_world
    }

    /// World-space corners of the region view rays can reach before planar depth `depth`:
    /// four on the near plane and four at `depth`.
    pub fn frustum_corners(&self, depth: f64) -> [DVec3; 8] {
        self.corners_of([0.0, 0.0, self.width as f64, self.height as f64], depth)
    }

    /// [`CameraModel::frustum_corners`] of the whole frame where the image is a window of
    /// it: what a shadow map fitted to the view covers, so that a window's pixels are the
    /// frame's.
    pub fn frame_frustum_corners(&self, depth: f64) -> [DVec3; 8] {
        self.corners_of(self.frame, depth)
    }

    fn corners_of(&self, [x0, y0, x1, y1]: [f64; 4], depth: f64) -> [DVec3; 8] {
        let mut corners = [DVec3::ZERO; 8];
        for (i, (px, py)) in [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .into_iter()
            .enumerate()
        {
            for (j, z) in [self.clip_start, depth].into_iter().enumerate() {
                let [x, y] = self.plane_point(px, py);
                let cam = if self.perspective {
                    DVec3::new(x * z, y * z, -z)
                } else {
                    DVec3::new(x, y, -z)
                };
                corners[i * 2 + j] = self.world_from_camera.transform_point3(cam);
            }
        }
        corners
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat4, Vec3};

    fn camera(projection: Projection, width: u32, height: u32) -> Camera {
        Camera {
            world_from_camera: Mat4::from_translation(Vec3::new(1.0, 2.0, 3.0)),
            projection,
            clip_start: 0.1,
            clip_end: 100.0,
            width,
            height,
            pixel_aspect: 1.0,
            window: None,
        }
    }

    fn perspective(fit: SensorFit, shift_x: f32) -> Projection {
        Projection::Perspective {
            focal_length: 50.0,
            sensor_width: 36.0,
            sensor_height: 24.0,
            sensor_fit: fit,
            shift_x,
            shift_y: 0.0,
        }
    }

    #[test]
    fn distance_per_depth_is_the_rays() {
        let orthographic = Projection::Orthographic {
            ortho_scale: 6.0,
            sensor_fit: SensorFit::Auto,
            shift_x: 0.2,
            shift_y: 0.0,
        };
        for projection in [perspective(SensorFit::Vertical, 0.3), orthographic] {
            let model = CameraModel::new(&camera(projection, 160, 90));
            for (px, py) in [(0.0, 0.0), (80.5, 45.5), (159.9, 3.25), (12.0, 89.0)] {
                let want = model.ray(px, py).distance_per_depth;
                assert_eq!(model.distance_per_depth(px, py), want, "({px}, {py})");
            }
        }
    }

    #[test]
    fn auto_fit_puts_sensor_width_on_the_larger_side() {
        // Portrait: the 36 mm sensor spans the height.
        let model = CameraModel::new(&camera(perspective(SensorFit::Auto, 0.0), 100, 200));
        let top = model.ray(50.0, 0.0).direction;
        let expected = (18.0f64 / 50.0).atan();
        assert!((top.y.atan2(-top.z) - expected).abs() < 1e-9);
    }

    #[test]
    fn horizontal_shift_moves_the_centre_by_the_fitted_width() {
        let model = CameraModel::new(&camera(perspective(SensorFit::Auto, 0.5), 200, 100));
        let centre = model.ray(100.0, 50.0).direction;
        // Shift 0.5 moves the centre by half the sensor width: x = 18/50 at unit depth.
        assert!((centre.x / -centre.z - 18.0 / 50.0).abs() < 1e-9);
    }

    #[test]
    fn ray_terms_generate_the_same_rays() {
        for projection in [
            perspective(SensorFit::Auto, 0.1),
            Projection::Orthographic {
                ortho_scale: 5.0,
                sensor_fit: SensorFit::Vertical,
                shift_x: 0.2,
                shift_y: -0.1,
            },
        ] {
            let model = CameraModel::new(&camera(projection, 320, 200));
            let terms = model.ray_terms();
            for (px, py) in [(0.0, 0.0), (160.5, 99.25), (319.5, 199.5)] {
                let ray = model.ray(px, py);
                let (origin, direction) = terms.at(px, py);
                let world_origin = model.world_from_camera.transform_point3(origin);
                let world_direction = model.world_from_camera.transform_vector3(direction);
                assert!((world_origin - ray.origin).length() < 1e-12);
                assert!((world_direction.normalize() - ray.direction).length() < 1e-12);
                assert!((direction.length() - ray.distance_per_depth).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn projection_matrix_maps_rays_back_to_their_pixels() {
        for projection in [
            perspective(SensorFit::Vertical, 0.2),
            Projection::Orthographic {
                ortho_scale: 7.0,
                sensor_fit: SensorFit::Auto,
                shift_x: -0.1,
                shift_y: 0.3,
            },
        ] {
            let model = CameraModel::new(&Camera {
                pixel_aspect: 0.75,
                ..camera(projection, 320, 240)
            });
            let m = model.pixel_from_world();
            for (px, py) in [(0.0, 0.0), (10.5, 200.25), (319.0, 1.0)] {
                let ray = model.ray(px, py);
                let t = 7.5;
                let clip = m * ray.at(t).extend(1.0);
                assert!((clip.x / clip.w - px).abs() < 1e-6, "{clip:?}");
                assert!((clip.y / clip.w - py).abs() < 1e-6);
                assert!((clip.z - t / ray.distance_per_depth).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn wide_pixels_see_what_square_pixels_as_much_narrower_see() {
        let orthographic = |fit, shift_x, shift_y| Projection::Orthographic {
            ortho_scale: 6.0,
            sensor_fit: fit,
            shift_x,
            shift_y,
        };
        for (width, height) in [(160, 90), (90, 160), (100, 150)] {
            for fit in [SensorFit::Auto, SensorFit::Horizontal, SensorFit::Vertical] {
                let shifted = Projection::Perspective {
                    focal_length: 35.0,
                    sensor_width: 36.0,
                    sensor_height: 24.0,
                    sensor_fit: fit,
                    shift_x: 0.15,
                    shift_y: -0.2,
                };
                for projection in [shifted, orthographic(fit, -0.1, 0.25)] {
                    for aspect in [2.0, 0.5, 1.5] {
                        let wide = CameraModel::new(&Camera {
                            pixel_aspect: aspect as f32,
                            ..camera(projection.clone(), width, height)
                        });
                        // The same view in square pixels, `aspect` times as many across.
                        let across = (width as f64 * aspect) as u32;
                        let square = CameraModel::new(&camera(projection.clone(), across, height));
                        for (px, py) in [(0.0, 0.0), (40.5, 30.25), (width as f64, height as f64)] {
                            let (a, b) = (wide.ray(px, py), square.ray(px * aspect, py));
                            let context = format!("{width}×{height} {fit:?} {aspect} ({px}, {py})");
                            assert!((a.direction - b.direction).length() < 1e-12, "{context}");
                            assert!((a.origin - b.origin).length() < 1e-12, "{context}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn a_window_sees_the_frames_pixels() {
        let orthographic = Projection::Orthographic {
            ortho_scale: 6.0,
            sensor_fit: SensorFit::Vertical,
            shift_x: 0.1,
            shift_y: -0.2,
        };
        for projection in [perspective(SensorFit::Auto, 0.2), orthographic] {
            for aspect in [1.0, 2.0] {
                let frame = Camera {
                    pixel_aspect: aspect,
                    ..camera(projection.clone(), 96, 54)
                };
                let window = PixelWindow {
                    x: 28,
                    y: 17,
                    width: 53,
                    height: 27,
                };
                let whole = CameraModel::new(&frame);
                let part = CameraModel::new(&Camera {
                    window: Some(window),
                    ..frame
                });
                assert_eq!((part.width, part.height), (53, 27));
                for (px, py) in [(0.0, 0.0), (10.5, 3.25), (53.0, 27.0)] {
                    let (a, b) = (part.ray(px, py), whole.ray(px + 28.0, py + 17.0));
                    assert!((a.direction - b.direction).length() < 1e-12);
                    assert!((a.origin - b.origin).length() < 1e-12);
                    let pixel = part.pixel_from_world() * b.at(3.0).extend(1.0);
                    assert!((pixel.x / pixel.w - px).abs() < 1e-9);
                    assert!((pixel.y / pixel.w - py).abs() < 1e-9);
                }
            }
        }
    }
}
