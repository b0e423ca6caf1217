//! Silhouette enhancement (papers 000/001 §4.1, Eq. 3): occluders are extruded along the
//! view rays, away from the camera, by a 1D dilation of the shadow map along epipolar
//! lines; an optional 1D erosion along the same lines afterwards makes it a closure.
//!
//! **The kernel.** View rays project into the map as lines through the epipole (the
//! camera's position in the map). A texel t takes the minimum over samples s on a line
//! through it, between t and at most `length` texels towards the epipole, of the depth
//! that the view ray through the occluder at s reaches once it has travelled on to t. For
//! a pinhole camera at light depth z_l that is Eq. 3,
//! `z'_t = min(z_t, z_l + d(t)/d(s) · (z_s − z_l))`, d being the 2D distance to the
//! epipole. For an orthographic camera the lines are parallel and Eq. 3 becomes linear,
//! `z'_t = min(z_t, z_s + k · |t − s|)`, with k the view direction's light-depth change
//! per texel. Both are flat minima of a transformed signal: `u = (z − z_l)/d` (or
//! `u = z − k·a`, a the position along the line) is minimised over the window and mapped
//! back at t, which is what lets a running minimum compute them.
//!
//! **Discretization.** The lines are a fixed family, stepped one texel column at a time
//! along their major axis, and sampled at each column's centre in the texel containing
//! the line there:
//! - Pinhole: texels are split by major axis (x where |Δx| ≥ |Δy| from the epipole, else
//!   y) and side of the epipole into four cones. In a cone whose farthest column lies at
//!   major distance M, ray i leaves the epipole and crosses that column at minor
//!   coordinate `i + ½`; at column q (centre at major distance X) it samples the texel
//!   containing `(i + ½)·X/M + l_minor·(M − X)/M`. The cone's rays are those with
//!   |i + ½ − l_minor| ≤ M + 1 (slopes up to 1 + 1/M): they are at most a texel apart at
//!   every column, so each texel of the cone is crossed by at least one.
//! - Orthographic: line i samples at column q the row `i + ⌊½ + m·(q + ½)⌋`, m the
//!   direction's minor-per-major slope; every texel lies on exactly one line.
//!
//! Along one ray, the kernel of its sample at column q holds that sample and the ray's
//! samples at the 1..=n columns before it (towards the epipole, never past it), with
//! n = ⌊length / step⌋ and step = √(1 + slope²) the distance one column moves along the
//! ray. A texel's result is the lowest over the rays of its cone that cross it (near
//! the epipole many do: a texel there spans a wedge of directions); a texel that none
//! crosses, through rounding, takes the ray that passes nearest its centre. Samples
//! outside the map take no part. The closure is, per ray, the erosion over the n samples
//! after t of that ray's dilation, mapped the same way and kept at or below the original
//! depth (it could only exceed it by rounding); its result is again the lowest over rays.
//! The texel holding the epipole is left as it is.
//!
//! [`apply`] sweeps all rays of a cone together, column by column, with running extrema
//! along the rays; [`apply_naive`] walks each texel's rays sample by sample. They
//! evaluate the same expressions on the same samples, so they agree exactly.
//!
//! Only the scattering's copy of the map is changed; surface shadows keep the original.

use std::sync::atomic::{AtomicU32, Ordering};

use glam::{DMat4, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::CameraModel;
use crate::error::{Error, Result, Sizing};
use crate::morphology::check_depth;
use crate::running::{BlockExtrema, Max, Min, Pick};
use crate::spare::Spare;

/// Where view rays come from, in the map's texel space (see
/// [`crate::shadow_map::ShadowMap::texel_from_world`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Epipole {
    /// Pinhole camera: its position, texel x and y and light depth (z_l of Eq. 3). It may
    /// lie inside or outside the map.
    Point(DVec3),
    /// Orthographic camera: its view direction, texels and light depth per unit of
    /// travel. Lines run along (x, y), away from an epipole at infinity behind; with a
    /// unit (x, y), z is the depth slope per texel. A direction along the light (zero
    /// x and y) extrudes nothing.
    Direction(DVec3),
}

impl Epipole {
    /// The epipole of `camera` in a map with this `texel_from_world`.
    pub fn of_camera(camera: &CameraModel, texel_from_world: &DMat4) -> Self {
        if camera.is_perspective() {
            Epipole::Point(texel_from_world.transform_point3(camera.position()))
        } else {
            let view = camera.world_from_camera.transform_vector3(DVec3::NEG_Z);
            Epipole::Direction(texel_from_world.transform_vector3(view))
        }
    }
}

/// Dilation alone, or dilation then erosion.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SilhouetteOp {
    #[default]
    Dilate,
    Close,
}

/// One silhouette filter. A length of 0 leaves the map unchanged.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SilhouetteDesc {
    pub op: SilhouetteOp,
    /// How far occluders are extruded, in texels along the line.
    pub length_texels: f32,
}

impl SilhouetteDesc {
    pub fn dilate(length_texels: f32) -> Self {
        Self {
            op: SilhouetteOp::Dilate,
            length_texels,
        }
    }

    pub fn close(length_texels: f32) -> Self {
        Self {
            op: SilhouetteOp::Close,
            length_texels,
        }
    }
}

/// Extrudes the occluders of a `size`×`size` depth map (row-major) away from `epipole`.
pub fn apply(
    depth: &[f32],
    size: u32,
    epipole: Epipole,
    desc: &SilhouetteDesc,
) -> Result<Vec<f32>> {
    let Some(lines) = Lines::new(depth, size, epipole, desc)? else {
        return Ok(depth.to_vec());
    };
    let swept = lines.sweep()?;
    swept.par_iter().enumerate().for_each(|(index, bits)| {
        if bits.load(Ordering::Relaxed) == UNSET {
            bits.store(lines.naive_texel(index).to_bits(), Ordering::Relaxed);
        }
    });
    // In place: the sweep's buffer becomes the result.
    Ok(swept
        .into_iter()
        .map(|bits| f32::from_bits(bits.into_inner()))
        .collect())
}

/// The same filter evaluated texel by texel, walking each texel's rays: the definition
/// that [`apply`] is tested against. O(length) per ray and texel, O(length²) for the
/// closure.
pub fn apply_naive(
    depth: &[f32],
    size: u32,
    epipole: Epipole,
    desc: &SilhouetteDesc,
) -> Result<Vec<f32>> {
    let Some(lines) = Lines::new(depth, size, epipole, desc)? else {
        return Ok(depth.to_vec());
    };
    Ok((0..depth.len())
        .into_par_iter()
        .map(|index| lines.naive_texel(index))
        .collect())
}

/// One family of lines flattened into per-column and per-ray tables: what an evaluator
/// that walks each texel's rays on its own (the Vulkan backend) needs to visit the same
/// samples and evaluate the same expressions as [`apply_naive`].
#[derive(Clone, Debug, PartialEq)]
pub struct FamilyTables {
    /// Columns run along texel x (else y).
    pub x_major: bool,
    /// +1 or −1: the direction, along the major axis, away from the epipole.
    pub sign: i32,
    /// Pinhole rays from a point (else parallel orthographic lines).
    pub fan: bool,
    /// Epipole coordinates along the major and minor axes (pinhole).
    pub major: f64,
    pub minor: f64,
    /// Inclusive range of the rays that reach the map.
    pub rays: (i32, i32),
    /// Depth transform base (z_l for a pinhole camera).
    pub base: f32,
    /// Per column: ray i samples row ⌊(i + ½)·along + shift⌋, and the ray nearest a texel
    /// centre c is ⌊c·inv_along − inv_shift⌋ (pinhole).
    pub along: Vec<f64>,
    pub shift: Vec<f64>,
    pub inv_along: Vec<f64>,
    pub inv_shift: Vec<f64>,
    /// Per column: line i samples row i + `rows` (orthographic).
    pub rows: Vec<i32>,
    /// Per column: the depth transform `u = (z − base)·scale − offset`, back by `unscale`.
    pub scale: Vec<f32>,
    pub offset: Vec<f32>,
    pub unscale: Vec<f32>,
    /// Per column: whether the rays visit it (pinhole rays start past the epipole).
    pub visits: Vec<bool>,
    /// Kernel length in columns of rays `steps_first..`, a little wider than `rays` so
    /// that the ray nearest any texel of the cone has an entry.
    pub steps_first: i32,
    pub steps: Vec<u32>,
}

/// Rays past either end of a family's range that [`FamilyTables::steps`] covers: the ray
/// nearest a texel of the cone lies at most a ray or two outside `rays`.
pub const STEPS_MARGIN: i32 = 4;

/// The line families of a filter as tables, in the order texels look them up (a texel
/// belongs to the first whose cone holds it); `None` when the filter changes nothing.
/// Validates like [`apply`], without the depth.
pub fn family_tables(
    size: u32,
    epipole: Epipole,
    desc: &SilhouetteDesc,
) -> Result<Option<Vec<FamilyTables>>> {
    let probe = [f32::INFINITY];
    // The depth only takes part in validation; a one-texel stand-in checks the rest.
    let Some(lines) = Lines::new_for(&probe, size, epipole, desc)? else {
        return Ok(None);
    };
    let narrow = |value: i64| {
        i32::try_from(value).map_err(|_| {
            Error::invalid(
                EPIPOLE_FIELD,
                format!("{epipole:?} puts rays beyond 32-bit indices"),
            )
        })
    };
    let n = lines.size;
    lines
        .families
        .iter()
        .map(|family| {
            let rays = (narrow(family.rays.0)?, narrow(family.rays.1)?);
            let steps_first = rays.0 - STEPS_MARGIN;
            let steps = (steps_first as i64..=rays.1 as i64 + STEPS_MARGIN as i64)
                .map(|ray| family.steps(ray, lines.length) as u32)
                .collect();
            let (major, minor, along, shift, inv_along, inv_shift, rows) = match &family.kind {
                Kind::Fan {
                    major,
                    minor,
                    along,
                    shift,
                    inv_along,
                    inv_shift,
                    ..
                } => (
                    *major,
                    *minor,
                    along.clone(),
                    shift.clone(),
                    inv_along.clone(),
                    inv_shift.clone(),
                    vec![0; n],
                ),
                Kind::Parallel { rows, .. } => (
                    0.0,
                    0.0,
                    vec![0.0; n],
                    vec![0.0; n],
                    vec![0.0; n],
                    vec![0.0; n],
                    rows.iter()
                        .map(|&row| narrow(row))
                        .collect::<Result<Vec<_>>>()?,
                ),
            };
            Ok(FamilyTables {
                x_major: family.axis == Axis::X,
                sign: family.sign as i32,
                fan: matches!(family.kind, Kind::Fan { .. }),
                major,
                minor,
                rays,
                base: family.base,
                along,
                shift,
                inv_along,
                inv_shift,
                rows,
                scale: family.scale.clone(),
                offset: family.offset.clone(),
                unscale: family.unscale.clone(),
                visits: (0..n).map(|q| family.visits(q)).collect(),
                steps_first,
                steps,
            })
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}

const LENGTH_FIELD: &str = "style.silhouette.length";
const EPIPOLE_FIELD: &str = "style.silhouette.epipole";

/// Largest coordinate of a pinhole epipole that the single-precision depth transform
/// handles.
const MAX_POINT: f64 = 1.0e12;

/// Marks texels no ray has written yet; outputs are never NaN.
const UNSET: u32 = 0x7fc0_dead;

/// Rays swept together: the lanes of the sweep's inner loops.
const LANES: usize = 32;

/// ⌊x⌋ for the map's texel lookups, without a libm call (baseline x86-64 has no rounding
/// instruction): the truncation of x shifted positive. Below 2²⁰ texels it is the floor
/// of x rounded by at most 2⁻³² of a texel, the same for every caller; rows far outside
/// stay outside, and it never decreases with x, which the sweep relies on.
#[inline(always)]
fn floor(x: f64) -> i64 {
    const SHIFT: i64 = 1 << 20;
    (x.max(-1.0e12) + SHIFT as f64) as i64 - SHIFT
}

/// Whole column steps within `length` texels along a line of minor-per-major `slope`.
fn column_steps(length: f64, slope: f64) -> usize {
    (length / (1.0 + slope * slope).sqrt()).floor() as usize
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Axis {
    X,
    Y,
}

/// The rays of one cone (pinhole) or all lines of the map (orthographic), stepping along
/// `axis` in direction `sign`, away from the epipole.
#[derive(Debug)]
struct Family {
    axis: Axis,
    sign: i64,
    /// Columns (major-axis indices) in the order the rays visit them, epipole first.
    columns: Vec<usize>,
    /// Inclusive range of the rays that reach the map.
    rays: (i64, i64),
    /// Per column: the inclusive range of minor indices in this family's cone.
    cone: Vec<(i64, i64)>,
    kind: Kind,
    /// Per column: the depth transform (see [`Transform`]).
    base: f32,
    scale: Vec<f32>,
    offset: Vec<f32>,
    unscale: Vec<f32>,
    /// Per column: the major distance X from the epipole (pinhole).
    distance: Vec<f64>,
}

#[derive(Debug)]
enum Kind {
    Fan {
        /// Epipole coordinates along the major and minor axes.
        major: f64,
        minor: f64,
        /// Major distance M of the farthest column.
        far: f64,
        /// Per column: `X/M` and `l_minor·(M − X)/M`, which place ray i at
        /// `(i + ½)·X/M + l_minor·(M − X)/M`; and `M/X` and `l_minor·(M − X)/X`, which
        /// give the ray through a texel centre c as `c·M/X − l_minor·(M − X)/X − ½`.
        along: Vec<f64>,
        shift: Vec<f64>,
        inv_along: Vec<f64>,
        inv_shift: Vec<f64>,
    },
    Parallel {
        /// Per column: the row offset ⌊½ + m·(q + ½)⌋ of line 0.
        rows: Vec<i64>,
        steps: usize,
    },
}

impl Family {
    fn fan(epipole: DVec3, axis: Axis, sign: i64, size: usize) -> Option<Family> {
        let (major, minor) = match axis {
            Axis::X => (epipole.x, epipole.y),
            Axis::Y => (epipole.y, epipole.x),
        };
        let distance = |q: usize| sign as f64 * ((q as f64 + 0.5) - major);
        let mut columns: Vec<usize> = (0..size).filter(|&q| distance(q) > 0.0).collect();
        if sign < 0 {
            columns.reverse();
        }
        let &far_q = columns.last()?;
        let far = distance(far_q);
        let mut along = vec![0.0; size];
        let mut shift = vec![0.0; size];
        let mut inv_along = vec![0.0; size];
        let mut inv_shift = vec![0.0; size];
        let mut scale = vec![0.0; size];
        let mut unscale = vec![0.0; size];
        let mut distances = vec![0.0; size];
        for &q in &columns {
            let x = distance(q);
            let behind = far_q.abs_diff(q) as f64;
            along[q] = x / far;
            shift[q] = minor * (behind / far);
            inv_along[q] = far / x;
            inv_shift[q] = minor * (behind / x);
            scale[q] = (1.0 / x) as f32;
            unscale[q] = x as f32;
            distances[q] = x;
        }
        // The cone's rays, |i + ½ − l_minor| ≤ M + 1, narrowed to those whose sample at
        // some column lies in the map (with a margin against rounding): the others
        // change nothing.
        let mut reach = (f64::INFINITY, f64::NEG_INFINITY);
        for &q in &columns {
            let first = -shift[q] / along[q] - 0.5;
            let last = (size as f64 - shift[q]) / along[q] - 0.5;
            reach = (reach.0.min(first), reach.1.max(last));
        }
        let lo = (minor - far - 1.5).ceil().max(reach.0 - 2.0);
        let hi = (minor + far + 0.5).floor().min(reach.1 + 2.0);
        if lo.is_nan() || hi.is_nan() || lo > hi {
            return None;
        }
        let mut family = Family {
            axis,
            sign,
            columns,
            rays: (lo as i64, hi as i64),
            cone: Vec::new(),
            kind: Kind::Fan {
                major,
                minor,
                far,
                along,
                shift,
                inv_along,
                inv_shift,
            },
            base: epipole.z as f32,
            offset: vec![0.0; size],
            scale,
            unscale,
            distance: distances,
        };
        family.cone = (0..size).map(|q| family.cone_rows(q, size)).collect();
        Some(family)
    }

    /// `None` when the direction runs along the light: lines are points and nothing moves.
    fn parallel(direction: DVec3, size: usize, length: f64) -> Option<Family> {
        let (axis, major, minor) = if direction.x.abs() >= direction.y.abs() {
            (Axis::X, direction.x, direction.y)
        } else {
            (Axis::Y, direction.y, direction.x)
        };
        if major.abs() <= 1e-12 * direction.length() {
            return None;
        }
        let sign = if major > 0.0 { 1 } else { -1 };
        let slope = minor / major.abs();
        let depth_per_step = direction.z / major.abs();
        let rows: Vec<i64> = (0..size)
            .map(|q| floor(0.5 + slope * (q as f64 + 0.5)))
            .collect();
        let lowest = rows.iter().copied().min().unwrap_or(0);
        let highest = rows.iter().copied().max().unwrap_or(0);
        let mut columns: Vec<usize> = (0..size).collect();
        if sign < 0 {
            columns.reverse();
        }
        let steps = column_steps(length, slope);
        Some(Family {
            axis,
            sign,
            columns,
            rays: (-highest, size as i64 - 1 - lowest),
            cone: vec![(0, size as i64 - 1); size],
            kind: Kind::Parallel { rows, steps },
            base: 0.0,
            scale: vec![1.0; size],
            offset: (0..size)
                .map(|q| (depth_per_step * (sign * q as i64) as f64) as f32)
                .collect(),
            unscale: vec![1.0; size],
            distance: vec![f64::INFINITY; size],
        })
    }

    /// The minor indices of column `q` in this pinhole family's cone (|Δminor| ≤ Δmajor,
    /// strictly for y so that diagonals go to x): an interval, found from its estimate
    /// and settled with the exact test.
    fn cone_rows(&self, q: usize, size: usize) -> (i64, i64) {
        let Kind::Fan { minor, .. } = &self.kind else {
            return (0, size as i64 - 1);
        };
        if !self.visits(q) {
            return (0, -1);
        }
        let x = self.distance[q];
        let last = size as f64 - 1.0;
        let mut lo = (minor - x - 0.5).ceil().clamp(0.0, last) as usize;
        let mut hi = (minor + x - 0.5).floor().clamp(0.0, last) as usize;
        while lo > 0 && self.in_cone(q, lo - 1) {
            lo -= 1;
        }
        while lo <= hi && !self.in_cone(q, lo) {
            lo += 1;
        }
        while hi + 1 < size && self.in_cone(q, hi + 1) {
            hi += 1;
        }
        while hi >= lo && !self.in_cone(q, hi) {
            if hi == 0 {
                return (0, -1);
            }
            hi -= 1;
        }
        if lo > hi {
            return (0, -1);
        }
        (lo as i64, hi as i64)
    }

    /// Whether texel (major `q`, minor `r`) lies in this family's cone: on its side of
    /// the epipole, nearer its major axis than the other (ties go to x).
    #[inline]
    fn in_cone(&self, q: usize, r: usize) -> bool {
        let Kind::Fan { major, minor, .. } = &self.kind else {
            return true;
        };
        let along = (q as f64 + 0.5) - major;
        let across = (r as f64 + 0.5) - minor;
        let nearer = match self.axis {
            Axis::X => along.abs() >= across.abs(),
            Axis::Y => along.abs() > across.abs(),
        };
        nearer && along * self.sign as f64 > 0.0
    }

    /// Whether the family's rays visit column `q` (pinhole rays start past the epipole).
    #[inline]
    fn visits(&self, q: usize) -> bool {
        match &self.kind {
            Kind::Fan { .. } => self.distance[q] > 0.0,
            Kind::Parallel { .. } => true,
        }
    }

    /// The minor index ray `ray` samples at column `q`.
    #[inline]
    fn row(&self, ray: i64, q: usize) -> i64 {
        match &self.kind {
            Kind::Fan { along, shift, .. } => floor((ray as f64 + 0.5) * along[q] + shift[q]),
            Kind::Parallel { rows, .. } => ray + rows[q],
        }
    }

    /// The ray passing nearest the centre of texel (major `q`, minor `r`).
    fn nearest(&self, q: usize, r: usize) -> i64 {
        match &self.kind {
            Kind::Fan {
                inv_along,
                inv_shift,
                ..
            } => floor((r as f64 + 0.5) * inv_along[q] - inv_shift[q]),
            Kind::Parallel { rows, .. } => r as i64 - rows[q],
        }
    }

    /// The rays of the family that cross texel (major `q`, minor `r`): a contiguous
    /// range, since a column's samples never decrease with the ray index.
    fn crossing(&self, q: usize, r: usize) -> Option<std::ops::RangeInclusive<i64>> {
        let (first, last) = self.rays;
        let r = r as i64;
        let mut ray = self.nearest(q, r as usize).clamp(first, last);
        while ray > first && self.row(ray, q) > r {
            ray -= 1;
        }
        while ray < last && self.row(ray, q) < r {
            ray += 1;
        }
        if self.row(ray, q) != r {
            return None;
        }
        let (mut lo, mut hi) = (ray, ray);
        while lo > first && self.row(lo - 1, q) == r {
            lo -= 1;
        }
        while hi < last && self.row(hi + 1, q) == r {
            hi += 1;
        }
        Some(lo..=hi)
    }

    /// Number of columns the kernel reaches back from a sample of ray `ray`; never more
    /// than there are columns.
    fn steps(&self, ray: i64, length: f64) -> usize {
        let steps = match &self.kind {
            Kind::Fan { minor, far, .. } => {
                let slope = (ray as f64 + 0.5 - minor) / far;
                column_steps(length, slope)
            }
            Kind::Parallel { steps, .. } => *steps,
        };
        steps.min(self.columns.len())
    }

    /// The depth transform at column `q`.
    #[inline(always)]
    fn transform(&self, q: usize) -> Transform {
        Transform {
            base: self.base,
            scale: self.scale[q],
            offset: self.offset[q],
            unscale: self.unscale[q],
        }
    }

    /// The rows the `rows.len()` rays from `first` on sample at column `q`.
    #[inline(always)]
    fn rows_into(&self, first: i64, q: usize, rows: &mut [i64]) {
        match &self.kind {
            Kind::Fan { along, shift, .. } => {
                let (along, shift) = (along[q], shift[q]);
                for (k, row) in rows.iter_mut().enumerate() {
                    *row = floor(((first + k as i64) as f64 + 0.5) * along + shift);
                }
            }
            Kind::Parallel { rows: offsets, .. } => {
                let offset = offsets[q];
                for (k, row) in rows.iter_mut().enumerate() {
                    *row = first + k as i64 + offset;
                }
            }
        }
    }
}

/// The map between depth and the flat-kernel signal at one column:
/// `u = (z − base)·scale − offset` and `z = base + (u + offset)·unscale`. Single
/// precision: its rounding (a few ulps of the depths involved) is far below any shadow
/// bias, and it halves the sweep's memory traffic.
#[derive(Clone, Copy)]
struct Transform {
    base: f32,
    scale: f32,
    offset: f32,
    unscale: f32,
}

impl Transform {
    #[inline(always)]
    fn forward(self, z: f32) -> f32 {
        (z - self.base) * self.scale - self.offset
    }

    /// Back to a depth. Clamped above −∞ so that a steep extrusion towards the light
    /// cannot leave an unusable depth in the map.
    #[inline(always)]
    fn back(self, u: f32) -> f32 {
        (self.base + (u + self.offset) * self.unscale).max(f32::MIN)
    }
}

struct Lines<'a> {
    depth: &'a [f32],
    size: usize,
    close: bool,
    length: f64,
    families: Vec<Family>,
}

impl<'a> Lines<'a> {
    /// Validates the inputs; `None` when the filter changes nothing.
    fn new(
        depth: &'a [f32],
        size: u32,
        epipole: Epipole,
        desc: &SilhouetteDesc,
    ) -> Result<Option<Self>> {
        Self::validated(depth, size, epipole, desc, true)
    }

    /// The lines of a `size`² map without its depth (`depth` is not read): for
    /// [`family_tables`].
    fn new_for(
        depth: &'a [f32],
        size: u32,
        epipole: Epipole,
        desc: &SilhouetteDesc,
    ) -> Result<Option<Self>> {
        Self::validated(depth, size, epipole, desc, false)
    }

    fn validated(
        depth: &'a [f32],
        size: u32,
        epipole: Epipole,
        desc: &SilhouetteDesc,
        check: bool,
    ) -> Result<Option<Self>> {
        let length = desc.length_texels;
        if !length.is_finite() || length < 0.0 {
            return Err(Error::invalid(
                LENGTH_FIELD,
                format!("{length} must be a finite number of texels, zero or more"),
            ));
        }
        let (Epipole::Point(v) | Epipole::Direction(v)) = epipole;
        if !v.is_finite() {
            return Err(Error::invalid(
                EPIPOLE_FIELD,
                format!("{v:?} is not finite"),
            ));
        }
        // The depth transform runs in single precision (see `Transform`).
        if matches!(epipole, Epipole::Point(_)) && v.abs().max_element() > MAX_POINT {
            return Err(Error::invalid(
                EPIPOLE_FIELD,
                format!("{v:?} lies too far from the map (beyond {MAX_POINT:e} texels or depth units); use a direction for a camera at infinity"),
            ));
        }
        let size = if check {
            check_depth(depth, size)?
        } else {
            size as usize
        };
        if length < 1.0 || size == 0 {
            return Ok(None);
        }
        let length = length as f64;
        let families = match epipole {
            Epipole::Point(p) => [Axis::X, Axis::Y]
                .into_iter()
                .flat_map(|axis| [1, -1].map(|sign| (axis, sign)))
                .filter_map(|(axis, sign)| Family::fan(p, axis, sign, size))
                .collect(),
            Epipole::Direction(d) => match Family::parallel(d, size, length) {
                Some(family) => vec![family],
                None => return Ok(None),
            },
        };
        Ok(Some(Self {
            depth,
            size,
            close: desc.op == SilhouetteOp::Close,
            length,
            families,
        }))
    }

    /// Index of the texel at major `q`, minor `r` of `axis`.
    #[inline(always)]
    fn index(&self, axis: Axis, q: usize, r: usize) -> usize {
        match axis {
            Axis::X => r * self.size + q,
            Axis::Y => q * self.size + r,
        }
    }

    /// Depth of the texel ray `ray` samples at column `q`, if inside the map.
    fn sample(&self, family: &Family, ray: i64, q: usize) -> Option<f32> {
        let r = family.row(ray, q);
        (0..self.size as i64)
            .contains(&r)
            .then(|| self.depth[self.index(family.axis, q, r as usize)])
    }

    /// The column `j` steps from `q` along the rays (negative: towards the epipole), if
    /// it is one the family's rays visit.
    fn step(&self, family: &Family, q: usize, j: i64) -> Option<usize> {
        let q = q as i64 + family.sign * j;
        if !(0..self.size as i64).contains(&q) {
            return None;
        }
        let q = q as usize;
        family.visits(q).then_some(q)
    }

    /// The dilation at column `q` of ray `ray`, whose own depth there is `own`.
    fn naive_dilation(&self, family: &Family, ray: i64, q: usize, own: f32) -> f32 {
        let mut lowest = Min::neutral::<f32>();
        for j in 1..=family.steps(ray, self.length) as i64 {
            let Some(s) = self.step(family, q, -j) else {
                break;
            };
            if let Some(z) = self.sample(family, ray, s) {
                lowest = Min::pick(lowest, family.transform(s).forward(z));
            }
        }
        Min::pick(own, family.transform(q).back(lowest))
    }

    /// The filter along one ray at column `q`, for a texel of depth `own`.
    fn naive_ray(&self, family: &Family, ray: i64, q: usize, own: f32) -> f32 {
        let dilated = self.naive_dilation(family, ray, q, own);
        if !self.close {
            return dilated;
        }
        let mut highest = Max::neutral::<f32>();
        for j in 1..=family.steps(ray, self.length) as i64 {
            let Some(s) = self.step(family, q, j) else {
                break;
            };
            if let Some(z) = self.sample(family, ray, s) {
                let d = self.naive_dilation(family, ray, s, z);
                highest = Max::pick(highest, family.transform(s).forward(d));
            }
        }
        Min::pick(own, Max::pick(dilated, family.transform(q).back(highest)))
    }

    fn naive_texel(&self, index: usize) -> f32 {
        let own = self.depth[index];
        let (x, y) = (index % self.size, index / self.size);
        let found = self.families.iter().find_map(|family| {
            let (q, r) = match family.axis {
                Axis::X => (x, y),
                Axis::Y => (y, x),
            };
            family.in_cone(q, r).then_some((family, q, r))
        });
        let Some((family, q, r)) = found else {
            return own;
        };
        match family.crossing(q, r) {
            Some(rays) => rays
                .map(|ray| self.naive_ray(family, ray, q, own))
                .fold(Min::neutral(), Min::pick),
            None => self.naive_ray(family, family.nearest(q, r), q, own),
        }
    }

    /// Runs every family's rays and returns, per texel, the lowest result over the rays
    /// that cross it, as bits, or [`UNSET`] where none does.
    ///
    /// The sweep reads a copy of the map with rows `stride` apart, a little more than the
    /// map's width: along x-major rays the lanes of a column are a row apart, and with a
    /// power-of-two row length they would all fall into the same cache set.
    fn sweep(&self) -> Result<Vec<AtomicU32>> {
        let n = self.size;
        let stride = n + PAD;
        // Every value is written below, in parallel, so a kept copy's old values do not
        // matter. Allocated afresh every frame and filled with +∞ first, in this one
        // thread, the copy of tree's 1024² map took 1.8–2.2 ms of a 16 ms closure; kept,
        // 0.2 ms.
        let mut padded = SPARE_PADDED_MAPS.try_take(n * stride, || {
            format!("the silhouette filter's copy of the {n}² shadow map")
        })?;
        padded
            .par_chunks_mut(stride)
            .zip(self.depth.par_chunks(n))
            .for_each(|(row, src)| {
                let (values, padding) = row.split_at_mut(n);
                values.copy_from_slice(src);
                padding.fill(f32::INFINITY);
            });
        let grid = Grid {
            depth: &padded,
            stride,
        };
        let out: Vec<AtomicU32> = (0..n * n)
            .into_par_iter()
            .map(|_| AtomicU32::new(UNSET))
            .collect();
        for family in &self.families {
            self.sweep_family(family, &grid, &out);
        }
        SPARE_PADDED_MAPS.keep(padded);
        Ok(out)
    }

    fn sweep_family(&self, family: &Family, grid: &Grid, out: &[AtomicU32]) {
        // Bundles of adjacent rays that share a kernel length.
        let mut bundles: Vec<Bundle> = Vec::new();
        let (first, last) = family.rays;
        for ray in first..=last {
            let steps = family.steps(ray, self.length);
            match bundles.last_mut() {
                Some(b) if b.steps == steps && b.count < LANES => b.count += 1,
                _ => bundles.push(Bundle {
                    first: ray,
                    count: 1,
                    steps,
                }),
            }
        }
        // Bundles write the texels only their own rays cross (see `scatter`) at once; the
        // few they share with a neighbour are merged here, in a fixed order, though the
        // minimum would not depend on it.
        let edges: Vec<Vec<(usize, f32)>> = bundles
            .par_iter()
            .map_init(Sweep::default, |sweep, bundle| {
                sweep.run(self, family, bundle, grid, out);
                std::mem::take(&mut sweep.edges)
            })
            .collect();
        for (texel, value) in edges.into_iter().flatten() {
            lower(&out[texel], value);
        }
    }
}

/// Lowers a texel's value to `value`, or sets it if nothing has yet.
#[inline]
fn lower(texel: &AtomicU32, value: f32) {
    let bits = texel.load(Ordering::Relaxed);
    if bits == UNSET || value < f32::from_bits(bits) {
        texel.store(value.to_bits(), Ordering::Relaxed);
    }
}

/// Texels of padding per row of the sweep's copy of the map (64 bytes).
const PAD: usize = 16;

// The sweep's copy of the map, kept from one frame's filter for the next (see
// `crate::spare`).
static SPARE_PADDED_MAPS: Spare<f32> = Spare::new(Sizing::Rectified);

/// Lets go of the sweep's kept copy ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    SPARE_PADDED_MAPS.clear();
}

/// The map as the sweep reads it, rows `stride` apart.
struct Grid<'a> {
    depth: &'a [f32],
    stride: usize,
}

impl Grid<'_> {
    #[inline(always)]
    fn index(&self, axis: Axis, q: usize, r: usize) -> usize {
        match axis {
            Axis::X => r * self.stride + q,
            Axis::Y => q * self.stride + r,
        }
    }
}

/// Adjacent rays swept together.
#[derive(Debug)]
struct Bundle {
    first: i64,
    count: usize,
    /// Kernel length in columns, shared by the bundle's rays.
    steps: usize,
}

/// Scratch for sweeping one bundle; the buffers hold one row of lanes per column.
#[derive(Default)]
struct Sweep {
    rows: Vec<i64>,
    depth: Vec<f32>,
    transformed: Vec<f32>,
    dilated: Vec<f32>,
    window: Vec<f32>,
    blocks: Option<BlockExtrema<f32>>,
    /// Results for texels on the bundle's edge rays: (texel index, value).
    edges: Vec<(usize, f32)>,
}

impl Sweep {
    fn run(
        &mut self,
        lines: &Lines,
        family: &Family,
        bundle: &Bundle,
        grid: &Grid,
        out: &[AtomicU32],
    ) {
        let (width, steps) = (bundle.count, bundle.steps);
        let size = lines.size as i64;
        self.edges.clear();

        // The columns where the bundle meets the map: its rows there run from its first
        // ray's to its last ray's without gaps (rays are at most a texel apart), and the
        // columns outside hold only absent samples, which change no window.
        let last_ray = bundle.first + width as i64 - 1;
        let touches =
            |q: &usize| family.row(bundle.first, *q) < size && family.row(last_ray, *q) >= 0;
        let Some(begin) = family.columns.iter().position(touches) else {
            return;
        };
        let end = family.columns.iter().rposition(touches).unwrap_or(begin) + 1;
        let span = &family.columns[begin..end];
        let len = span.len() * width;
        let lanes = |c: usize| c * width..(c + 1) * width;

        self.rows.resize(len, 0);
        self.depth.resize(len, 0.0);
        self.transformed.resize(len, 0.0);
        for (c, &q) in span.iter().enumerate() {
            let rows = &mut self.rows[lanes(c)];
            family.rows_into(bundle.first, q, rows);
            let transform = family.transform(q);
            for ((&r, z), u) in rows
                .iter()
                .zip(&mut self.depth[lanes(c)])
                .zip(&mut self.transformed[lanes(c)])
            {
                *z = if (0..size).contains(&r) {
                    grid.depth[grid.index(family.axis, q, r as usize)]
                } else {
                    f32::INFINITY
                };
                *u = transform.forward(*z);
            }
        }
        if steps == 0 {
            scatter(
                lines,
                family,
                bundle,
                span,
                &self.rows,
                &self.depth,
                &mut self.edges,
                out,
            );
            return;
        }

        let blocks = self.blocks.get_or_insert_with(BlockExtrema::new);
        self.window.resize(width, 0.0);
        self.dilated.resize(len, 0.0);
        blocks.build::<Min>(&self.transformed, width, steps);
        for (c, &q) in span.iter().enumerate() {
            if c == 0 {
                self.window.fill(Min::neutral());
            } else {
                blocks.window_into::<Min>(c.saturating_sub(steps), c - 1, &mut self.window);
            }
            let transform = family.transform(q);
            // With a closure to follow, the erosion's input is prepared in the same pass.
            for ((((d, u), &z), &w), &r) in self.dilated[lanes(c)]
                .iter_mut()
                .zip(&mut self.transformed[lanes(c)])
                .zip(&self.depth[lanes(c)])
                .zip(&self.window)
                .zip(&self.rows[lanes(c)])
            {
                *d = Min::pick(z, transform.back(w));
                *u = if (0..size).contains(&r) {
                    transform.forward(*d)
                } else {
                    Max::neutral()
                };
            }
        }
        if !lines.close {
            scatter(
                lines,
                family,
                bundle,
                span,
                &self.rows,
                &self.dilated,
                &mut self.edges,
                out,
            );
            return;
        }

        blocks.build::<Max>(&self.transformed, width, steps);
        let last = span.len() - 1;
        for (c, &q) in span.iter().enumerate() {
            if c == last {
                self.window.fill(Max::neutral());
            } else {
                blocks.window_into::<Max>(c + 1, (c + steps).min(last), &mut self.window);
            }
            let transform = family.transform(q);
            // The closure overwrites the dilation column by column: a column's dilation
            // is not read again once its erosion is done.
            for ((d, &z), &w) in self.dilated[lanes(c)]
                .iter_mut()
                .zip(&self.depth[lanes(c)])
                .zip(&self.window)
            {
                *d = Min::pick(z, Max::pick(*d, transform.back(w)));
            }
        }
        scatter(
            lines,
            family,
            bundle,
            span,
            &self.rows,
            &self.dilated,
            &mut self.edges,
            out,
        );
    }
}

/// Writes a bundle's results, `values` at `rows` (one row of lanes per column of `span`),
/// for the texels of the family's cone. Rays that cross the same texel are adjacent, so
/// a column's lanes come in runs of equal rows, each reduced to its lowest value; a run
/// that no ray outside the bundle crosses is the texel's final value and is stored at
/// once, the bundle's first and last run otherwise go to `edges` to be merged.
#[allow(clippy::too_many_arguments)]
fn scatter(
    lines: &Lines,
    family: &Family,
    bundle: &Bundle,
    span: &[usize],
    rows: &[i64],
    values: &[f32],
    edges: &mut Vec<(usize, f32)>,
    out: &[AtomicU32],
) {
    let width = bundle.count;
    let (first, last) = (bundle.first, bundle.first + width as i64 - 1);
    for ((&q, rows), values) in span
        .iter()
        .zip(rows.chunks_exact(width))
        .zip(values.chunks_exact(width))
    {
        let (lo, hi) = family.cone[q];
        let shared_first = first > family.rays.0 && family.row(first - 1, q) == rows[0];
        let shared_last = last < family.rays.1 && family.row(last + 1, q) == rows[width - 1];
        let mut k = 0;
        while k < width {
            let r = rows[k];
            let mut value = values[k];
            let mut end = k + 1;
            while end < width && rows[end] == r {
                value = Min::pick(value, values[end]);
                end += 1;
            }
            if (lo..=hi).contains(&r) {
                let texel = lines.index(family.axis, q, r as usize);
                if (k == 0 && shared_first) || (end == width && shared_last) {
                    edges.push((texel, value));
                } else {
                    out[texel].store(value.to_bits(), Ordering::Relaxed);
                }
            }
            k = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn random_map(size: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..size * size)
            .map(|_| {
                if rng.random_bool(0.3) {
                    f32::INFINITY
                } else {
                    rng.random_range(0.0f32..100.0)
                }
            })
            .collect()
    }

    fn epipoles() -> Vec<Epipole> {
        vec![
            Epipole::Point(DVec3::new(30.3, 17.8, 40.0)),
            Epipole::Point(DVec3::new(30.5, 30.5, 120.0)),
            Epipole::Point(DVec3::new(-20.7, 45.1, -30.0)),
            Epipole::Point(DVec3::new(70.0, -12.0, 60.0)),
            Epipole::Direction(DVec3::new(0.6, 0.8, 0.4)),
            Epipole::Direction(DVec3::new(-1.0, 0.0, -0.2)),
        ]
    }

    #[test]
    fn every_texel_of_a_cone_is_crossed_by_its_rays() {
        // The sweep leaves only texels no ray crosses to the naive walk: there should be
        // none but the epipole's own.
        let size = 61;
        let map = random_map(size, 1);
        for epipole in epipoles() {
            let desc = SilhouetteDesc::close(12.0);
            let lines = Lines::new(&map, size as u32, epipole, &desc)
                .unwrap()
                .unwrap();
            let swept = lines.sweep().unwrap();
            let unset = swept
                .iter()
                .filter(|bits| bits.load(Ordering::Relaxed) == UNSET)
                .count();
            assert!(
                unset <= 1,
                "{epipole:?}: {unset} texels left to the naive walk"
            );
        }
    }

    #[test]
    fn tables_repeat_the_lines_and_cover_every_nearest_ray() {
        // A device walks texels with these tables alone: they must hold the families'
        // values, and a kernel length for the ray nearest any texel of a cone.
        let size = 53;
        let map = random_map(size, 3);
        for epipole in epipoles() {
            let desc = SilhouetteDesc::close(7.0);
            let lines = Lines::new(&map, size as u32, epipole, &desc)
                .unwrap()
                .unwrap();
            let tables = family_tables(size as u32, epipole, &desc).unwrap().unwrap();
            assert_eq!(tables.len(), lines.families.len());
            for (family, table) in lines.families.iter().zip(&tables) {
                assert_eq!(table.scale, family.scale);
                assert_eq!(table.rays, (family.rays.0 as i32, family.rays.1 as i32));
                let last = table.steps_first + table.steps.len() as i32 - 1;
                for q in 0..size {
                    for r in 0..size {
                        if !family.in_cone(q, r) {
                            continue;
                        }
                        let ray = family.nearest(q, r);
                        assert!(
                            (table.steps_first as i64..=last as i64).contains(&ray),
                            "{epipole:?}: ray {ray} of texel ({q}, {r}) outside the table"
                        );
                        let index = (ray - table.steps_first as i64) as usize;
                        assert_eq!(table.steps[index] as usize, family.steps(ray, lines.length));
                    }
                }
            }
        }
    }

    /// Eq. 3 written out: the minimum over the same samples of the depth each one's view
    /// ray reaches at t, mixed in double precision without the flat-kernel transform.
    fn eq3(lines: &Lines, epipole: Epipole, index: usize) -> f32 {
        let own = lines.depth[index];
        let (x, y) = (index % lines.size, index / lines.size);
        let Some((family, q, r)) = lines.families.iter().find_map(|family| {
            let (q, r) = match family.axis {
                Axis::X => (x, y),
                Axis::Y => (y, x),
            };
            family.in_cone(q, r).then_some((family, q, r))
        }) else {
            return own;
        };
        let rays = family
            .crossing(q, r)
            .unwrap_or_else(|| family.nearest(q, r)..=family.nearest(q, r));
        let mut lowest = own as f64;
        for ray in rays {
            for j in 1..=family.steps(ray, lines.length) as i64 {
                let Some(s) = lines.step(family, q, -j) else {
                    break;
                };
                let Some(z) = lines.sample(family, ray, s) else {
                    continue;
                };
                let z = z as f64;
                let reached = match (epipole, &family.kind) {
                    (Epipole::Point(l), Kind::Fan { .. }) => {
                        l.z + family.distance[q] / family.distance[s] * (z - l.z)
                    }
                    (Epipole::Direction(v), _) => {
                        let major = match family.axis {
                            Axis::X => v.x,
                            Axis::Y => v.y,
                        };
                        z + v.z / major.abs() * j as f64
                    }
                    _ => unreachable!(),
                };
                lowest = lowest.min(reached);
            }
        }
        lowest as f32
    }

    /// The sweep's kept copy of an earlier map (here one of NaN) leaves no trace: every
    /// texel of the padded copy is written before it is read.
    #[test]
    fn a_kept_copy_of_an_earlier_map_changes_nothing() {
        let size = 53;
        let map = random_map(size, 5);
        let stride = size + PAD;
        let mut stale = SPARE_PADDED_MAPS
            .try_take(size * stride, String::new)
            .unwrap();
        stale.fill(f32::NAN);
        SPARE_PADDED_MAPS.keep(stale);
        for epipole in epipoles() {
            let desc = SilhouetteDesc::close(7.5);
            let fast = apply(&map, size as u32, epipole, &desc).unwrap();
            let naive = apply_naive(&map, size as u32, epipole, &desc).unwrap();
            assert!(
                fast.iter()
                    .zip(&naive)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{epipole:?}"
            );
        }
    }

    #[test]
    fn flat_kernel_on_the_transformed_signal_is_eq3() {
        // The sweep minimises u = (z − z_l)/X (or z − k·a) in single precision and maps
        // the minimum back; written out, Eq. 3 differs from it by rounding alone, a few
        // ulps of the depths involved.
        let size = 45;
        let map = random_map(size, 2);
        for epipole in epipoles() {
            let desc = SilhouetteDesc::dilate(9.5);
            let lines = Lines::new(&map, size as u32, epipole, &desc)
                .unwrap()
                .unwrap();
            let naive = apply_naive(&map, size as u32, epipole, &desc).unwrap();
            let scale = match epipole {
                Epipole::Point(l) => l.z.abs() as f32,
                Epipole::Direction(_) => 0.0,
            };
            for (i, &value) in naive.iter().enumerate() {
                let expected = eq3(&lines, epipole, i);
                let tolerance = 4.0 * f32::EPSILON * (expected.abs() + scale + 100.0);
                assert!(
                    value == expected || (value - expected).abs() <= tolerance,
                    "{epipole:?} texel {i}: {value} vs Eq. 3 {expected}"
                );
            }
        }
    }
}
