//! Occluder manipulation on a 1024² shadow map (papers 000/001 §4.1, Table 2): 2D
//! closing for hole filling, and 1D epipolar dilation and closure for silhouette
//! enhancement, on the `tree` scene's map with its own epipole and with epipoles placed
//! inside, outside and at infinity.

use crepuscular::builtin_scene;
use crepuscular::camera::CameraModel;
use crepuscular::morphology::{self, KernelShape, MorphologyDesc};
use crepuscular::shadow_map::ShadowMap;
use crepuscular::silhouette::{self, Epipole, SilhouetteDesc};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use glam::DVec3;

fn tree_map() -> (ShadowMap, Epipole) {
    let mut scene = builtin_scene("tree").expect("built-in scene");
    scene.render.shadow_map_size = 1024;
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
    let epipole = Epipole::of_camera(&camera, &shadow.texel_from_world);
    (shadow, epipole)
}

fn hole_filling(c: &mut Criterion) {
    let (shadow, _) = tree_map();
    let mut group = c.benchmark_group("morphology_1024");
    group.sample_size(20);
    for (name, desc) in [
        (
            "close_disk_r20",
            MorphologyDesc::close(KernelShape::Disk, 20.0),
        ),
        (
            "close_box_r20",
            MorphologyDesc::close(KernelShape::Box, 20.0),
        ),
        (
            "close_disk_r5",
            MorphologyDesc::close(KernelShape::Disk, 5.0),
        ),
        (
            "close_disk_r10",
            MorphologyDesc::close(KernelShape::Disk, 10.0),
        ),
        (
            "dilate_disk_r20",
            MorphologyDesc::dilate(KernelShape::Disk, 20.0),
        ),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| morphology::apply(&shadow.depth, shadow.size, &desc).expect("valid"))
        });
    }
    group.finish();
}

fn silhouette_enhancement(c: &mut Criterion) {
    let (shadow, own) = tree_map();
    let mut group = c.benchmark_group("silhouette_1024");
    group.sample_size(20);
    let epipoles = [
        ("tree_camera", own),
        ("inside", Epipole::Point(DVec3::new(512.3, 400.7, 0.0))),
        ("outside", Epipole::Point(DVec3::new(-300.0, 700.0, 0.0))),
        ("parallel", Epipole::Direction(DVec3::new(0.8, -0.35, 0.1))),
    ];
    for (name, epipole) in epipoles {
        for (op, desc) in [
            ("close_60", SilhouetteDesc::close(60.0)),
            ("dilate_60", SilhouetteDesc::dilate(60.0)),
        ] {
            group.bench_function(BenchmarkId::new(op, name), |b| {
                b.iter(|| {
                    silhouette::apply(&shadow.depth, shadow.size, epipole, &desc).expect("valid")
                })
            });
        }
    }
    group.finish();
}

criterion_group!(stylize, hole_filling, silhouette_enhancement);
criterion_main!(stylize);
