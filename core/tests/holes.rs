//! Hole creation (papers 000/001 §4.1): threshold response, which objects open, motion
//! over time, determinism, independence from the map's resolution, and input checks.

use crepuscular::holes::{holed_depth, HoleNoise, HolesDesc};
use crepuscular::raster::NO_OBJECT;
use crepuscular::scene::parse_json_at;
use crepuscular::shadow_map::ShadowMap;
use crepuscular::Error;
use glam::{DMat4, DVec3};

/// A `size`² map looking straight down on the square of side `extent` centred on the
/// world origin; every texel has an occluder at depth 1 with the id `ids` gives it.
fn map(size: u32, extent: f64, ids: impl Fn(u32, u32) -> u32) -> ShadowMap {
    let scale = size as f64 / extent;
    let texel_from_world = DMat4::from_scale(DVec3::new(scale, scale, 1.0))
        * DMat4::from_translation(DVec3::new(0.5 * extent, 0.5 * extent, 0.0));
    let ids: Vec<u32> = (0..size)
        .flat_map(|y| (0..size).map(move |x| (x, y)))
        .map(|(x, y)| ids(x, y))
        .collect();
    let depth = ids
        .iter()
        .map(|&id| if id == NO_OBJECT { f32::INFINITY } else { 1.0 })
        .collect();
    ShadowMap {
        size,
        depth,
        ids,
        texel_from_world,
        texel_size: 1.0 / scale,
        bias: 0.0,
    }
}

fn fraction(holes: &[bool]) -> f64 {
    holes.iter().filter(|&&hole| hole).count() as f64 / holes.len() as f64
}

fn flipped(a: &[bool], b: &[bool]) -> f64 {
    a.iter().zip(b).filter(|(a, b)| a != b).count() as f64 / a.len() as f64
}

fn holes(desc: &HolesDesc, map: &ShadowMap) -> Vec<bool> {
    HoleNoise::for_map(desc, map).unwrap().hole_map()
}

fn field_of(error: Error) -> String {
    match error {
        Error::InvalidInput { field, .. } => field,
        other => panic!("expected an invalid-input error, got {other}"),
    }
}

#[test]
fn raising_the_hole_probability_opens_more_holes() {
    // Eq. 4: a hole where N < h, so the fraction grows with h, from none to all.
    let map = map(256, 16.0, |_, _| 1);
    let mut last = 0.0;
    let mut fractions = Vec::new();
    for step in 0..=20 {
        let threshold = step as f32 / 20.0;
        let desc = HolesDesc {
            threshold,
            time: 4.0,
            ..HolesDesc::default()
        };
        let holes = fraction(&holes(&desc, &map));
        assert!(holes >= last, "h = {threshold}: {holes} < {last}");
        last = holes;
        fractions.push(holes);
    }
    assert_eq!(fractions[0], 0.0);
    assert_eq!(fractions[20], 1.0);
    assert!(
        (0.3..0.7).contains(&fractions[10]),
        "h = 0.5 opens {}",
        fractions[10]
    );
    assert!(fractions[8] < fractions[10] && fractions[10] < fractions[12]);
}

#[test]
fn only_chosen_objects_open_and_others_keep_their_depth_bits() {
    // Stripes of objects 1, 2, 3 and empty texels, narrower than a block of evaluation in
    // the upper half and as wide as one in the lower; depths vary per texel.
    let mut map = map(256, 16.0, |x, y| {
        match (x / if y < 128 { 16 } else { 64 }) % 4 {
            0 => 1,
            1 => 2,
            2 => 3,
            _ => NO_OBJECT,
        }
    });
    for (index, depth) in map.depth.iter_mut().enumerate() {
        if depth.is_finite() {
            *depth = 0.5 + (index % 97) as f32 * 0.013;
        }
    }
    let original = map.clone();
    // A few chosen objects, and more than a few (ids no texel has besides), which are
    // told apart another way.
    for objects in [vec![3, 1], [3, 1].into_iter().chain(100..110).collect()] {
        let desc = HolesDesc {
            objects,
            time: 2.0,
            ..HolesDesc::default()
        };
        let holed = holed_depth(&desc, &map).unwrap();
        let hole_map = holes(&desc, &map);
        let mut opened = [0usize; 4];
        for (index, (&before, &after)) in map.depth.iter().zip(&holed).enumerate() {
            let id = map.ids[index];
            if (id == 1 || id == 3) && hole_map[index] {
                assert_eq!(after, f32::INFINITY, "texel {index} of object {id}");
                opened[id as usize] += 1;
            } else {
                assert_eq!(after.to_bits(), before.to_bits(), "texel {index} (id {id})");
            }
        }
        // Both chosen objects got a fair share of holes; the map itself is unchanged.
        assert!(opened[1] > 2000 && opened[3] > 2000, "{opened:?}");
        assert_eq!(map.depth, original.depth);
        assert_eq!(map.ids, original.ids);

        // Applying in place reports the same count.
        let mut depth = map.depth.clone();
        let noise = HoleNoise::for_map(&desc, &map).unwrap();
        assert_eq!(
            noise.apply(&mut depth, &map.ids).unwrap(),
            opened[1] + opened[3]
        );
        assert!(depth
            .iter()
            .zip(&holed)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

#[test]
fn no_chosen_objects_change_nothing() {
    let map = map(64, 8.0, |x, y| x + y);
    let holed = holed_depth(&HolesDesc::default(), &map).unwrap();
    assert_eq!(holed, map.depth);
    let desc = HolesDesc {
        objects: vec![1000],
        ..HolesDesc::default()
    };
    assert_eq!(holed_depth(&desc, &map).unwrap(), map.depth);
}

/// The continuity bound: at most this fraction of texels may change state between two
/// frames at 24 fps with the default speed and warp, within 8 scene units (16 first-octave
/// cells) of the pivot. Measured about 0.8%.
const MAX_FLIPS_PER_FRAME: f64 = 0.015;

#[test]
fn holes_move_a_little_per_frame_and_a_lot_over_time() {
    let map = map(512, 16.0, |_, _| 1);
    let at = |time: f32| {
        holes(
            &HolesDesc {
                time,
                ..HolesDesc::default()
            },
            &map,
        )
    };
    for start in [0.0, 10.0, 250.0, -3.0] {
        let now = at(start);
        let next = at(start + 1.0 / 24.0);
        let flips = flipped(&now, &next);
        assert!(
            flips <= MAX_FLIPS_PER_FRAME,
            "{:.2}% flipped in one frame from t = {start}",
            100.0 * flips
        );
        assert!(flips > 0.0, "nothing moved from t = {start}");
        // Half a minute later the map has changed substantially (independent maps
        // would differ in about half their texels).
        let later = flipped(&now, &at(start + 30.0));
        assert!(
            later > 0.15,
            "only {:.1}% changed in 30 s from t = {start}",
            100.0 * later
        );
    }
}

#[test]
fn without_warp_time_changes_nothing() {
    let map = map(128, 16.0, |_, _| 1);
    let noise = |time| {
        HoleNoise::for_map(
            &HolesDesc {
                warp: 0.0,
                time,
                ..HolesDesc::default()
            },
            &map,
        )
        .unwrap()
        .noise_map()
    };
    assert_eq!(noise(0.0), noise(77.0));
}

#[test]
fn the_same_time_gives_the_same_bits_for_any_thread_count() {
    let map = map(300, 12.0, |x, y| 1 + (x * y) % 3);
    let desc = HolesDesc {
        time: 12.375,
        objects: vec![1, 2],
        ..HolesDesc::default()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let noise = HoleNoise::for_map(&desc, &map).unwrap().noise_map();
            (noise, holed_depth(&desc, &map).unwrap())
        })
    };
    let (noise, depth) = run(1);
    for threads in [1, 2, 3] {
        let (other_noise, other_depth) = run(threads);
        assert!(noise
            .iter()
            .zip(&other_noise)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(depth
            .iter()
            .zip(&other_depth)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
    // Rows agree with the whole map.
    let noise_field = HoleNoise::for_map(&desc, &map).unwrap();
    let mut row = vec![0.0; 300];
    noise_field.noise_row(123, &mut row).unwrap();
    assert_eq!(row, noise[123 * 300..124 * 300]);
}

#[test]
fn the_holes_do_not_depend_on_the_maps_resolution() {
    let desc = HolesDesc {
        time: 6.0,
        ..HolesDesc::default()
    };
    let coarse = holes(&desc, &map(512, 20.0, |_, _| 1));
    let fine = holes(&desc, &map(1024, 20.0, |_, _| 1));
    let (coarse_fraction, fine_fraction) = (fraction(&coarse), fraction(&fine));
    assert!(
        (coarse_fraction - fine_fraction).abs() < 0.01,
        "{coarse_fraction} at 512² vs {fine_fraction} at 1024²"
    );
    // Texel by texel: a coarse texel mostly agrees with the fine texels it covers.
    let mut agree = 0;
    for y in 0..512 {
        for x in 0..512 {
            let covered: usize = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .filter(|(dx, dy)| fine[(2 * y + dy) * 1024 + 2 * x + dx])
                .count();
            agree += usize::from((covered >= 2) == coarse[y * 512 + x]);
        }
    }
    let agreement = agree as f64 / (512.0 * 512.0);
    assert!(agreement > 0.9, "{:.1}% of texels agree", 100.0 * agreement);
}

#[test]
fn the_holes_stay_put_in_the_world_when_the_map_moves() {
    // A map shifted by 37 texels sees world point x at texel x + 37: the overlap agrees.
    let desc = HolesDesc {
        time: 1.0,
        ..HolesDesc::default()
    };
    let here = map(256, 16.0, |_, _| 1);
    let mut there = here.clone();
    let shift = 37.0 * here.texel_size;
    there.texel_from_world =
        here.texel_from_world * DMat4::from_translation(DVec3::new(shift, 0.0, 0.0));
    let (here, there) = (holes(&desc, &here), holes(&desc, &there));
    let mut same = 0;
    for y in 0..256 {
        for x in 37..256 {
            same += usize::from(here[y * 256 + x - 37] == there[y * 256 + x]);
        }
    }
    let agreement = same as f64 / (256.0 * 219.0);
    assert!(agreement > 0.999, "{:.2}% agree", 100.0 * agreement);
}

#[test]
fn noise_stays_within_zero_and_one() {
    let map = map(256, 10.0, |_, _| 1);
    for (octaves, persistence, warp, grid_size, seed) in [
        (1, 0.5, 0.0, 64, 0),
        (1, 1.0, 8.0, 7, 3),
        (4, 0.5, 0.5, 64, 11),
        (8, 1.0, 64.0, 1, 5),
        (16, 0.9, 2.0, 16, 12345),
        (6, 0.7, 1.0, 4096, 99),
    ] {
        let desc = HolesDesc {
            octaves,
            persistence,
            warp,
            grid_size,
            seed,
            time: 9.0,
            frequency: 0.05,
            ..HolesDesc::default()
        };
        let noise = HoleNoise::for_map(&desc, &map).unwrap().noise_map();
        let (low, high) = noise.iter().fold((1.0f32, 0.0f32), |(low, high), &n| {
            (low.min(n), high.max(n))
        });
        assert!(
            (0.0..=1.0).contains(&low) && (0.0..=1.0).contains(&high),
            "{desc:?}: [{low}, {high}]"
        );
        if octaves == 1 && grid_size == 64 {
            // One octave alone spans most of the range: the scale is not too timid.
            assert!(low < 0.1 && high > 0.9, "[{low}, {high}]");
        }
    }
}

#[test]
fn the_seed_changes_the_pattern() {
    let map = map(128, 16.0, |_, _| 1);
    let with = |seed| {
        holes(
            &HolesDesc {
                seed,
                ..HolesDesc::default()
            },
            &map,
        )
    };
    assert!(flipped(&with(1), &with(2)) > 0.3);
}

#[test]
fn bad_settings_name_their_field() {
    let bad = [
        (
            HolesDesc {
                frequency: -1.0,
                ..HolesDesc::default()
            },
            "style.holes.frequency",
        ),
        (
            HolesDesc {
                frequency: f32::NAN,
                ..HolesDesc::default()
            },
            "style.holes.frequency",
        ),
        (
            HolesDesc {
                persistence: 0.0,
                ..HolesDesc::default()
            },
            "style.holes.persistence",
        ),
        (
            HolesDesc {
                persistence: 1.5,
                ..HolesDesc::default()
            },
            "style.holes.persistence",
        ),
        (
            HolesDesc {
                octaves: 0,
                ..HolesDesc::default()
            },
            "style.holes.octaves",
        ),
        (
            HolesDesc {
                octaves: 17,
                ..HolesDesc::default()
            },
            "style.holes.octaves",
        ),
        (
            HolesDesc {
                threshold: f32::NAN,
                ..HolesDesc::default()
            },
            "style.holes.threshold",
        ),
        (
            HolesDesc {
                threshold: 1.5,
                ..HolesDesc::default()
            },
            "style.holes.threshold",
        ),
        (
            HolesDesc {
                grid_size: 0,
                ..HolesDesc::default()
            },
            "style.holes.grid_size",
        ),
        (
            HolesDesc {
                time: f32::INFINITY,
                ..HolesDesc::default()
            },
            "style.holes.time",
        ),
        (
            HolesDesc {
                speed: f32::NAN,
                ..HolesDesc::default()
            },
            "style.holes.speed",
        ),
        (
            HolesDesc {
                warp: -0.1,
                ..HolesDesc::default()
            },
            "style.holes.warp",
        ),
        (
            HolesDesc {
                pivot: [0.0, f32::NAN, 0.0],
                ..HolesDesc::default()
            },
            "style.holes.pivot[1]",
        ),
        (
            HolesDesc {
                objects: vec![2, NO_OBJECT],
                ..HolesDesc::default()
            },
            "style.holes.objects[1]",
        ),
    ];
    let map = map(64, 8.0, |_, _| 1);
    for (desc, field) in bad {
        assert_eq!(field_of(desc.validate().unwrap_err()), field, "{desc:?}");
        assert_eq!(field_of(holed_depth(&desc, &map).unwrap_err()), field);
    }
    HolesDesc::default().validate().unwrap();
}

#[test]
fn bad_maps_are_errors_not_panics() {
    let desc = HolesDesc {
        objects: vec![1],
        ..HolesDesc::default()
    };
    let good = map(64, 8.0, |_, _| 1);

    let mut nan = good.clone();
    nan.texel_from_world.x_axis.x = f64::NAN;
    assert_eq!(
        field_of(holed_depth(&desc, &nan).unwrap_err()),
        "shadow_map.texel_from_world"
    );
    let mut flat = good.clone();
    flat.texel_from_world.y_axis = flat.texel_from_world.x_axis;
    flat.texel_from_world.x_axis = glam::DVec4::ZERO;
    assert!(holed_depth(&desc, &flat).is_err());

    let mut short = good.clone();
    short.depth.pop();
    assert!(holed_depth(&desc, &short).is_err());
    let mut tiny = good.clone();
    tiny.size = 0;
    assert!(holed_depth(&desc, &tiny).is_err());

    // So many cells per texel that the noise could not be resolved.
    let dense = HolesDesc {
        frequency: 1.0e6,
        grid_size: 4096,
        octaves: 16,
        ..desc.clone()
    };
    assert_eq!(
        field_of(holed_depth(&dense, &good).unwrap_err()),
        "style.holes.frequency"
    );

    let noise = HoleNoise::for_map(&desc, &good).unwrap();
    let mut row = vec![0.0; 10];
    assert!(noise.noise_row(0, &mut row).is_err());
    let mut row = vec![0.0; 64];
    assert!(noise.noise_row(64, &mut row).is_err());
}

#[test]
fn settings_read_from_json_with_defaults_and_reject_unknown_keys() {
    let desc: HolesDesc = parse_json_at(
        "style.holes",
        r#"{"threshold": 0.3, "objects": [4, 9], "pivot": [1, 2, 3]}"#,
    )
    .unwrap();
    assert_eq!(desc.threshold, 0.3);
    assert_eq!(desc.objects, vec![4, 9]);
    assert_eq!(desc.pivot, [1.0, 2.0, 3.0]);
    assert_eq!(desc.octaves, HolesDesc::default().octaves);
    let text = serde_json::to_string(&desc).unwrap();
    assert_eq!(parse_json_at::<HolesDesc>("", &text).unwrap(), desc);

    let error = parse_json_at::<HolesDesc>("style.holes", r#"{"treshold": 0.3}"#).unwrap_err();
    assert!(error.to_string().contains("treshold"), "{error}");
}

/// A scene names the hole objects that none of its meshes is: a typo, or a preset written
/// for another scene; they are listed once each, sorted.
#[test]
fn hole_objects_without_a_mesh_are_listed() {
    let mut scene = crepuscular::builtin_scene("tree").unwrap();
    let ids: Vec<u32> = scene.meshes.iter().map(|mesh| mesh.object_id).collect();
    assert!(
        scene.hole_objects_without_mesh().is_empty(),
        "no holes style"
    );
    scene.style.holes = Some(HolesDesc {
        objects: vec![99, ids[0], 42, 99],
        ..HolesDesc::default()
    });
    assert_eq!(scene.hole_objects_without_mesh(), [42, 99]);
    scene.style.holes.as_mut().unwrap().objects = ids;
    assert!(scene.hole_objects_without_mesh().is_empty());
}
