//! Projective ("linear") rectification of the shadow map (dissertation §4.4.2).
//!
//! Light view space is rotated about the light's direction so that the bisectrix of the
//! camera frustum, seen along the light, is +X; the camera is the origin and Z runs along
//! the light's travel. One homogeneous matrix then maps a world point (X, Y, Z) to
//! (column·w, row·w, depth·w, w) with w = X:
//! - the row is uniform in Y/X: a row is a plane through the camera that contains the
//!   light direction, an epipolar slice, which no view ray leaves;
//! - the depth Z/X is constant along every view ray, since they all start at the camera;
//! - the column is a + b/X, from the frustum's smallest X (column 0, the light frustum's
//!   near plane) to its largest (the last column's far edge).
//!
//! Each texel is a line along the light, as in a regular shadow map, so the scene is
//! rasterized straight into the rectified map, without resampling. This needs every view
//! ray to move away from the camera along X: the frustum seen along the light must span
//! less than a half-turn around the camera (neither the sun nor the anti-sun point in the
//! image), and the camera must be a pinhole. Columns are uniform in 1/X, so they widen
//! with the square of X: deep frusta get coarse far columns, which is what
//! [`ProjectiveGrid::is_sharp`] rules on.

use std::f64::consts::PI;

use glam::{DMat4, DVec3, DVec4};

use crate::camera::CameraModel;
use crate::epipolar::RectifyDesc;
use crate::error::{Error, Result};
use crate::scene::Rectification;

/// Widest angle the frustum may span around the camera, seen along the light. Towards a
/// half-turn the rows' tangents and the far-to-near ratio grow without bound.
pub const MAX_SPAN_DEGREES: f64 = 160.0;

/// `auto` takes the projective map only when its farthest column covers at most this many
/// regular shadow-map texel widths.
pub const MAX_FAR_COLUMN_TEXELS: f64 = 2.0;

/// Most columns a projective map gets, whatever the texel size.
const MAX_COLUMNS: f64 = 65536.0;

/// Why a view cannot be rectified projectively.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Unsupported {
    Orthographic,
    SunInImage,
    AntiSunInImage,
    /// The frustum spans this many degrees around the camera, seen along the light.
    TooWide(f64),
}

impl std::fmt::Display for Unsupported {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unsupported::Orthographic => write!(
                f,
                "needs a pinhole camera: an orthographic camera has no centre of projection"
            ),
            Unsupported::SunInImage => write!(
                f,
                "needs the sun outside the image, but this camera looks towards it"
            ),
            Unsupported::AntiSunInImage => write!(
                f,
                "needs the anti-sun point outside the image, but this camera looks along the light"
            ),
            Unsupported::TooWide(span) => write!(
                f,
                "needs the view, seen along the light, to span at most {MAX_SPAN_DEGREES}° \
                 around the camera, but it spans {span:.1}° (the sun or the anti-sun point \
                 is too close to the image)"
            ),
        }
    }
}

/// The light frustum wrapped around the camera frustum.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectiveFrame {
    /// World to (X, Y, Z): X along the bisectrix, Z along the light's travel, camera at 0.
    pub view_from_world: DMat4,
    /// Smallest and largest X of the camera frustum's corners.
    pub near: f64,
    pub far: f64,
    /// Largest |Y/X| of the frustum: rows span tangents from −tan_max to tan_max.
    pub tan_max: f64,
}

impl ProjectiveFrame {
    /// Wraps a light frustum around `camera`'s frustum from its near clip plane to planar
    /// depth `reach` (at least twice the near clip distance, as the regular shadow map
    /// does), for light travelling along `light_travel`.
    pub fn fit(
        camera: &CameraModel,
        light_travel: DVec3,
        reach: f64,
    ) -> std::result::Result<Self, Unsupported> {
        if !camera.is_perspective() {
            return Err(Unsupported::Orthographic);
        }
        let light = light_travel.normalize();
        // The epipoles first: they name the cause better than the span does.
        for (direction, cause) in [
            (-light, Unsupported::SunInImage),
            (light, Unsupported::AntiSunInImage),
        ] {
            if in_image(camera, direction) {
                return Err(cause);
            }
        }
        let (right, up) = perpendicular_basis(light);
        let angle_of = |d: DVec3| d.dot(up).atan2(d.dot(right));
        let (w, h) = (camera.width as f64, camera.height as f64);
        // Every view ray lies in the cone of the four corner rays, so their directions
        // seen along the light bound the frustum's; the centre ray lies within.
        let centre = angle_of(camera.ray(0.5 * w, 0.5 * h).direction);
        let (mut low, mut high) = (0.0f64, 0.0f64);
        for (px, py) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            let d = camera.ray(px, py).direction;
            if d.dot(right).hypot(d.dot(up)) < 1e-12 {
                return Err(Unsupported::TooWide(180.0));
            }
            let offset = wrap_angle(angle_of(d) - centre);
            low = low.min(offset);
            high = high.max(offset);
        }
        let span = (high - low).to_degrees();
        if span > MAX_SPAN_DEGREES {
            return Err(Unsupported::TooWide(span));
        }
        let bisectrix = centre + 0.5 * (low + high);
        let (sin, cos) = bisectrix.sin_cos();
        let x_axis = right * cos + up * sin;
        let y_axis = up * cos - right * sin;
        let rotation = DMat4::from_cols(
            DVec4::new(x_axis.x, y_axis.x, light.x, 0.0),
            DVec4::new(x_axis.y, y_axis.y, light.y, 0.0),
            DVec4::new(x_axis.z, y_axis.z, light.z, 0.0),
            DVec4::W,
        );
        let view_from_world = rotation * DMat4::from_translation(-camera.position());
        let corners = camera
            .frustum_corners(reach.max(2.0 * camera.clip_start))
            .map(|p| view_from_world.transform_point3(p));
        let near = corners.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
        let far = corners
            .iter()
            .map(|p| p.x)
            .fold(f64::NEG_INFINITY, f64::max);
        if !(near > 0.0 && far > near && far.is_finite()) {
            return Err(Unsupported::TooWide(span));
        }
        let tan_max = corners
            .iter()
            .map(|p| (p.y / p.x).abs())
            .fold(0.0, f64::max)
            .max(1e-9);
        Ok(Self {
            view_from_world,
            near,
            far,
            tan_max,
        })
    }

    /// Sizes the map for `desc` against a regular shadow map of `texel_size` world units.
    /// Columns: as many as the epipolar layout spends on its widest slice from the camera
    /// to the frustum's far end (that length in texels × `samples_per_texel`). Rows, with
    /// automatic slices: `slices_per_texel` apart at the far end along the bisectrix.
    pub fn grid(&self, desc: &RectifyDesc, texel_size: f64) -> ProjectiveGrid {
        let secant = self.tan_max.hypot(1.0);
        let slice_texels = self.far * secant / texel_size;
        let columns = (slice_texels * desc.samples_per_texel)
            .ceil()
            .clamp(1.0, MAX_COLUMNS) as u32;
        let rows = if desc.slices == 0 {
            let across_texels = 2.0 * self.tan_max * self.far / texel_size;
            ((across_texels * desc.slices_per_texel).ceil() as u32).clamp(16, desc.max_auto_slices)
        } else {
            desc.slices
        };
        ProjectiveGrid {
            frame: *self,
            columns,
            rows: rows.max(2),
        }
    }
}

/// A projective frame with the rectified map's resolution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectiveGrid {
    pub frame: ProjectiveFrame,
    pub columns: u32,
    pub rows: u32,
}

impl ProjectiveGrid {
    /// 1/X at column edge `column` (0 at the near plane, `columns` at the far one).
    pub fn reciprocal_at_column(&self, column: f64) -> f64 {
        let f = &self.frame;
        1.0 / f.near - column * self.reciprocal_step()
    }

    /// The change of 1/X from one column edge to the next.
    pub fn reciprocal_step(&self) -> f64 {
        (1.0 / self.frame.near - 1.0 / self.frame.far) / self.columns as f64
    }

    /// The continuous column of a point at distance `x` along the bisectrix.
    pub fn column_at(&self, x: f64) -> f64 {
        (1.0 / self.frame.near - 1.0 / x) / self.reciprocal_step()
    }

    /// The change of Y/X from one slice to the next; slice j, at Y/X = −tan_max + j·step,
    /// is the image row centred at j + ½.
    pub fn tan_step(&self) -> f64 {
        2.0 * self.frame.tan_max / (self.rows - 1) as f64
    }

    /// The continuous image row (not slice) of the tangent Y/X.
    pub fn row_at(&self, tan: f64) -> f64 {
        (tan + self.frame.tan_max) / self.tan_step() + 0.5
    }

    /// Maps a world point to (column·X, row·X, Z, X): image coordinates for the
    /// rasterizer, which divides by w = X and stores the depth Z/X.
    pub fn clip_from_world(&self) -> DMat4 {
        let f = &self.frame;
        let n = self.columns as f64;
        // column·X = a·X + b with column(near) = 0 and column(far) = n.
        let a = n * f.far / (f.far - f.near);
        let b = -n * f.near * f.far / (f.far - f.near);
        let tan_step = self.tan_step();
        let row_offset = f.tan_max / tan_step + 0.5;
        let image_from_view = DMat4::from_cols(
            DVec4::new(a, row_offset, 0.0, 1.0),
            DVec4::new(0.0, 1.0 / tan_step, 0.0, 0.0),
            DVec4::new(0.0, 0.0, 1.0, 0.0),
            DVec4::new(b, 0.0, 0.0, 0.0),
        );
        image_from_view * f.view_from_world
    }

    /// World length that the farthest column covers along the widest slice.
    pub fn far_column_length(&self) -> f64 {
        let f = &self.frame;
        let start = 1.0 / self.reciprocal_at_column(self.columns as f64 - 1.0);
        (f.far - start) * f.tan_max.hypot(1.0)
    }

    /// Whether the map resolves shadows about as finely as the regular shadow map of
    /// `texel_size` that the epipolar layout resamples: the rule `auto` applies is that
    /// [`far_column_length`](Self::far_column_length) is at most
    /// [`MAX_FAR_COLUMN_TEXELS`] × `texel_size`. With the columns of
    /// [`ProjectiveFrame::grid`] that holds, to first order, while far/near ≤
    /// 1 + 2 × `samples_per_texel`: 5 for both fast methods.
    pub fn is_sharp(&self, texel_size: f64) -> bool {
        self.far_column_length() <= MAX_FAR_COLUMN_TEXELS * texel_size
    }
}

/// The projective grid to rectify with, or `None` for the epipolar layout.
/// - `Epipolar`: always `None`.
/// - `Projective`: the grid, or an error naming `render.rectification` where the view
///   cannot be rectified projectively.
/// - `Auto`: the grid where the view allows it and it [is sharp](ProjectiveGrid::is_sharp).
pub fn choose(
    rectification: Rectification,
    camera: &CameraModel,
    light_travel: DVec3,
    reach: f64,
    desc: &RectifyDesc,
    texel_size: f64,
) -> Result<Option<ProjectiveGrid>> {
    match rectification {
        Rectification::Epipolar => Ok(None),
        Rectification::Projective => match ProjectiveFrame::fit(camera, light_travel, reach) {
            Ok(frame) => Ok(Some(frame.grid(desc, texel_size))),
            Err(why) => Err(Error::invalid(
                "render.rectification",
                format!("'projective' {why}; use 'auto' or 'epipolar' for this view"),
            )),
        },
        Rectification::Auto => Ok(ProjectiveFrame::fit(camera, light_travel, reach)
            .ok()
            .map(|frame| frame.grid(desc, texel_size))
            .filter(|grid| grid.is_sharp(texel_size))),
    }
}

/// Whether the point at infinity in `direction` appears within the image (borders
/// included).
fn in_image(camera: &CameraModel, direction: DVec3) -> bool {
    let clip = camera.pixel_from_world() * direction.extend(0.0);
    if clip.w <= 0.0 {
        return false;
    }
    let (px, py) = (clip.x / clip.w, clip.y / clip.w);
    px >= 0.0 && py >= 0.0 && px <= camera.width as f64 && py <= camera.height as f64
}

/// Two unit vectors completing `forward` (unit) to an orthonormal basis.
fn perpendicular_basis(forward: DVec3) -> (DVec3, DVec3) {
    let helper = if forward.z.abs() < 0.9 {
        DVec3::Z
    } else {
        DVec3::X
    };
    let right = helper.cross(forward).normalize();
    (right, forward.cross(right))
}

/// The angle in [−π, π).
fn wrap_angle(angle: f64) -> f64 {
    (angle + PI).rem_euclid(2.0 * PI) - PI
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Camera;
    use glam::Vec3;

    const WIDTH: u32 = 160;
    const HEIGHT: u32 = 90;

    /// Light travelling down and towards +Y, 35° above the horizon.
    fn light() -> DVec3 {
        let elevation = 35f64.to_radians();
        DVec3::new(0.0, elevation.cos(), -elevation.sin())
    }

    fn camera_looking(forward: DVec3) -> CameraModel {
        let mut camera = Camera::pinhole_looking_at(
            Vec3::new(0.0, 0.0, 2.0),
            Vec3::new(0.0, 0.0, 2.0) + forward.as_vec3(),
            35.0,
            WIDTH,
            HEIGHT,
        );
        camera.clip_start = 1.0;
        CameraModel::new(&camera)
    }

    /// Looking across the light: along +X, level.
    fn sideways() -> CameraModel {
        camera_looking(DVec3::X)
    }

    fn grid() -> ProjectiveGrid {
        let frame = ProjectiveFrame::fit(&sideways(), light(), 20.0).expect("valid view");
        frame.grid(&RectifyDesc::prefiltered(0), 0.05)
    }

    fn project(m: &DMat4, p: DVec3) -> DVec3 {
        let clip = *m * p.extend(1.0);
        DVec3::new(clip.x / clip.w, clip.y / clip.w, clip.z / clip.w)
    }

    #[test]
    fn view_rays_keep_their_row_and_depth() {
        let camera = sideways();
        let grid = grid();
        let m = grid.clip_from_world();
        for (px, py) in [(0.0, 0.0), (37.5, 80.25), (160.0, 45.0), (100.0, 3.0)] {
            let ray = camera.ray(px, py);
            let first = project(&m, ray.at(1.5));
            for t in [2.0, 5.0, 11.0, 19.0] {
                let p = project(&m, ray.at(t));
                assert!(
                    (p.y - first.y).abs() < 1e-9,
                    "row at t = {t}: {p} vs {first}"
                );
                assert!((p.z - first.z).abs() < 1e-12, "depth at t = {t}");
                assert!(p.x > first.x, "columns grow along the ray");
            }
        }
    }

    #[test]
    fn the_bisectrix_maps_to_the_middle_row() {
        let grid = grid();
        let m = grid.clip_from_world();
        let camera = sideways();
        let bisectrix = grid
            .frame
            .view_from_world
            .inverse()
            .transform_vector3(DVec3::X);
        assert!(
            bisectrix.dot(light()).abs() < 1e-12,
            "perpendicular to the light"
        );
        let p = project(&m, camera.position() + 7.0 * bisectrix);
        assert!((p.y - 0.5 * grid.rows as f64).abs() < 1e-9, "row {}", p.y);
        // The frustum is symmetric about it: its extreme rows are the first and the last.
        let corners = camera.frustum_corners(20.0).map(|c| project(&m, c));
        let lowest = corners.iter().map(|c| c.y).fold(f64::INFINITY, f64::min);
        let highest = corners
            .iter()
            .map(|c| c.y)
            .fold(f64::NEG_INFINITY, f64::max);
        assert!((lowest - 0.5).abs() < 1e-9 && (highest - (grid.rows as f64 - 0.5)).abs() < 1e-9);
    }

    #[test]
    fn frustum_corners_land_inside_the_map_and_near_far_span_its_columns() {
        let camera = sideways();
        let grid = grid();
        let m = grid.clip_from_world();
        let (w, h) = (grid.columns as f64, grid.rows as f64);
        for corner in camera.frustum_corners(20.0) {
            let p = project(&m, corner);
            let slack = 1e-9 * w;
            assert!(
                p.x >= -slack && p.x <= w + slack && p.y >= 0.0 && p.y <= h,
                "{p}"
            );
        }
        let to_world = grid.frame.view_from_world.inverse();
        let at_x = |x: f64| project(&m, to_world.transform_point3(DVec3::new(x, 0.3 * x, 1.0)));
        assert!(at_x(grid.frame.near).x.abs() < 1e-9 * w);
        assert!((at_x(grid.frame.far).x - w).abs() < 1e-9 * w);
        assert!((grid.column_at(grid.frame.far) - w).abs() < 1e-9 * w);
        assert!((1.0 / grid.reciprocal_at_column(w) - grid.frame.far).abs() < 1e-9);
        // Depth is light depth over X: the same along the light's travel at fixed X.
        let p = to_world.transform_point3(DVec3::new(4.0, 1.0, -3.0));
        assert!((project(&m, p).z - -3.0 / 4.0).abs() < 1e-12);
        let along = project(&m, p + 2.0 * light());
        assert!((along.z - -1.0 / 4.0).abs() < 1e-12);
        assert!(
            (along.x - project(&m, p).x).abs() < 1e-9 && (along.y - project(&m, p).y).abs() < 1e-9
        );
    }

    #[test]
    fn validity_depends_on_where_the_sun_is() {
        let light = light();
        let sideways = ProjectiveFrame::fit(&camera_looking(DVec3::X), light, 20.0);
        assert!(sideways.is_ok(), "{sideways:?}");
        // Into the sun, and with it at one's back looking down its shadows.
        assert_eq!(
            ProjectiveFrame::fit(&camera_looking(-light), light, 20.0),
            Err(Unsupported::SunInImage)
        );
        assert_eq!(
            ProjectiveFrame::fit(&camera_looking(light), light, 20.0),
            Err(Unsupported::AntiSunInImage)
        );
        // Turning away from the sun: it leaves the image, the view then spans nearly a
        // half-turn around the camera (too wide), and less and less after that.
        let stages: Vec<u8> = (0..150)
            .map(|k| {
                let beside = camera_looking(-light + DVec3::X * (0.3 + 0.02 * k as f64));
                match ProjectiveFrame::fit(&beside, light, 20.0) {
                    Err(Unsupported::SunInImage) => 0,
                    Err(Unsupported::TooWide(span)) => {
                        assert!(span > MAX_SPAN_DEGREES && span < 180.0, "{span}");
                        1
                    }
                    Ok(_) => 2,
                    Err(other) => panic!("{other:?}"),
                }
            })
            .collect();
        assert!(stages.windows(2).all(|w| w[0] <= w[1]), "{stages:?}");
        assert!(
            [0, 1, 2].iter().all(|stage| stages.contains(stage)),
            "{stages:?}"
        );
        let mut ortho = Camera::pinhole_looking_at(Vec3::ZERO, Vec3::X, 35.0, WIDTH, HEIGHT);
        ortho.projection = crate::scene::Projection::orthographic(10.0);
        assert_eq!(
            ProjectiveFrame::fit(&CameraModel::new(&ortho), light, 20.0),
            Err(Unsupported::Orthographic)
        );
    }

    #[test]
    fn auto_takes_projective_only_where_sharp_and_forcing_names_the_field() {
        let desc = RectifyDesc::prefiltered(0);
        let camera = sideways();
        // Shallow: from the near plane at 1 to 1.6 units, the far column is fine.
        let shallow = choose(Rectification::Auto, &camera, light(), 1.6, &desc, 0.05)
            .expect("auto never fails");
        let shallow = shallow.expect("projective for a shallow frustum");
        assert!(shallow.is_sharp(0.05), "{}", shallow.far_column_length());
        // Deep: 1 to 40 units; the last of its columns covers many texels.
        let deep = choose(Rectification::Auto, &camera, light(), 40.0, &desc, 0.05).unwrap();
        assert!(deep.is_none());
        let forced = choose(
            Rectification::Projective,
            &camera,
            light(),
            40.0,
            &desc,
            0.05,
        );
        let forced = forced.expect("valid view").expect("a grid");
        assert!(forced.far_column_length() > 10.0 * 0.05);
        assert!(
            choose(Rectification::Epipolar, &camera, light(), 1.6, &desc, 0.05)
                .unwrap()
                .is_none()
        );
        let into_sun = camera_looking(-light());
        assert!(
            choose(Rectification::Auto, &into_sun, light(), 1.6, &desc, 0.05)
                .unwrap()
                .is_none()
        );
        match choose(
            Rectification::Projective,
            &into_sun,
            light(),
            1.6,
            &desc,
            0.05,
        ) {
            Err(Error::InvalidInput { field, reason }) => {
                assert_eq!(field, "render.rectification");
                assert!(reason.contains("sun"), "{reason}");
            }
            other => panic!("expected an invalid-input error, got {other:?}"),
        }
    }

    #[test]
    fn column_spacing_is_uniform_in_reciprocal_distance() {
        let grid = grid();
        for column in [0.0, 0.5, 3.0, grid.columns as f64 - 0.5] {
            let x = 1.0 / grid.reciprocal_at_column(column);
            assert!((grid.column_at(x) - column).abs() < 1e-6, "{column}");
        }
        let widths: Vec<f64> = (0..grid.columns)
            .map(|c| {
                1.0 / grid.reciprocal_at_column(c as f64 + 1.0)
                    - 1.0 / grid.reciprocal_at_column(c as f64)
            })
            .collect();
        assert!(
            widths.windows(2).all(|w| w[1] > w[0]),
            "columns widen with X"
        );
    }
}
