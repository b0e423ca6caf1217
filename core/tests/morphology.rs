//! Hole filling by 2D morphology: the fast disk and box filters against brute force, the
//! kernels' shapes, the algebra of closing and opening, and bad input.

use crepuscular::morphology::{apply, apply_naive, in_disk, KernelShape, MorphologyDesc};
use crepuscular::Error;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

/// A map of random depths with a share of empty (+∞) texels. With `levels`, depths take
/// few distinct values so that ties are common.
fn random_map(size: usize, seed: u64, empty: f64, levels: Option<u32>) -> Vec<f32> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..size * size)
        .map(|_| {
            if rng.random_bool(empty) {
                f32::INFINITY
            } else if let Some(levels) = levels {
                rng.random_range(0..levels) as f32
            } else {
                rng.random_range(-10.0f32..100.0)
            }
        })
        .collect()
}

fn all_descs(radius: f32) -> Vec<MorphologyDesc> {
    [KernelShape::Disk, KernelShape::Box]
        .into_iter()
        .flat_map(|shape| {
            [
                MorphologyDesc::dilate(shape, radius),
                MorphologyDesc::erode(shape, radius),
                MorphologyDesc::close(shape, radius),
                MorphologyDesc::open(shape, radius),
            ]
        })
        .collect()
}

#[test]
fn fast_filters_equal_brute_force_exactly() {
    let radii = [
        0.0, 0.5, 1.0, 1.4, 1.5, 2.0, 2.9, 3.0, 4.25, 7.0, 13.6, 60.0, 1e9,
    ];
    for (seed, size) in [(1, 1), (2, 2), (3, 7), (4, 33), (5, 48)] {
        for levels in [None, Some(4)] {
            let map = random_map(size, seed, 0.3, levels);
            for radius in radii {
                for desc in all_descs(radius) {
                    let fast = apply(&map, size as u32, &desc).expect("valid");
                    let naive = apply_naive(&map, size as u32, &desc).expect("valid");
                    assert!(
                        fast.iter()
                            .zip(&naive)
                            .all(|(a, b)| a.to_bits() == b.to_bits()),
                        "{desc:?} on {size}² differs from brute force"
                    );
                }
            }
        }
    }
}

#[test]
fn radius_zero_is_the_identity() {
    let map = random_map(20, 9, 0.2, None);
    for desc in all_descs(0.0).into_iter().chain(all_descs(0.99)) {
        assert_eq!(apply(&map, 20, &desc).expect("valid"), map, "{desc:?}");
    }
}

/// One occluder dilates into exactly the kernel's footprint, at its own depth.
fn footprint(shape: KernelShape, radius: f32) -> Vec<(i64, i64)> {
    let size = 31;
    let centre = 15;
    let mut map = vec![f32::INFINITY; size * size];
    map[centre * size + centre] = 2.5;
    let out = apply(&map, size as u32, &MorphologyDesc::dilate(shape, radius)).expect("valid");
    let mut texels = Vec::new();
    for (i, &v) in out.iter().enumerate() {
        if v != f32::INFINITY {
            assert_eq!(v, 2.5);
            texels.push(((i % size) as i64 - 15, (i / size) as i64 - 15));
        }
    }
    texels
}

#[test]
fn a_single_occluder_dilates_into_the_disk() {
    // Lattice points with dx² + dy² ≤ r²: 5, 9, 13, 21, 29 for r² = 1, 2.25, 4, 6.25, 9.
    for (radius, count) in [(1.0, 5), (1.5, 9), (2.0, 13), (2.5, 21), (3.0, 29)] {
        let texels = footprint(KernelShape::Disk, radius);
        assert_eq!(texels.len(), count, "radius {radius}");
        assert!(texels.iter().all(|&(dx, dy)| in_disk(dx, dy, radius)));
    }
    let texels = footprint(KernelShape::Disk, 7.3);
    let expected = (-7..=7)
        .flat_map(|dy| (-7..=7).map(move |dx| (dx, dy)))
        .filter(|&(dx, dy)| ((dx * dx + dy * dy) as f64) <= 7.3f32 as f64 * 7.3f32 as f64)
        .count();
    assert_eq!(texels.len(), expected);
}

#[test]
fn a_single_occluder_dilates_into_the_box() {
    let texels = footprint(KernelShape::Box, 2.7);
    assert_eq!(texels.len(), 25);
    assert!(texels
        .iter()
        .all(|&(dx, dy)| dx.abs() <= 2 && dy.abs() <= 2));
}

#[test]
fn closing_and_opening_are_idempotent_and_bracket_the_map() {
    let size = 64;
    for (seed, radius) in [(11, 1.5), (12, 3.0), (13, 5.7)] {
        let map = random_map(size, seed, 0.4, None);
        for shape in [KernelShape::Disk, KernelShape::Box] {
            let run = |desc: MorphologyDesc, map: &[f32]| apply(map, size as u32, &desc).unwrap();
            let closed = run(MorphologyDesc::close(shape, radius), &map);
            let opened = run(MorphologyDesc::open(shape, radius), &map);
            let dilated = run(MorphologyDesc::dilate(shape, radius), &map);
            let eroded = run(MorphologyDesc::erode(shape, radius), &map);
            assert_eq!(run(MorphologyDesc::close(shape, radius), &closed), closed);
            assert_eq!(run(MorphologyDesc::open(shape, radius), &opened), opened);
            // Depth order is the reverse of occlusion: in occlusion terms this is
            // opening ≤ original ≤ closing.
            for i in 0..map.len() {
                assert!(
                    dilated[i] <= closed[i] && closed[i] <= map[i],
                    "{shape:?} {i}"
                );
                assert!(
                    map[i] <= opened[i] && opened[i] <= eroded[i],
                    "{shape:?} {i}"
                );
            }
        }
    }
}

#[test]
fn closing_fills_a_hole_smaller_than_the_kernel() {
    // An occluding ring (depth 4) of outer radius 12 around a hole of radius 3.
    let size = 40;
    let mut map = vec![f32::INFINITY; size * size];
    for y in 0..size {
        for x in 0..size {
            let (dx, dy) = (x as f64 - 20.0, y as f64 - 20.0);
            let r = (dx * dx + dy * dy).sqrt();
            if (3.0..=12.0).contains(&r) {
                map[y * size + x] = 4.0;
            }
        }
    }
    let closed = apply(
        &map,
        size as u32,
        &MorphologyDesc::close(KernelShape::Disk, 4.0),
    )
    .unwrap();
    assert_eq!(closed[20 * size + 20], 4.0, "the hole is filled");
    assert_eq!(closed[20 * size + 35], f32::INFINITY, "outside stays open");
    let small = apply(
        &map,
        size as u32,
        &MorphologyDesc::close(KernelShape::Disk, 2.0),
    )
    .unwrap();
    assert_eq!(
        small[20 * size + 20],
        f32::INFINITY,
        "a smaller kernel keeps it"
    );
}

#[test]
fn output_does_not_depend_on_the_thread_count() {
    let size = 200;
    let map = random_map(size, 21, 0.3, None);
    let run = |threads: usize, desc: MorphologyDesc| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| apply(&map, size as u32, &desc).unwrap())
    };
    for desc in [
        MorphologyDesc::close(KernelShape::Disk, 9.5),
        MorphologyDesc::open(KernelShape::Box, 6.0),
    ] {
        assert_eq!(run(1, desc), run(3, desc), "{desc:?}");
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
    for radius in [-1.0, f32::NAN, f32::INFINITY] {
        let error = apply(&map, 4, &MorphologyDesc::close(KernelShape::Disk, radius)).unwrap_err();
        assert_eq!(field_of(error), "style.closing.radius");
    }
    let error = apply(&map, 4, &MorphologyDesc::open(KernelShape::Box, -2.0)).unwrap_err();
    assert_eq!(field_of(error), "style.opening.radius");
    let error = apply(&map, 5, &MorphologyDesc::close(KernelShape::Disk, 1.0)).unwrap_err();
    assert_eq!(field_of(error), "shadow_map.depth");
    let error = apply(
        &map[..15],
        4,
        &MorphologyDesc::close(KernelShape::Disk, 1.0),
    )
    .unwrap_err();
    assert_eq!(field_of(error), "shadow_map.depth");
    for bad in [f32::NAN, f32::NEG_INFINITY] {
        let mut map = map.clone();
        map[6] = bad;
        let error = apply(&map, 4, &MorphologyDesc::close(KernelShape::Disk, 1.0)).unwrap_err();
        assert_eq!(field_of(error), "shadow_map.depth");
    }
    assert_eq!(
        apply(&[], 0, &MorphologyDesc::close(KernelShape::Disk, 3.0)).unwrap(),
        Vec::<f32>::new()
    );
}

#[test]
fn kernel_shapes_read_from_presets() {
    let shape: KernelShape = serde_json::from_str("\"box\"").unwrap();
    assert_eq!(shape, KernelShape::Box);
    let shape: KernelShape = serde_json::from_str("\"disk\"").unwrap();
    assert_eq!(shape, KernelShape::Disk);
    assert_eq!(KernelShape::default(), KernelShape::Disk);
    assert!(serde_json::from_str::<KernelShape>("\"circle\"").is_err());
}
