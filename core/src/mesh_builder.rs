//! Procedural meshes: planes, quads, boxes, cylinders, tori and arches, accumulated into
//! one [`Mesh`].
//!
//! Every closed primitive shares the vertices of neighbouring faces, so each of its edges
//! belongs to exactly two triangles (watertight), and its triangles wind counter-clockwise
//! seen from outside. A primitive is placed by a transform as it is appended; a mirroring
//! transform keeps the winding outward. Angles are evaluated in f64 and rounded, so the
//! f32 positions do not depend on the platform's last-bit trigonometry in practice.

use std::f64::consts::{PI, TAU};

use glam::{Mat4, Vec3};

use crate::scene::Mesh;

/// Triangles under construction; each primitive appends its own vertices.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshBuilder {
    positions: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
}

/// An arched wall: a block with a doorway whose top is a semicircle, in the XZ plane.
///
/// The block spans x ∈ [−width/2, width/2], z ∈ [0, height] and y ∈ [−thickness/2,
/// thickness/2]. The opening is centred on x = 0: straight sides from z = 0 up to
/// `spring_height`, then a semicircle of `opening_radius`. The shape is sound when
/// `0 < opening_radius < width/2` and `spring_height + opening_radius < height`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Arch {
    pub width: f32,
    pub height: f32,
    pub thickness: f32,
    pub opening_radius: f32,
    /// Height of the opening's straight sides; 0 (or less) springs the arch from the base.
    pub spring_height: f32,
    /// Segments of the semicircle (at least 2 are used).
    pub segments: u32,
}

impl MeshBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }

    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Finishes the mesh with an identity `world_from_object`: positions are final.
    pub fn build(self, name: impl Into<String>, object_id: u32) -> Mesh {
        Mesh {
            name: name.into(),
            object_id,
            world_from_object: Mat4::IDENTITY,
            positions: self.positions,
            triangles: self.triangles,
            uvs: None,
            alpha_mask: None,
            blocks_sun: true,
            seen_by_camera: true,
        }
    }

    /// One free-standing quad of two triangles; the front is the side from which the
    /// corners run counter-clockwise.
    pub fn quad(&mut self, corners: [Vec3; 4]) {
        self.append(Mat4::IDENTITY, &corners, &[[0, 1, 2], [0, 2, 3]]);
    }

    /// An open, flat grid in the XY plane centred on the origin, facing +Z: `width` along
    /// X, `depth` along Y, with `cells_x` × `cells_y` cells (at least one each).
    pub fn grid(&mut self, transform: Mat4, width: f32, depth: f32, cells_x: u32, cells_y: u32) {
        let (nx, ny) = (cells_x.max(1), cells_y.max(1));
        let mut positions = Vec::with_capacity(((nx + 1) * (ny + 1)) as usize);
        for j in 0..=ny {
            for i in 0..=nx {
                positions.push(Vec3::new(
                    width * (i as f32 / nx as f32 - 0.5),
                    depth * (j as f32 / ny as f32 - 0.5),
                    0.0,
                ));
            }
        }
        let index = |i: u32, j: u32| j * (nx + 1) + i;
        let mut triangles = Vec::with_capacity((2 * nx * ny) as usize);
        for j in 0..ny {
            for i in 0..nx {
                push_quad(
                    &mut triangles,
                    [
                        index(i, j),
                        index(i + 1, j),
                        index(i + 1, j + 1),
                        index(i, j + 1),
                    ],
                );
            }
        }
        self.append(transform, &positions, &triangles);
    }

    /// A closed box of full extents `size`, centred on the origin: 8 vertices, 12 triangles.
    pub fn cuboid(&mut self, transform: Mat4, size: Vec3) {
        let half = size * 0.5;
        // Vertex i has x, y, z at the high side where bits 0, 1, 2 of i are set.
        let positions: Vec<Vec3> = (0..8u32)
            .map(|i| {
                let sign = |bit: u32| if i & bit != 0 { 1.0 } else { -1.0 };
                half * Vec3::new(sign(1), sign(2), sign(4))
            })
            .collect();
        let mut triangles = Vec::with_capacity(12);
        for face in [
            [0, 4, 6, 2], // −X
            [1, 3, 7, 5], // +X
            [0, 1, 5, 4], // −Y
            [2, 6, 7, 3], // +Y
            [0, 2, 3, 1], // −Z
            [4, 5, 7, 6], // +Z
        ] {
            push_quad(&mut triangles, face);
        }
        self.append(transform, &positions, &triangles);
    }

    /// A cylinder around +Z from z = 0 to z = `height`, with `segments` sides (at least 3).
    /// Capped, it is closed: 2·segments + 2 vertices and 4·segments triangles; uncapped,
    /// an open tube of 2·segments vertices and triangles.
    pub fn cylinder(
        &mut self,
        transform: Mat4,
        radius: f32,
        height: f32,
        segments: u32,
        capped: bool,
    ) {
        let n = segments.max(3);
        let mut positions = Vec::with_capacity(2 * n as usize + 2);
        for z in [0.0, height] {
            for i in 0..n {
                let (x, y) = polar(radius, TAU * f64::from(i) / f64::from(n));
                positions.push(Vec3::new(x, y, z));
            }
        }
        let mut triangles = Vec::with_capacity(4 * n as usize);
        for i in 0..n {
            let next = (i + 1) % n;
            push_quad(&mut triangles, [i, next, n + next, n + i]);
        }
        if capped {
            let (bottom, top) = (2 * n, 2 * n + 1);
            positions.push(Vec3::ZERO);
            positions.push(Vec3::new(0.0, 0.0, height));
            for i in 0..n {
                let next = (i + 1) % n;
                triangles.push([bottom, next, i]);
                triangles.push([top, n + i, n + next]);
            }
        }
        self.append(transform, &positions, &triangles);
    }

    /// A closed torus around the Z axis, centred on the origin: `segments_u` steps around
    /// the axis and `segments_v` around the tube (at least 3 each), giving u·v vertices
    /// and 2·u·v triangles.
    pub fn torus(
        &mut self,
        transform: Mat4,
        major_radius: f32,
        minor_radius: f32,
        segments_u: u32,
        segments_v: u32,
    ) {
        let (nu, nv) = (segments_u.max(3), segments_v.max(3));
        let (major, minor) = (f64::from(major_radius), f64::from(minor_radius));
        let mut positions = Vec::with_capacity((nu * nv) as usize);
        for u in 0..nu {
            let phi = TAU * f64::from(u) / f64::from(nu);
            for v in 0..nv {
                let theta = TAU * f64::from(v) / f64::from(nv);
                let ring = major + minor * theta.cos();
                positions.push(Vec3::new(
                    (ring * phi.cos()) as f32,
                    (ring * phi.sin()) as f32,
                    (minor * theta.sin()) as f32,
                ));
            }
        }
        let index = |u: u32, v: u32| (u % nu) * nv + v % nv;
        let mut triangles = Vec::with_capacity(2 * (nu * nv) as usize);
        for u in 0..nu {
            for v in 0..nv {
                push_quad(
                    &mut triangles,
                    [
                        index(u, v),
                        index(u + 1, v),
                        index(u + 1, v + 1),
                        index(u, v + 1),
                    ],
                );
            }
        }
        self.append(transform, &positions, &triangles);
    }

    /// A closed arched wall (see [`Arch`]).
    pub fn arch(&mut self, transform: Mat4, arch: &Arch) {
        let half_width = f64::from(arch.width) * 0.5;
        let height = f64::from(arch.height);
        let radius = f64::from(arch.opening_radius);
        let spring = f64::from(arch.spring_height).max(0.0);

        // The semicircle's samples, plus the two angles whose rays from its centre hit the
        // block's top corners, so that the outer boundary has vertices exactly there.
        let corner = (height - spring).atan2(half_width);
        let n = arch.segments.max(2);
        let mut angles: Vec<f64> = (0..=n).map(|k| PI * f64::from(k) / f64::from(n)).collect();
        for extra in [corner, PI - corner] {
            if angles.iter().all(|&a| (a - extra).abs() > 1e-9) {
                angles.push(extra);
            }
        }
        angles.sort_by(f64::total_cmp);
        let right_corner = angles.partition_point(|&a| a < corner - 1e-9);
        let left_corner = angles.partition_point(|&a| a < PI - corner - 1e-9);

        let inner: Vec<[f64; 2]> = angles
            .iter()
            .map(|&a| [radius * a.cos(), spring + radius * a.sin()])
            .collect();
        // Where each sample's ray from the semicircle's centre leaves the block.
        let outer: Vec<[f64; 2]> = angles
            .iter()
            .enumerate()
            .map(|(k, &a)| {
                if k == right_corner {
                    [half_width, height]
                } else if k == left_corner {
                    [-half_width, height]
                } else if k < right_corner {
                    [half_width, spring + half_width * a.tan()]
                } else if k > left_corner {
                    [-half_width, spring + half_width * (PI - a).tan()]
                } else {
                    [(height - spring) * a.cos() / a.sin(), height]
                }
            })
            .collect();

        // The outline runs counter-clockwise in (x, z); every face vertex lies on it.
        let m = angles.len() as u32;
        let mut outline: Vec<[f64; 2]> = Vec::with_capacity(2 * m as usize + 4);
        let jambs = spring > 0.0;
        if jambs {
            outline.push([-half_width, 0.0]);
            outline.push([-radius, 0.0]);
        }
        let inner_start = outline.len() as u32;
        outline.extend(inner.iter().rev());
        if jambs {
            outline.push([radius, 0.0]);
            outline.push([half_width, 0.0]);
        }
        let outer_start = outline.len() as u32;
        outline.extend(outer.iter());
        let inner_at = |k: u32| inner_start + (m - 1 - k);
        let outer_at = |k: u32| outer_start + k;

        let mut faces = Vec::with_capacity(2 * m as usize + 2);
        for k in 0..m - 1 {
            push_quad(
                &mut faces,
                [inner_at(k), outer_at(k), outer_at(k + 1), inner_at(k + 1)],
            );
        }
        if jambs {
            push_quad(
                &mut faces,
                [
                    inner_start + m,
                    inner_start + m + 1,
                    outer_at(0),
                    inner_at(0),
                ],
            );
            push_quad(&mut faces, [0, 1, inner_at(m - 1), outer_at(m - 1)]);
        }
        self.extrude(transform, &outline, &faces, arch.thickness);
    }

    /// A prism from an outline in the (x, z) plane, counter-clockwise, whose face
    /// triangulation uses only outline vertices; it spans y ∈ [−thickness/2, thickness/2].
    fn extrude(
        &mut self,
        transform: Mat4,
        outline: &[[f64; 2]],
        faces: &[[u32; 3]],
        thickness: f32,
    ) {
        let count = outline.len() as u32;
        let half = thickness * 0.5;
        let positions: Vec<Vec3> = [-half, half]
            .iter()
            .flat_map(|&y| {
                outline
                    .iter()
                    .map(move |&[x, z]| Vec3::new(x as f32, y, z as f32))
            })
            .collect();
        let mut triangles = Vec::with_capacity(2 * faces.len() + 2 * outline.len());
        // Counter-clockwise in (x, z) faces −Y, so the y = −half face keeps the winding.
        triangles.extend_from_slice(faces);
        triangles.extend(
            faces
                .iter()
                .map(|&[a, b, c]| [a + count, c + count, b + count]),
        );
        for i in 0..count {
            let next = (i + 1) % count;
            push_quad(&mut triangles, [next, i, i + count, next + count]);
        }
        self.append(transform, &positions, &triangles);
    }

    /// Appends a primitive's local vertices placed by `transform`; a mirroring transform
    /// reverses the winding so that fronts stay outside.
    fn append(&mut self, transform: Mat4, positions: &[Vec3], triangles: &[[u32; 3]]) {
        let base = self.positions.len() as u32;
        let mirrored = transform.determinant() < 0.0;
        self.positions.extend(
            positions
                .iter()
                .map(|&p| transform.transform_point3(p).to_array()),
        );
        self.triangles.extend(triangles.iter().map(|&[a, b, c]| {
            if mirrored {
                [a + base, c + base, b + base]
            } else {
                [a + base, b + base, c + base]
            }
        }));
    }
}

/// Two triangles of a quad whose corners run counter-clockwise seen from its front.
fn push_quad(triangles: &mut Vec<[u32; 3]>, [a, b, c, d]: [u32; 4]) {
    triangles.push([a, b, c]);
    triangles.push([a, c, d]);
}

fn polar(radius: f32, angle: f64) -> (f32, f32) {
    let r = f64::from(radius);
    ((r * angle.cos()) as f32, (r * angle.sin()) as f32)
}

#[cfg(test)]
pub(crate) mod tests {
    use std::collections::BTreeMap;

    use super::*;

    /// Whether every edge is shared by exactly two triangles that traverse it in
    /// opposite directions (closed and consistently wound), with indices in range.
    pub(crate) fn is_closed(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> bool {
        let mut directed: BTreeMap<(u32, u32), u32> = BTreeMap::new();
        for t in triangles {
            if t.iter().any(|&i| i as usize >= positions.len()) {
                return false;
            }
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *directed.entry((a, b)).or_default() += 1;
            }
        }
        directed
            .iter()
            .all(|(&(a, b), &n)| n == 1 && directed.get(&(b, a)) == Some(&1))
    }

    /// Edges used by exactly one triangle.
    fn boundary_edges(triangles: &[[u32; 3]]) -> usize {
        let mut edges: BTreeMap<(u32, u32), u32> = BTreeMap::new();
        for t in triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        edges.values().filter(|&&n| n == 1).count()
    }

    /// Signed volume by the divergence theorem: positive when fronts face outward.
    fn volume(builder: &MeshBuilder) -> f64 {
        builder
            .triangles()
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| Vec3::from(builder.positions()[i as usize]).as_dvec3());
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    fn assert_close(actual: f64, expected: f64, tolerance: f64) {
        assert!(
            (actual - expected).abs() <= tolerance * expected.abs(),
            "{actual} is not within {tolerance} of {expected}"
        );
    }

    #[test]
    fn quad_and_grid_are_open_sheets() {
        let mut quad = MeshBuilder::new();
        quad.quad([Vec3::ZERO, Vec3::X, Vec3::X + Vec3::Y, Vec3::Y]);
        assert_eq!((quad.vertex_count(), quad.triangle_count()), (4, 2));
        assert_eq!(boundary_edges(quad.triangles()), 4);

        let mut grid = MeshBuilder::new();
        grid.grid(Mat4::IDENTITY, 4.0, 2.0, 4, 3);
        assert_eq!((grid.vertex_count(), grid.triangle_count()), (20, 24));
        assert_eq!(boundary_edges(grid.triangles()), 2 * (4 + 3));
        let [a, b, c] = grid.triangles()[0].map(|i| Vec3::from(grid.positions()[i as usize]));
        assert!((b - a).cross(c - a).z > 0.0, "the grid faces +Z");
        let xs = grid.positions().iter().map(|p| p[0]);
        assert_eq!(xs.clone().fold(f32::MAX, f32::min), -2.0);
        assert_eq!(xs.fold(f32::MIN, f32::max), 2.0);
    }

    #[test]
    fn cuboid_is_closed_with_its_volume() {
        let mut cuboid = MeshBuilder::new();
        cuboid.cuboid(
            Mat4::from_translation(Vec3::new(1.0, 2.0, 3.0)),
            Vec3::new(1.0, 2.0, 3.0),
        );
        assert_eq!((cuboid.vertex_count(), cuboid.triangle_count()), (8, 12));
        assert!(is_closed(cuboid.positions(), cuboid.triangles()));
        assert_close(volume(&cuboid), 6.0, 1e-6);
    }

    #[test]
    fn cylinder_counts_closedness_and_volume() {
        let mut capped = MeshBuilder::new();
        capped.cylinder(Mat4::IDENTITY, 0.5, 2.0, 32, true);
        assert_eq!((capped.vertex_count(), capped.triangle_count()), (66, 128));
        assert!(is_closed(capped.positions(), capped.triangles()));
        let polygon_area = 0.5 * 32.0 * (TAU / 32.0).sin() * 0.25;
        assert_close(volume(&capped), polygon_area * 2.0, 1e-5);

        let mut tube = MeshBuilder::new();
        tube.cylinder(Mat4::IDENTITY, 0.5, 2.0, 2, false);
        assert_eq!((tube.vertex_count(), tube.triangle_count()), (6, 6));
        assert!(!is_closed(tube.positions(), tube.triangles()));
        assert_eq!(boundary_edges(tube.triangles()), 6);
    }

    #[test]
    fn torus_counts_closedness_and_volume() {
        let mut torus = MeshBuilder::new();
        torus.torus(Mat4::IDENTITY, 2.0, 0.5, 64, 24);
        assert_eq!(
            (torus.vertex_count(), torus.triangle_count()),
            (64 * 24, 2 * 64 * 24)
        );
        assert!(is_closed(torus.positions(), torus.triangles()));
        assert_close(volume(&torus), 2.0 * PI * PI * 2.0 * 0.25, 0.02);
    }

    #[test]
    fn arch_counts_closedness_and_volume() {
        let arch = Arch {
            width: 3.0,
            height: 3.0,
            thickness: 0.5,
            opening_radius: 1.0,
            spring_height: 1.0,
            segments: 16,
        };
        let mut with_jambs = MeshBuilder::new();
        with_jambs.arch(Mat4::IDENTITY, &arch);
        // 17 samples plus the two corner rays; the outline has 4 more vertices.
        let m = 19;
        assert_eq!(with_jambs.vertex_count(), 2 * (2 * m + 4));
        assert_eq!(with_jambs.triangle_count(), 8 * m + 12);
        assert!(is_closed(with_jambs.positions(), with_jambs.triangles()));
        // The semicircle's chords cut off a little of the opening.
        let solid = 3.0 * 3.0 - 2.0 * 1.0 - PI / 2.0;
        assert_close(volume(&with_jambs), solid * 0.5, 0.005);

        let sprung = Arch {
            spring_height: 0.0,
            ..arch
        };
        let mut springing = MeshBuilder::new();
        springing.arch(Mat4::IDENTITY, &sprung);
        assert_eq!(springing.vertex_count(), 2 * (2 * m));
        assert_eq!(springing.triangle_count(), 8 * m - 4);
        assert!(is_closed(springing.positions(), springing.triangles()));
        assert_close(volume(&springing), (9.0 - PI / 2.0) * 0.5, 0.005);
    }

    #[test]
    fn arch_outline_has_its_corners() {
        let mut arch = MeshBuilder::new();
        arch.arch(
            Mat4::IDENTITY,
            &Arch {
                width: 2.0,
                height: 2.5,
                thickness: 0.2,
                opening_radius: 0.7,
                spring_height: 0.5,
                segments: 8,
            },
        );
        for corner in [
            [-1.0, 0.1, 2.5],
            [1.0, 0.1, 2.5],
            [-1.0, -0.1, 0.0],
            [0.7, 0.1, 0.0],
        ] {
            assert!(arch.positions().contains(&corner), "{corner:?} is missing");
        }
        let top = arch
            .positions()
            .iter()
            .map(|p| p[2])
            .fold(f32::MIN, f32::max);
        assert_eq!(top, 2.5);
    }

    #[test]
    fn mirroring_keeps_fronts_outside() {
        let mirror = Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        let mut torus = MeshBuilder::new();
        torus.torus(mirror, 2.0, 0.5, 16, 8);
        assert!(is_closed(torus.positions(), torus.triangles()));
        assert!(volume(&torus) > 0.0);
        let mut cuboid = MeshBuilder::new();
        cuboid.cuboid(mirror, Vec3::ONE);
        assert_close(volume(&cuboid), 1.0, 1e-6);
    }

    #[test]
    fn primitives_append_to_one_mesh() {
        let mut builder = MeshBuilder::new();
        builder.cuboid(Mat4::IDENTITY, Vec3::ONE);
        builder.cylinder(Mat4::from_translation(Vec3::X * 3.0), 0.5, 1.0, 8, true);
        assert!(is_closed(builder.positions(), builder.triangles()));
        let mesh = builder.build("pieces", 7);
        assert_eq!(
            (mesh.positions.len(), mesh.triangles.len()),
            (8 + 18, 12 + 32)
        );
        assert_eq!(mesh.object_id, 7);
        mesh.validate("meshes[0]").unwrap();
    }
}
