//! Silhouette enhancement by 1D epipolar dilation and closure (Eq. 3): the line sweep
//! against the texel-by-texel definition for epipoles inside, outside on every side and
//! at infinity; the shape and depths of an extruded occluder; order properties; bad input.

use crepuscular::builtin_scene;
use crepuscular::camera::CameraModel;
use crepuscular::scene::Projection;
use crepuscular::shadow_map::ShadowMap;
use crepuscular::silhouette::{apply, apply_naive, Epipole, SilhouetteDesc};
use crepuscular::Error;
use glam::DVec3;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

fn random_map(size: usize, seed: u64, empty: f64) -> Vec<f32> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..size * size)
        .map(|_| {
            if rng.random_bool(empty) {
                f32::INFINITY
            } else {
                rng.random_range(0.0f32..100.0)
            }
        })
        .collect()
}

/// Pinhole epipoles at camera depths above, amid and below the occluders (0..100).
fn points() -> Vec<Epipole> {
    let positions = [
        (20.3, 17.8),   // inside
        (20.5, 20.5),   // on a texel centre
        (20.0, 21.0),   // on a texel corner
        (0.2, 40.9),    // inside, at the border
        (-15.2, 10.7),  // left
        (60.3, 22.1),   // right
        (15.2, -30.4),  // above
        (33.3, 70.1),   // below
        (-20.0, -20.0), // off a corner, on the diagonal
        (55.0, -3.0),   // off a corner
        (-1e4, 3e3),    // far away
    ];
    positions
        .into_iter()
        .flat_map(|(x, y)| [-50.0, 50.0, 150.0].map(|z| Epipole::Point(DVec3::new(x, y, z))))
        .collect()
}

/// Orthographic view directions: along the axes, diagonals, and in between, with view
/// rays climbing, level, and falling in light depth.
fn directions() -> Vec<Epipole> {
    [
        (1.0, 0.0, 0.3),
        (-1.0, 0.0, -0.2),
        (0.0, 1.0, 0.5),
        (0.0, -1.0, 0.0),
        (1.0, 1.0, 0.1),
        (-1.0, 1.0, -3.0),
        (0.3, -0.8, 2.0),
        (-0.9, 0.4, -1.0),
        (0.55, 0.2, 0.0),
    ]
    .into_iter()
    .map(|(x, y, z)| Epipole::Direction(DVec3::new(x, y, z)))
    .collect()
}

fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[test]
fn line_sweep_equals_the_texel_by_texel_definition() {
    let size = 41;
    let map = random_map(size, 7, 0.35);
    let lengths = [0.0, 0.9, 1.0, 2.5, 7.0, 12.3, 100.0, 1e30];
    for (e, epipole) in points().into_iter().chain(directions()).enumerate() {
        for (l, length) in lengths.into_iter().enumerate() {
            // The closure's naive form is O(length²) per texel: spread the cases.
            let descs = if (e + l) % 2 == 0 || length < 20.0 {
                vec![
                    SilhouetteDesc::dilate(length),
                    SilhouetteDesc::close(length),
                ]
            } else {
                vec![SilhouetteDesc::dilate(length)]
            };
            for desc in descs {
                let fast = apply(&map, size as u32, epipole, &desc).expect("valid");
                let naive = apply_naive(&map, size as u32, epipole, &desc).expect("valid");
                let differing = fast
                    .iter()
                    .zip(&naive)
                    .filter(|(a, b)| a.to_bits() != b.to_bits())
                    .count();
                assert_eq!(differing, 0, "{epipole:?} {desc:?}");
            }
        }
    }
}

#[test]
fn line_sweep_equals_the_definition_on_a_larger_map() {
    let size = 150;
    let map = random_map(size, 8, 0.5);
    for epipole in [
        Epipole::Point(DVec3::new(70.4, 90.2, 40.0)),
        Epipole::Point(DVec3::new(-300.0, 20.0, 20.0)),
        Epipole::Direction(DVec3::new(0.7, -0.3, 0.4)),
    ] {
        for desc in [SilhouetteDesc::dilate(30.0), SilhouetteDesc::close(9.0)] {
            let fast = apply(&map, size as u32, epipole, &desc).unwrap();
            let naive = apply_naive(&map, size as u32, epipole, &desc).unwrap();
            assert!(same_bits(&fast, &naive), "{epipole:?} {desc:?}");
        }
    }
}

/// Texels that the dilation of a single occluder at `source` changed.
fn extrusion(
    size: usize,
    source: (usize, usize),
    epipole: Epipole,
    length: f32,
) -> Vec<(i64, i64, f32)> {
    let mut map = vec![f32::INFINITY; size * size];
    map[source.1 * size + source.0] = 5.0;
    let out = apply(&map, size as u32, epipole, &SilhouetteDesc::dilate(length)).unwrap();
    let naive = apply_naive(&map, size as u32, epipole, &SilhouetteDesc::dilate(length)).unwrap();
    assert!(same_bits(&out, &naive));
    out.iter()
        .enumerate()
        .filter(|&(_, &v)| v != f32::INFINITY)
        .map(|(i, &v)| (i as i64 % size as i64, i as i64 / size as i64, v))
        .collect()
}

#[test]
fn a_single_occluder_extrudes_into_a_segment_away_from_the_epipole() {
    let size = 40;
    // Parallel lines along +x, level view rays: a flat segment of 6 texels after it.
    let texels = extrusion(
        size,
        (10, 20),
        Epipole::Direction(DVec3::new(2.0, 0.0, 0.0)),
        6.0,
    );
    let expected: Vec<_> = (10..=16).map(|x| (x, 20, 5.0)).collect();
    assert_eq!(texels, expected);

    // Along −y with rays gaining 0.5 depth per texel: Eq. 3's orthographic form.
    let texels = extrusion(
        size,
        (10, 20),
        Epipole::Direction(DVec3::new(0.0, -1.0, 0.5)),
        4.5,
    );
    let expected: Vec<_> = (0..=4)
        .rev()
        .map(|j| (10, 20 - j, 5.0 + 0.5 * j as f32))
        .collect();
    assert_eq!(texels, expected);

    // Diagonal: one column step is √2 long, so 6 texels of length is 4 steps.
    let texels = extrusion(
        size,
        (10, 20),
        Epipole::Direction(DVec3::new(1.0, 1.0, 0.0)),
        6.0,
    );
    let expected: Vec<_> = (0..=4).map(|j| (10 + j, 20 + j, 5.0)).collect();
    assert_eq!(texels, expected);

    // Pinhole camera far to the left on the occluder's row, at light depth 1: the view
    // ray from the camera through the occluder descends, and Eq. 3 gives its depth.
    let (lx, zl) = (-89.5, 1.0);
    let epipole = Epipole::Point(DVec3::new(lx, 20.5, zl));
    let texels = extrusion(size, (10, 20), epipole, 3.0);
    assert_eq!(texels.len(), 4);
    for (j, &(x, y, z)) in texels.iter().enumerate() {
        assert_eq!((x, y), (10 + j as i64, 20));
        let ratio = (x as f64 + 0.5 - lx) / (10.5 - lx);
        let eq3 = zl + ratio * (5.0 - zl);
        assert!((z as f64 - eq3).abs() < 1e-5, "{j}: {z} vs {eq3}");
    }
}

#[test]
fn extrusion_points_away_from_an_epipole_inside_the_map() {
    let size = 41;
    let l = (20.5, 20.5);
    let length = 8.0;
    for source in [
        (30, 22),
        (10, 18),
        (19, 10),
        (22, 31),
        (30, 30),
        (10, 30),
        (27, 12),
    ] {
        let epipole = Epipole::Point(DVec3::new(l.0, l.1, -10.0));
        let texels = extrusion(size, source, epipole, length);
        let s = (source.0 as f64 + 0.5, source.1 as f64 + 0.5);
        let away = ((s.0 - l.0), (s.1 - l.1));
        let norm = (away.0 * away.0 + away.1 * away.1).sqrt();
        // No gaps: every column from the occluder on, as far as the kernel reaches
        // even along a diagonal, holds part of the extrusion.
        let (major, sign) = if away.0.abs() >= away.1.abs() {
            (0, away.0.signum() as i64)
        } else {
            (1, away.1.signum() as i64)
        };
        let start = [source.0 as i64, source.1 as i64][major];
        for k in 0..=(length as f64 / 2f64.sqrt()) as i64 {
            let column = start + sign * k;
            assert!(
                texels.iter().any(|&(x, y, _)| [x, y][major] == column),
                "{source:?}: gap at column {column}: {texels:?}"
            );
        }
        for &(x, y, z) in &texels {
            let t = (x as f64 + 0.5 - s.0, y as f64 + 0.5 - s.1);
            let along = (t.0 * away.0 + t.1 * away.1) / norm;
            let across = (t.0 * away.1 - t.1 * away.0).abs() / norm;
            assert!(
                (0.0..=length as f64 + 1e-9).contains(&along),
                "{source:?} {x},{y}"
            );
            // Each sample is the texel containing the ray point (half a texel off at s,
            // widening as the rays fan out), and t is half a texel off its own ray.
            let spread = (norm + along) / norm;
            assert!(
                across <= 0.5 + 0.5 * spread,
                "{source:?} {x},{y}: {across} off the line"
            );
            // The camera is nearer the sun than the occluder: rays go on descending.
            assert!(z >= 5.0);
        }
    }
}

#[test]
fn dilation_and_closure_are_ordered() {
    let size = 48;
    let map = random_map(size, 3, 0.4);
    for epipole in points().into_iter().step_by(2).chain(directions()) {
        let dilated = apply(&map, size as u32, epipole, &SilhouetteDesc::dilate(9.0)).unwrap();
        let closed = apply(&map, size as u32, epipole, &SilhouetteDesc::close(9.0)).unwrap();
        for i in 0..map.len() {
            assert!(dilated[i] <= map[i], "{epipole:?} {i}");
            assert!(
                dilated[i] <= closed[i] && closed[i] <= map[i],
                "{epipole:?} {i}"
            );
        }
    }
}

#[test]
fn closure_fills_gaps_along_the_line_and_restores_the_rest() {
    let size = 30;
    let mut map = vec![f32::INFINITY; size * size];
    map[15 * size + 10] = 5.0;
    map[15 * size + 12] = 5.0;
    let epipole = Epipole::Direction(DVec3::new(1.0, 0.0, 0.0));
    let closed = apply(&map, size as u32, epipole, &SilhouetteDesc::close(3.0)).unwrap();
    let mut expected = map.clone();
    expected[15 * size + 11] = 5.0;
    assert_eq!(closed, expected);
}

#[test]
fn degenerate_inputs_leave_the_map_unchanged() {
    let size = 20;
    let map = random_map(size, 4, 0.3);
    let along_light = Epipole::Direction(DVec3::new(0.0, 0.0, 1.0));
    assert_eq!(
        apply(&map, 20, along_light, &SilhouetteDesc::close(5.0)).unwrap(),
        map
    );
    let inside = Epipole::Point(DVec3::new(7.5, 7.5, 0.0));
    assert_eq!(
        apply(&map, 20, inside, &SilhouetteDesc::dilate(0.0)).unwrap(),
        map
    );
    assert_eq!(
        apply(&[], 0, inside, &SilhouetteDesc::dilate(4.0)).unwrap(),
        Vec::<f32>::new()
    );
    let single = [3.0];
    assert_eq!(
        apply(&single, 1, inside, &SilhouetteDesc::close(4.0)).unwrap(),
        single
    );
}

#[test]
fn output_does_not_depend_on_the_thread_count() {
    let size = 160;
    let map = random_map(size, 5, 0.3);
    let run = |threads: usize, epipole: Epipole| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| apply(&map, size as u32, epipole, &SilhouetteDesc::close(20.0)).unwrap())
    };
    for epipole in [
        Epipole::Point(DVec3::new(80.2, 60.7, 30.0)),
        Epipole::Direction(DVec3::new(-0.4, 0.9, 0.2)),
    ] {
        assert!(same_bits(&run(1, epipole), &run(3, epipole)));
    }
}

fn field_of(error: Error) -> String {
    match error {
        Error::InvalidInput { field, .. } => field,
        other => panic!("expected an invalid-input error, got {other}"),
    }
}

#[test]
fn bad_parameters_name_their_field() {
    let map = vec![1.0; 16];
    let epipole = Epipole::Point(DVec3::new(1.0, 2.0, 3.0));
    for length in [-1.0, f32::NAN, f32::INFINITY] {
        let error = apply(&map, 4, epipole, &SilhouetteDesc::dilate(length)).unwrap_err();
        assert_eq!(field_of(error), "style.silhouette.length");
    }
    for bad in [
        Epipole::Point(DVec3::new(f64::NAN, 0.0, 0.0)),
        Epipole::Direction(DVec3::new(1.0, f64::INFINITY, 0.0)),
        Epipole::Point(DVec3::new(1.0, 2.0, 1e300)),
        Epipole::Point(DVec3::new(-1e40, 2.0, 3.0)),
    ] {
        let error = apply(&map, 4, bad, &SilhouetteDesc::close(3.0)).unwrap_err();
        assert_eq!(field_of(error), "style.silhouette.epipole");
    }
    let error = apply(&map, 3, epipole, &SilhouetteDesc::close(3.0)).unwrap_err();
    assert_eq!(field_of(error), "shadow_map.depth");
    let mut with_nan = map.clone();
    with_nan[3] = f32::NAN;
    let error = apply(&with_nan, 4, epipole, &SilhouetteDesc::close(3.0)).unwrap_err();
    assert_eq!(field_of(error), "shadow_map.depth");
}

#[test]
fn extrusions_have_no_gaps_for_any_occluder_position() {
    let size = 33;
    let length = 6.0f32;
    for l in [
        (16.5, 16.5),
        (16.0, 17.0),
        (12.37, 20.81),
        (-7.3, 12.2),
        (40.2, 45.9),
    ] {
        let epipole = Epipole::Point(DVec3::new(l.0, l.1, 200.0));
        for sy in (1..size).step_by(3) {
            for sx in (2..size).step_by(3) {
                let texels = extrusion(size, (sx, sy), epipole, length);
                let away = (sx as f64 + 0.5 - l.0, sy as f64 + 0.5 - l.1);
                let (major, sign) = if away.0.abs() >= away.1.abs() {
                    (0, away.0.signum() as i64)
                } else {
                    (1, away.1.signum() as i64)
                };
                let start = [sx as i64, sy as i64][major];
                for k in 0..=(length as f64 / 2f64.sqrt()) as i64 {
                    let column = start + sign * k;
                    if !(0..size as i64).contains(&column) {
                        break;
                    }
                    // Where the line leaves the map sideways the extrusion may end early.
                    let minor = [sy as f64, sx as f64][major] + 0.5;
                    let drift =
                        k as f64 * [away.1, away.0][major].abs() / [away.0, away.1][major].abs();
                    if minor - drift < 1.0 || minor + drift > size as f64 - 1.0 {
                        break;
                    }
                    assert!(
                        texels.iter().any(|&(x, y, _)| [x, y][major] == column),
                        "epipole {l:?} source ({sx}, {sy}): gap at column {column}: {texels:?}"
                    );
                }
            }
        }
    }
}

#[test]
fn a_camera_projects_to_its_position_or_its_view_direction() {
    let mut scene = builtin_scene("torus").unwrap();
    scene.render.shadow_map_size = 64;
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
    let map = shadow.texel_from_world;
    match Epipole::of_camera(&camera, &map) {
        Epipole::Point(p) => {
            assert!((p - map.transform_point3(camera.position())).length() < 1e-9)
        }
        other => panic!("a pinhole camera gave {other:?}"),
    }

    scene.camera.projection = Projection::orthographic(10.0);
    let camera = CameraModel::new(&scene.camera);
    let Epipole::Direction(direction) = Epipole::of_camera(&camera, &map) else {
        panic!("an orthographic camera has its epipole at infinity");
    };
    // Any view ray runs along it, away from the camera.
    let ray = camera.ray(3.0, 4.0);
    let along = map.transform_point3(ray.at(5.0)) - map.transform_point3(ray.at(1.0));
    assert!((along.normalize() - direction.normalize()).length() < 1e-9);
}
