//! The built-in test scenes, each a known hard case for light shafts:
//!
//! - `torus`: a tilted ring whose hole lets one shaft through its shadow (paper Fig. 3;
//!   hole filling must close the torus hole).
//! - `tree`: 20,000 leaf quads in clumps, with shafts pouring through the gaps.
//! - `plane`: a slab cut by narrow parallel slits into sheet-like shafts, the worst case
//!   for Fourier ringing.
//! - `colonnade`: two rows of pillars and arches under a roof, lit by a low sun: many
//!   sharp shafts.
//!
//! Scenes are in metres with +Z up. They are deterministic: the only randomness is a
//! fixed-seed PCG stream turned into floats by exact arithmetic.

use glam::{Mat4, Vec2, Vec3};
use rand::Rng;
use rand_pcg::Pcg64;

use crate::error::{Error, Result};
use crate::mesh_builder::{Arch, MeshBuilder};
use crate::scene::{
    Camera, Extent, Medium, Mesh, Method, PhaseModel, RenderSettings, Scene, Sun, SCENE_VERSION,
};
use crate::style::Style;

/// Names accepted by [`builtin_scene`].
pub const BUILTIN_SCENES: [&str; 4] = ["torus", "tree", "plane", "colonnade"];

const GROUND_ID: u32 = 1;

/// Sun irradiance in W/m²: with σs ≈ 0.04/m and a phase function of about 0.03–0.1/sr,
/// tens of metres of lit fog then scatter a radiance of order 0.1–1.
const SUN_STRENGTH: f32 = 8.0;

/// Builds the named built-in scene.
pub fn builtin_scene(name: &str) -> Result<Scene> {
    let scene = match name {
        "torus" => torus(),
        "tree" => tree(),
        "plane" => plane(),
        "colonnade" => colonnade(),
        _ => {
            return Err(Error::UnknownScene {
                name: name.to_owned(),
                available: BUILTIN_SCENES.join(", "),
            })
        }
    };
    scene.validate()?;
    Ok(scene)
}

/// A ring above the ground facing halfway between the sun and the camera, so that both
/// look through its hole: the shaft through the hole shows inside the ring's shadow.
fn torus() -> Scene {
    torus_tessellated(96, 32)
}

/// The `torus` scene with its ring cut into `segments_u` × `segments_v` quads (2·u·v
/// triangles): the same look at any geometric density, for rasterization benchmarks.
pub fn torus_tessellated(segments_u: u32, segments_v: u32) -> Scene {
    let centre = Vec3::new(0.0, 0.0, 5.0);
    let eye = Vec3::new(9.0, -8.0, 9.0);
    let sun = sun_at(90.0, 70.0, Vec3::ONE, SUN_STRENGTH);
    let towards_sun = -sun.direction.normalize();
    let axis = (towards_sun + (eye - centre).normalize()).normalize();
    let mut ring = MeshBuilder::new();
    ring.torus(frame(centre, axis), 2.0, 0.6, segments_u, segments_v);
    Scene {
        version: SCENE_VERSION,
        camera: Camera::pinhole_looking_at(eye, Vec3::new(0.3, -0.8, 3.6), 28.0, 1920, 1080),
        sun,
        medium: fog(0.04, 0.4),
        meshes: vec![
            ground(Vec2::new(-52.0, -12.0), Vec2::new(10.0, 52.0)),
            ring.build("torus", 2),
        ],
        render: settings(60.0),
        style: Style::default(),
    }
}

/// A trunk under a crown of leaf clumps. Twenty thousand leaves scattered uniformly
/// through the crown would make it opaque; packed into clumps near its surface they
/// leave about a fifth of it open to the sun.
fn tree() -> Scene {
    const LEAVES: usize = 20_000;
    const CLUMPS: usize = 44;
    let crown_centre = Vec3::new(0.0, 0.0, 6.0);
    let crown_radii = Vec3::new(3.5, 3.5, 2.2);
    let mut rng = Pcg64::new(0x7265_6521_7472_6565, 0x6c65_6176_6573);

    let clumps: Vec<(Vec3, f32)> = (0..CLUMPS)
        .map(|_| {
            // Foliage gathers towards the crown's surface, as on a real tree.
            let depth = uniform(&mut rng, 0.45, 0.9);
            let centre = crown_centre + crown_radii * depth * on_unit_sphere(&mut rng);
            (centre, uniform(&mut rng, 0.3, 0.55))
        })
        .collect();
    let mut leaves = MeshBuilder::new();
    for _ in 0..LEAVES {
        let clump = (unit(&mut rng) * CLUMPS as f32) as usize;
        let (clump_centre, clump_radius) = clumps[clump.min(CLUMPS - 1)];
        let centre = clump_centre + clump_radius * in_unit_ball(&mut rng);
        let normal = on_unit_sphere(&mut rng);
        let along = (on_unit_sphere(&mut rng).cross(normal)).normalize_or(Vec3::X);
        let across = normal.cross(along);
        let length = uniform(&mut rng, 0.15, 0.3);
        let half_length = along * (0.5 * length);
        let half_width = across * (0.5 * length * uniform(&mut rng, 0.5, 0.9));
        leaves.quad([
            centre - half_length - half_width,
            centre + half_length - half_width,
            centre + half_length + half_width,
            centre - half_length + half_width,
        ]);
    }

    let mut trunk = MeshBuilder::new();
    trunk.cylinder(Mat4::IDENTITY, 0.22, 5.5, 24, true);
    Scene {
        version: SCENE_VERSION,
        camera: Camera::pinhole_looking_at(
            Vec3::new(1.0, -14.0, 1.7),
            Vec3::new(0.0, 0.0, 4.6),
            35.0,
            1920,
            1080,
        ),
        sun: sun_at(50.0, 55.0, Vec3::ONE, SUN_STRENGTH),
        medium: fog(0.05, 0.45),
        meshes: vec![
            ground(Vec2::new(-40.0, -25.0), Vec2::new(40.0, 60.0)),
            trunk.build("trunk", 2),
            leaves.build("leaves", 3),
        ],
        render: settings(70.0),
        style: Style::default(),
    }
}

/// A slab cut into strips: each slit lets a thin vertical sheet of light through, seen
/// nearly edge-on by a camera underneath.
fn plane() -> Scene {
    // (centre x, width) of each slit, in metres; widths vary to vary the ringing.
    const SLITS: [(f32, f32); 5] = [
        (-3.0, 0.2),
        (-1.5, 0.3),
        (0.0, 0.5),
        (1.5, 0.4),
        (3.0, 0.25),
    ];
    const HALF_WIDTH: f32 = 10.0;
    const Y_RANGE: (f32, f32) = (-20.0, 30.0);
    const BOTTOM: f32 = 5.0;
    const THICKNESS: f32 = 0.1;
    let mut edges = vec![-HALF_WIDTH];
    for (centre, width) in SLITS {
        edges.push(centre - 0.5 * width);
        edges.push(centre + 0.5 * width);
    }
    edges.push(HALF_WIDTH);
    let mut slab = MeshBuilder::new();
    for strip in edges.chunks_exact(2) {
        let (x0, x1) = (strip[0], strip[1]);
        let centre = Vec3::new(
            0.5 * (x0 + x1),
            0.5 * (Y_RANGE.0 + Y_RANGE.1),
            BOTTOM + 0.5 * THICKNESS,
        );
        let size = Vec3::new(x1 - x0, Y_RANGE.1 - Y_RANGE.0, THICKNESS);
        slab.cuboid(Mat4::from_translation(centre), size);
    }
    Scene {
        version: SCENE_VERSION,
        camera: Camera::pinhole_looking_at(
            Vec3::new(0.35, -14.0, 1.6),
            Vec3::new(0.0, 0.0, 4.0),
            50.0,
            1920,
            1080,
        ),
        sun: sun_at(100.0, 82.0, Vec3::ONE, SUN_STRENGTH),
        medium: fog(0.04, 0.35),
        meshes: vec![
            ground(Vec2::new(-30.0, -25.0), Vec2::new(30.0, 60.0)),
            slab.build("slotted plane", 2),
        ],
        render: settings(70.0),
        style: Style::default(),
    }
}

/// Two rows of pillars along +Y carrying arches and a roof; a low sun from the side
/// slants through every bay.
///
/// The sun stands 28° off the colonnade's axis, so that seen from it the pillars of a row
/// nearly close ranks: the gaps between them, and so the shafts, are about 0.3 m wide,
/// and most of the interior stays dark.
fn colonnade() -> Scene {
    const PER_ROW: u32 = 10;
    const SPACING: f32 = 2.5;
    const ROW_X: f32 = 3.0;
    const PILLAR_RADIUS: f32 = 0.45;
    const PILLAR_HEIGHT: f32 = 4.0;
    const ARCH_HEIGHT: f32 = 1.2;
    const ROOF_THICKNESS: f32 = 0.4;
    let length = SPACING * (PER_ROW - 1) as f32;

    let mut pillars = MeshBuilder::new();
    let mut arches = MeshBuilder::new();
    let arch = Arch {
        width: SPACING,
        height: ARCH_HEIGHT,
        thickness: 2.0 * PILLAR_RADIUS,
        opening_radius: 0.5 * SPACING - PILLAR_RADIUS,
        spring_height: 0.0,
        segments: 24,
    };
    // The arch's width runs along X; turn it to run along the rows.
    let along_row = Mat4::from_cols(
        Vec3::Y.extend(0.0),
        (-Vec3::X).extend(0.0),
        Vec3::Z.extend(0.0),
        Vec3::ZERO.extend(1.0),
    );
    for x in [-ROW_X, ROW_X] {
        for i in 0..PER_ROW {
            let y = SPACING * i as f32;
            pillars.cylinder(
                Mat4::from_translation(Vec3::new(x, y, 0.0)),
                PILLAR_RADIUS,
                PILLAR_HEIGHT,
                24,
                true,
            );
            if i + 1 < PER_ROW {
                let placed = Mat4::from_translation(Vec3::new(x, y + 0.5 * SPACING, PILLAR_HEIGHT));
                arches.arch(placed * along_row, &arch);
            }
        }
    }
    let mut roof = MeshBuilder::new();
    let overhang = PILLAR_RADIUS + 0.1;
    roof.cuboid(
        Mat4::from_translation(Vec3::new(
            0.0,
            0.5 * length,
            PILLAR_HEIGHT + ARCH_HEIGHT + 0.5 * ROOF_THICKNESS,
        )),
        Vec3::new(
            2.0 * (ROW_X + overhang),
            length + 2.0 * overhang,
            ROOF_THICKNESS,
        ),
    );

    Scene {
        version: SCENE_VERSION,
        camera: Camera::pinhole_looking_at(
            Vec3::new(-0.5, -5.0, 1.7),
            Vec3::new(0.6, 10.0, 2.7),
            35.0,
            1920,
            1080,
        ),
        sun: sun_at(62.0, 15.0, Vec3::new(1.0, 0.85, 0.65), SUN_STRENGTH),
        medium: fog(0.04, 0.4),
        meshes: vec![
            ground(Vec2::new(-30.0, -15.0), Vec2::new(35.0, 60.0)),
            pillars.build("pillars", 2),
            arches.build("arches", 3),
            roof.build("roof", 4),
        ],
        render: settings(60.0),
        style: Style::default(),
    }
}

/// A sun standing at `azimuth` degrees (counter-clockwise from +X) and `elevation`
/// degrees above the horizon; its light travels the opposite way.
fn sun_at(azimuth: f64, elevation: f64, color: Vec3, strength: f32) -> Sun {
    let (azimuth, elevation) = (azimuth.to_radians(), elevation.to_radians());
    let towards_sun = Vec3::new(
        (elevation.cos() * azimuth.cos()) as f32,
        (elevation.cos() * azimuth.sin()) as f32,
        elevation.sin() as f32,
    );
    Sun {
        direction: -towards_sun,
        color,
        strength,
        angular_diameter: 0.526_f32.to_radians(),
        attenuated_by_medium: true,
    }
}

/// Unbounded white fog scattering forward.
fn fog(extinction: f32, anisotropy: f32) -> Medium {
    Medium {
        extinction,
        channel_extinction: None,
        albedo: Vec3::ONE,
        anisotropy,
        phase: PhaseModel::HenyeyGreenstein,
        extent: Extent::Unbounded,
    }
}

fn settings(max_distance: f32) -> RenderSettings {
    RenderSettings {
        shadow_map_size: 1024,
        method: Method::Prefiltered,
        max_distance,
        ..RenderSettings::default()
    }
}

/// The ground at z = 0 over the rectangle from `min` to `max`: just large enough to
/// catch the view rays within the render distance, to keep a fitted shadow map sharp.
fn ground(min: Vec2, max: Vec2) -> Mesh {
    let centre = 0.5 * (min + max);
    let size = max - min;
    let mut ground = MeshBuilder::new();
    ground.grid(
        Mat4::from_translation(centre.extend(0.0)),
        size.x,
        size.y,
        8,
        8,
    );
    ground.build("ground", GROUND_ID)
}

/// Object-to-world placing the origin at `origin` with local +Z along the unit `axis`.
fn frame(origin: Vec3, axis: Vec3) -> Mat4 {
    let helper = if axis.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let x = helper.cross(axis).normalize();
    let y = axis.cross(x);
    Mat4::from_cols(
        x.extend(0.0),
        y.extend(0.0),
        axis.extend(0.0),
        origin.extend(1.0),
    )
}

/// A float in [0, 1) from the top 24 bits of one output: exact on every platform.
fn unit(rng: &mut Pcg64) -> f32 {
    (rng.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

fn uniform(rng: &mut Pcg64, low: f32, high: f32) -> f32 {
    low + (high - low) * unit(rng)
}

/// Uniform in the unit ball, by rejection: only exact arithmetic.
fn in_unit_ball(rng: &mut Pcg64) -> Vec3 {
    loop {
        let p = Vec3::new(
            uniform(rng, -1.0, 1.0),
            uniform(rng, -1.0, 1.0),
            uniform(rng, -1.0, 1.0),
        );
        if p.length_squared() <= 1.0 {
            return p;
        }
    }
}

/// Uniform on the unit sphere: a ball sample pushed out (sqrt is correctly rounded).
fn on_unit_sphere(rng: &mut Pcg64) -> Vec3 {
    loop {
        let p = in_unit_ball(rng);
        let length = p.length();
        if length > 1e-3 {
            return p / length;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh_builder::tests::is_closed;
    use crate::scene::Projection;

    fn all() -> Vec<Scene> {
        BUILTIN_SCENES
            .iter()
            .map(|name| builtin_scene(name).unwrap())
            .collect()
    }

    #[test]
    fn every_builtin_scene_validates() {
        for (name, scene) in BUILTIN_SCENES.iter().zip(all()) {
            scene
                .validate()
                .unwrap_or_else(|err| panic!("{name}: {err}"));
            let ids: Vec<u32> = scene.meshes.iter().map(|m| m.object_id).collect();
            assert_eq!(ids[0], GROUND_ID, "{name}: the ground comes first");
            let mut unique = ids.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), ids.len(), "{name}: object ids {ids:?} repeat");
        }
    }

    #[test]
    fn a_denser_torus_casts_the_same_shadow() {
        let coarse = builtin_scene("torus").unwrap();
        let dense = torus_tessellated(384, 128);
        assert_eq!(dense.meshes[1].triangles.len(), 2 * 384 * 128);
        assert_eq!(dense.camera, coarse.camera);
        assert_eq!(dense.sun, coarse.sun);
        let ring_texels = |scene: &Scene| {
            let camera = crate::camera::CameraModel::new(&scene.camera);
            let geometry = crate::render::FlatGeometry::from_scene(scene);
            let map =
                crate::shadow_map::ShadowMap::of_scene_geometry(scene, &camera, &geometry).unwrap();
            map.ids.iter().map(|&id| id == 2).collect::<Vec<bool>>()
        };
        let (coarse, dense) = (ring_texels(&coarse), ring_texels(&dense));
        let ring = coarse.iter().filter(|&&hit| hit).count();
        let differ = coarse.iter().zip(&dense).filter(|(a, b)| a != b).count();
        assert!(ring > 1_000, "the ring covers {ring} texels");
        // Only the coarse ring's chords differ: a few texels along its outline.
        assert!(differ * 50 < ring, "{differ} of {ring} ring texels differ");
    }

    #[test]
    fn unknown_name_is_named_with_the_alternatives() {
        let err = builtin_scene("teapot").unwrap_err();
        match &err {
            Error::UnknownScene { name, available } => {
                assert_eq!(name, "teapot");
                for known in BUILTIN_SCENES {
                    assert!(available.contains(known), "{available}");
                }
            }
            other => panic!("unexpected error {other}"),
        }
        assert!(err.to_string().contains("teapot"));
    }

    #[test]
    fn scenes_are_deterministic_and_round_trip_through_json() {
        for name in BUILTIN_SCENES {
            let scene = builtin_scene(name).unwrap();
            let json = scene.to_json();
            assert_eq!(json, builtin_scene(name).unwrap().to_json(), "{name}");
            assert_eq!(Scene::from_json(&json).unwrap(), scene, "{name}");
        }
    }

    #[test]
    fn tree_has_its_leaves_in_one_mesh() {
        let scene = builtin_scene("tree").unwrap();
        let leaves: Vec<&Mesh> = scene.meshes.iter().filter(|m| m.object_id == 3).collect();
        assert_eq!(leaves.len(), 1);
        let count = leaves[0].triangles.len();
        assert!((35_000..=45_000).contains(&count), "{count} leaf triangles");
    }

    #[test]
    fn solid_occluders_are_closed() {
        for scene in all() {
            for mesh in scene
                .meshes
                .iter()
                .filter(|m| !matches!(m.name.as_str(), "ground" | "leaves"))
            {
                assert!(
                    is_closed(&mesh.positions, &mesh.triangles),
                    "{} is open",
                    mesh.name
                );
            }
        }
    }

    #[test]
    fn cameras_stand_clear_of_the_geometry_and_frame_it() {
        for (name, scene) in BUILTIN_SCENES.iter().zip(all()) {
            let world_from_camera = scene.camera.world_from_camera;
            let eye = world_from_camera.w_axis.truncate();
            assert!(eye.z > 1.0, "{name}: the camera stands above the ground");
            let Projection::Perspective {
                focal_length,
                sensor_width,
                ..
            } = scene.camera.projection
            else {
                panic!("{name}: not a perspective camera");
            };
            let aspect = scene.camera.width as f32 / scene.camera.height as f32;
            let camera_from_world = world_from_camera.inverse();
            for mesh in scene.meshes.iter().filter(|m| m.object_id != GROUND_ID) {
                let (low, high) = mesh.positions.iter().fold(
                    (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
                    |(low, high), &p| {
                        let p = mesh.world_from_object.transform_point3(Vec3::from(p));
                        (low.min(p), high.max(p))
                    },
                );
                let inside = eye.cmpge(low).all() && eye.cmple(high).all();
                assert!(!inside, "{name}: the camera is inside {}", mesh.name);
                // Blender's auto sensor fit: the sensor width spans the wider side.
                let centre = camera_from_world.transform_point3(0.5 * (low + high));
                assert!(centre.z < 0.0, "{name}: {} is behind the camera", mesh.name);
                let scale = focal_length / (0.5 * sensor_width) / -centre.z;
                let (x, y) = (centre.x * scale, centre.y * scale * aspect);
                assert!(
                    x.abs() < 1.0 && y.abs() < 1.0,
                    "{name}: {} is centred off frame at ({x}, {y})",
                    mesh.name
                );
            }
        }
    }
}
