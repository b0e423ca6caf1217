//! Kernel benchmarks: shadow-map and camera rasterization, the reference ray march,
//! epipolar rectification, and prefiltering (basis transform with weighted prefix sums,
//! and per-ray evaluation) on the built-in scenes. Whole-frame timings come from
//! `crepuscular bench`.

use std::sync::Mutex;

use crepuscular::adaptive::{
    shade_adaptively, EpipolarLines, SurfaceCoordinate, DEFAULT_TOLERANCE,
};
use crepuscular::camera::{CameraModel, Ray};
use crepuscular::epipolar::{epipoles_in_image, EpipolarMap, RectifyDesc};
use crepuscular::layers::{Layers, Pixel};
use crepuscular::prefiltered::{Prefiltered, PrefilteredDesc};
use crepuscular::raster::{rasterize, rasterize_depth, RasterDesc};
use crepuscular::reference::{Marcher, RaySample};
use crepuscular::render::FlatGeometry;
use crepuscular::shadow_map::ShadowMap;
use crepuscular::upsample::{joint_bilateral, reduced_size, sample_pixel};
use crepuscular::{builtin_scene, RenderControl, Scene, BUILTIN_SCENES};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use rayon::prelude::*;

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
            |b, g| b.iter(|| ShadowMap::of_scene_geometry(&scene, &camera, g).unwrap()),
        );
        let desc = RasterDesc::perspective(1920, 1080, camera.clip_start, camera.clip_end);
        let pixel_from_world = camera.pixel_from_world();
        group.bench_with_input(BenchmarkId::new("camera_1080p", name), &geometry, |b, g| {
            b.iter(|| rasterize_depth(&g.view(), &pixel_from_world, &desc).unwrap())
        });
    }
    group.finish();
}

/// A built-in scene, optionally resized, with its camera and shadow map.
fn with_shadow_map(name: &str, size: Option<(u32, u32)>) -> (Scene, CameraModel, ShadowMap) {
    let mut scene = builtin_scene(name).expect("built-in scene");
    if let Some((width, height)) = size {
        scene.camera.width = width;
        scene.camera.height = height;
    }
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
    (scene, camera, shadow)
}

/// 1024 rays of 1024 steps each through the centre row of the image, and the exact walk
/// through the shadow map's texels.
fn reference_march(c: &mut Criterion) {
    let mut group = c.benchmark_group("reference_march");
    group.sample_size(20);
    for name in BUILTIN_SCENES {
        let (scene, camera, shadow) = with_shadow_map(name, None);
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
        // The fast methods' exact fallback, on the rays near a sun in view that cross few
        // texels: a block of 64×64 pixels around it, walked to the max distance.
        let Some([sun_x, sun_y]) = epipoles_in_image(&camera, &shadow, 0.0).next() else {
            continue;
        };
        let block: Vec<_> = (0..64 * 64)
            .map(|i| {
                camera.ray(
                    sun_x + (i % 64) as f64 - 32.0,
                    sun_y + (i / 64) as f64 - 32.0,
                )
            })
            .collect();
        group.bench_function(BenchmarkId::new("walk_64x64_at_the_sun", name), |b| {
            b.iter(|| {
                block
                    .iter()
                    .map(|ray| marcher.walk_texels(ray, 0.1, max_distance).scattering)
                    .sum::<f64>()
            })
        });
    }
    group.finish();
}

/// At 1920×1080 with a 1024² map: rectification, the filtered basis for M = 16/32/64,
/// and evaluation of 4096 rays spread over the image, of the rays a frame's adaptive
/// shading shades (the method's batches alone: the rays it declines are not walked), and
/// of a block of 128×128 pixels at its centre.
fn prefiltering(c: &mut Criterion) {
    let mut group = c.benchmark_group("prefiltering");
    group.sample_size(10);
    for name in ["tree", "colonnade"] {
        let (scene, camera, shadow) = with_shadow_map(name, Some((1920, 1080)));
        let desc = RectifyDesc::prefiltered(0);
        group.bench_function(BenchmarkId::new("rectify", name), |b| {
            b.iter(|| EpipolarMap::build(&camera, &shadow, &desc))
        });
        let map = EpipolarMap::build(&camera, &shadow, &desc)
            .expect("memory for the map")
            .expect("rectifiable view");
        let epipoles: Vec<[f64; 2]> = epipoles_in_image(&camera, &shadow, f64::INFINITY).collect();
        for bases in [16, 32, 64] {
            group.bench_function(BenchmarkId::new(format!("filter_m{bases}"), name), |b| {
                let desc = PrefilteredDesc {
                    bases,
                    ..PrefilteredDesc::from_settings(&scene.render)
                };
                b.iter(|| {
                    Prefiltered::build(&map, &camera, &epipoles, &desc, &scene.sun, &scene.medium)
                })
            });
        }
        let desc = PrefilteredDesc::from_settings(&scene.render);
        let prefiltered =
            Prefiltered::build(&map, &camera, &epipoles, &desc, &scene.sun, &scene.medium)
                .expect("memory for the method");
        let rays: Vec<_> = (0..4096)
            .map(|i| {
                camera.ray(
                    (i % 64) as f64 * 30.0 + 15.0,
                    (i / 64) as f64 * 16.875 + 8.0,
                )
            })
            .collect();
        let max_distance = scene.render.max_distance as f64;
        group.bench_function(BenchmarkId::new("evaluate_4096_rays_m32", name), |b| {
            b.iter(|| {
                rays.iter()
                    .filter_map(|ray| prefiltered.march(ray, 0.1, max_distance))
                    .map(|sample| sample.scattering)
                    .sum::<f64>()
            })
        });
        let runs = shaded_runs(&scene, &camera, &shadow, &prefiltered);
        let rays: usize = runs.iter().map(Vec::len).sum();
        eprintln!(
            "{name}: adaptive shading shades {rays} rays in {} runs",
            runs.len()
        );
        group.bench_function(BenchmarkId::new("shaded_rays_m32", name), |b| {
            b.iter(|| {
                runs.par_iter()
                    .map(|run| {
                        let mut out = vec![None; run.len()];
                        prefiltered.march_many(
                            run.len(),
                            |i| (&run[i].0, run[i].1, run[i].2),
                            &mut out,
                        );
                        out.iter()
                            .flatten()
                            .map(|sample| sample.scattering)
                            .sum::<f64>()
                    })
                    .sum::<f64>()
            })
        });
        // Neighbouring pixels, as a frame shades them: its rectified rows stay in cache.
        let block: Vec<_> = (0..128 * 128)
            .map(|i| camera.ray((896 + i % 128) as f64 + 0.5, (476 + i / 128) as f64 + 0.5))
            .collect();
        group.bench_function(BenchmarkId::new("evaluate_128x128_block_m32", name), |b| {
            b.iter(|| {
                block
                    .iter()
                    .filter_map(|ray| prefiltered.march(ray, 0.1, max_distance))
                    .map(|sample| sample.scattering)
                    .sum::<f64>()
            })
        });
    }
    group.finish();
}

/// The rays a 1920×1080 frame of `scene` shades with prefiltering, each with its span, in
/// the runs that adaptive shading hands the method (in the frame's order within a run):
/// to time the method's rays apart from the passes between them. The frame is the
/// renderer's but for the light's colour and phase, which scale every pixel alike, and
/// rays the method declines, which take the reference's march here rather than the walk.
fn shaded_runs(
    scene: &Scene,
    camera: &CameraModel,
    shadow: &ShadowMap,
    prefiltered: &Prefiltered,
) -> Vec<Vec<(Ray, f64, f64)>> {
    let planar = camera_depth_1080p(scene, camera);
    let max_distance = scene.render.max_distance;
    // Along the ray to the surface, +∞ for background.
    let distance =
        |x: usize, y: usize, ray: &Ray| planar[y * 1920 + x] as f64 * ray.distance_per_depth;
    let ray_of = |x: usize, y: usize| {
        let ray = camera.ray(x as f64 + 0.5, y as f64 + 0.5);
        let t_end = distance(x, y, &ray).min(max_distance as f64);
        (ray, camera.clip_start * ray.distance_per_depth, t_end)
    };
    let marcher = Marcher::new(shadow, &scene.sun, &scene.medium, scene.render.steps);
    let runs = Mutex::new(Vec::new());
    let shade = |pixels: &[(usize, usize)], out: &mut [Pixel]| {
        let rays: Vec<_> = pixels.iter().map(|&(x, y)| ray_of(x, y)).collect();
        let mut samples = vec![None; rays.len()];
        prefiltered.march_many(
            rays.len(),
            |i| (&rays[i].0, rays[i].1, rays[i].2),
            &mut samples,
        );
        for ((sample, (ray, t_start, t_end)), out) in samples.iter().zip(&rays).zip(out) {
            let RaySample {
                scattering,
                alpha,
                visibility,
            } = sample.unwrap_or_else(|| marcher.march(ray, *t_start, *t_end));
            let v = scattering as f32;
            *out = Pixel {
                volume: [v, v, v, alpha as f32],
                visibility: visibility as f32,
                depth: *t_end as f32,
            };
        }
        runs.lock().unwrap().push((pixels[0], rays));
    };
    let surface =
        |x: usize, y: usize| Some(distance(x, y, &camera.ray(x as f64 + 0.5, y as f64 + 0.5)));
    let lines = EpipolarLines::of_view(camera, scene.sun.direction.as_dvec3(), 1);
    shade_adaptively(
        1920,
        1080,
        DEFAULT_TOLERANCE,
        max_distance,
        Some(lines),
        SurfaceCoordinate::of_camera(camera),
        &RenderControl::new(),
        surface,
        shade,
    )
    .unwrap();
    let mut runs = runs.into_inner().unwrap();
    // In a fixed order: threads finish runs in any.
    runs.sort_by_key(|&((x, y), _)| (y, x));
    runs.into_iter().map(|(_, rays)| rays).collect()
}

/// `tree` at 1920×1080 and its rasterized camera depth (+∞ for background): its leaves
/// make many depth edges.
fn tree_camera_depth_1080p() -> (Scene, Vec<f32>) {
    let (scene, camera, _) = with_shadow_map("tree", Some((1920, 1080)));
    let depth = camera_depth_1080p(&scene, &camera);
    (scene, depth)
}

/// `scene`'s rasterized planar camera depth at 1920×1080 (+∞ for background).
fn camera_depth_1080p(scene: &Scene, camera: &CameraModel) -> Vec<f32> {
    let geometry = FlatGeometry::from_scene(scene);
    let desc = RasterDesc::perspective(1920, 1080, camera.clip_start, camera.clip_end);
    rasterize(&geometry.view(), &camera.pixel_from_world(), &desc)
        .unwrap()
        .depth
}

/// Joint-bilateral upsampling of ½- and ¼-resolution layers to 1920×1080, guided by
/// tree's rasterized camera depth (its leaves make many depth edges).
fn upsampling(c: &mut Criterion) {
    let mut group = c.benchmark_group("upsample_1080p");
    group.sample_size(20);
    let (scene, depth) = tree_camera_depth_1080p();
    let depth: Vec<f32> = depth
        .iter()
        .map(|&d| d.min(scene.render.max_distance))
        .collect();
    for factor in [2u32, 4] {
        let (width, height) = (reduced_size(1920, factor), reduced_size(1080, factor));
        let mut low = Layers::new(width, height);
        for y in 0..height {
            for x in 0..width {
                let i = (y * width + x) as usize;
                let full = sample_pixel(y, factor, 1080) * 1920 + sample_pixel(x, factor, 1920);
                low.depth[i] = depth[full as usize];
                low.visibility[i] = ((x ^ y) % 7) as f32 / 6.0;
                low.volume[i * 4..i * 4 + 4].fill(low.visibility[i]);
            }
        }
        group.bench_function(BenchmarkId::new("joint_bilateral", factor), |b| {
            b.iter(|| joint_bilateral(&low, &depth, None, 1920, 1080, factor).unwrap())
        });
    }
    group.finish();
}

/// Adaptive shading's own cost at 1080p: a shading function that costs next to nothing,
/// smooth but for tree's depth edges, so the time is the bookkeeping of the shaded grids
/// and the test of every pixel between, without and with tree's epipolar lines.
fn adaptive_shading(c: &mut Criterion) {
    let mut group = c.benchmark_group("adaptive_1080p");
    group.sample_size(20);
    let (scene, depth) = tree_camera_depth_1080p();
    let camera = CameraModel::new(&scene.camera);
    let max_distance = scene.render.max_distance;
    let surface = |x: usize, y: usize| Some(depth[y * 1920 + x] as f64);
    let shade = |pixels: &[(usize, usize)], out: &mut [Pixel]| {
        for (&(x, y), out) in pixels.iter().zip(out) {
            let v = 1.0 + 1e-4 * (x + y) as f32;
            *out = Pixel {
                volume: [v, v, v, 0.5],
                visibility: 0.5,
                depth: depth[y * 1920 + x].min(max_distance),
            };
        }
    };
    let lines = EpipolarLines::of_view(&camera, scene.sun.direction.as_dvec3(), 1);
    for (name, lines) in [
        ("tree_depth_smooth_light", None),
        ("tree_depth_smooth_light_epipolar", Some(lines)),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                let control = RenderControl::new();
                shade_adaptively(
                    1920,
                    1080,
                    DEFAULT_TOLERANCE,
                    max_distance,
                    lines,
                    SurfaceCoordinate::of_camera(&camera),
                    &control,
                    surface,
                    shade,
                )
                .unwrap()
            })
        });
    }
    group.finish();
}

criterion_group!(
    kernels,
    rasterization,
    reference_march,
    prefiltering,
    upsampling,
    adaptive_shading
);
criterion_main!(kernels);
