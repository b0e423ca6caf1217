//! Hole creation on 1024² shadow maps: a map that the chosen object covers entirely (the
//! worst case: every texel is evaluated) and the `tree` scene's map with its leaves chosen.

use crepuscular::holes::{HoleNoise, HolesDesc};
use crepuscular::shadow_map::ShadowMap;
use crepuscular::{builtin_scene, camera::CameraModel};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use glam::{DMat4, DVec3};

/// A 1024² map of one object covering 40 × 40 scene units, seen straight from above.
fn covered_map() -> ShadowMap {
    let size = 1024;
    let scale = size as f64 / 40.0;
    let texel_from_world = DMat4::from_scale(DVec3::new(scale, scale, 1.0))
        * DMat4::from_translation(DVec3::new(20.0, 20.0, 0.0));
    let texels = (size * size) as usize;
    ShadowMap {
        size,
        depth: vec![1.0; texels],
        ids: vec![7; texels],
        texel_from_world,
        texel_size: 1.0 / scale,
        bias: 0.0,
    }
}

fn tree_map() -> ShadowMap {
    let scene = builtin_scene("tree").expect("built-in scene");
    ShadowMap::of_scene(&scene, &CameraModel::new(&scene.camera)).unwrap()
}

fn holes(c: &mut Criterion) {
    let mut group = c.benchmark_group("holes_1024");
    group.sample_size(30);
    let maps = [
        ("covered", covered_map(), 7),
        ("tree_leaves", tree_map(), 3),
    ];
    for (name, map, object) in &maps {
        for octaves in [4, 5] {
            let desc = HolesDesc {
                octaves,
                time: 1.5,
                objects: vec![*object],
                ..HolesDesc::default()
            };
            let mut depth = map.depth.clone();
            group.bench_with_input(
                BenchmarkId::new(*name, format!("{octaves}_octaves")),
                &desc,
                |b, desc| {
                    b.iter(|| {
                        // Opening a hole twice is the same work, so one copy serves all runs.
                        let noise = HoleNoise::for_map(desc, map).expect("valid settings");
                        noise.apply(&mut depth, &map.ids)
                    })
                },
            );
        }
    }
    group.finish();
}

criterion_group!(benches, holes);
criterion_main!(benches);
