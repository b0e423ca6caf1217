//! Kernel benchmarks: shadow-map and camera rasterization, and the reference ray march,
//! on the built-in scenes. Whole-frame timings come from `crepuscular bench`.

use crepuscular::camera::CameraModel;
use crepuscular::raster::{rasterize, RasterDesc};
use crepuscular::reference::Marcher;
use crepuscular::render::FlatGeometry;
use crepuscular::shadow_map::ShadowMap;
use crepuscular::{builtin_scene, BUILTIN_SCENES};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};

fn rasterization(c: &mut Criterion) {
    let mut group = c.benchmark_group("rasterize");
    group.sample_size(20);
    for name in BUILTIN_SCENES {
        let scene = builtin_scene(name).expect("built-in scene");
        let geometry = FlatGeometry::from_scene(&scene);
        let camera = CameraModel::new(&scene.camera);
        group.bench_with_input(
            BenchmarkId::new("shadow_map_1024", name),
            &geometry,
            |b, g| {
                b.iter(|| {
                    ShadowMap::build(&camera, &scene.sun, &scene.medium, &scene.render, &g.view())
                })
            },
        );
        let desc = RasterDesc::perspective(1920, 1080, camera.clip_start, camera.clip_end);
        let pixel_from_world = camera.pixel_from_world();
        group.bench_with_input(BenchmarkId::new("camera_1080p", name), &geometry, |b, g| {
            b.iter(|| rasterize(&g.view(), &pixel_from_world, &desc))
        });
    }
    group.finish();
}

/// 1024 rays of 1024 steps each through the centre row of the image.
fn reference_march(c: &mut Criterion) {
    let mut group = c.benchmark_group("reference_march");
    group.sample_size(20);
    for name in BUILTIN_SCENES {
        let scene = builtin_scene(name).expect("built-in scene");
        let geometry = FlatGeometry::from_scene(&scene);
        let camera = CameraModel::new(&scene.camera);
        let shadow = ShadowMap::build(
            &camera,
            &scene.sun,
            &scene.medium,
            &scene.render,
            &geometry.view(),
        );
        let marcher = Marcher::new(&shadow, &scene.sun, &scene.medium, 1024);
        let rays: Vec<_> = (0..1024)
            .map(|i| {
                camera.ray(
                    (i as f64 + 0.5) * camera.width as f64 / 1024.0,
                    camera.height as f64 / 2.0,
                )
            })
            .collect();
        let max_distance = scene.render.max_distance as f64;
        group.bench_function(BenchmarkId::new("1024_rays_1024_steps", name), |b| {
            b.iter(|| {
                rays.iter()
                    .map(|ray| marcher.march(ray, 0.1, max_distance).scattering)
                    .sum::<f64>()
            })
        });
    }
    group.finish();
}

criterion_group!(kernels, rasterization, reference_march);
criterion_main!(kernels);
