//! Output must be bit-identical run to run and for any thread count (DESIGN §3).

mod common;

use common::*;
use crepuscular::scene::Scene;
use crepuscular::{render_scene, Layers, RenderControl};
use glam::Vec3;
use rand::{RngExt, SeedableRng};

fn scattered_quads_scene() -> Scene {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(42);
    let mut meshes = vec![horizontal_quad(1, -100.0, 100.0, -100.0, 100.0, 0.0)];
    for id in 2..300 {
        let (x, y, z) = (
            rng.random_range(-8.0..8.0),
            rng.random_range(-8.0..8.0),
            rng.random_range(3.0..9.0),
        );
        let size = rng.random_range(0.2..0.8);
        meshes.push(horizontal_quad(id, x, x + size, y, y + size, z));
    }
    let camera = pinhole(
        Vec3::new(-14.0, -3.0, 2.0),
        Vec3::new(1.0, 0.2, 0.15),
        28.0,
        96,
        54,
    );
    let mut render = settings(512, 256, 50.0);
    render.supersampling = 2;
    scene(
        camera,
        Vec3::new(0.3, 0.2, -1.0),
        medium(0.06, 0.5),
        meshes,
        render,
    )
}

fn render_with_threads(scene: &Scene, threads: usize) -> Layers {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    pool.install(|| render_scene(scene, &RenderControl::new()))
        .expect("render succeeds")
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

#[test]
fn output_is_bit_identical_across_thread_counts_and_runs() {
    let scene = scattered_quads_scene();
    let one = render_with_threads(&scene, 1);
    let two = render_with_threads(&scene, 2);
    let again = render_with_threads(&scene, 2);
    for other in [&two, &again] {
        assert_eq!(bits(&one.volume), bits(&other.volume));
        assert_eq!(bits(&one.visibility), bits(&other.visibility));
        assert_eq!(bits(&one.depth), bits(&other.depth));
    }
    // The scene really has shafts: visibility varies and some pixels are partly shadowed.
    let partial = one
        .visibility
        .iter()
        .filter(|&&v| v > 0.05 && v < 0.95)
        .count();
    assert!(partial > 100, "only {partial} partly shadowed pixels");
}

/// Layers reuse an earlier frame's dropped buffers without clearing them: every method,
/// shading adaptively or every pixel, at full and half resolution, must set every pixel,
/// so a frame rendered after another scene's (another view) is bit for bit the frame
/// rendered before it.
#[test]
fn frames_do_not_keep_values_from_earlier_frames() {
    use crepuscular::scene::Method;
    let base = scattered_quads_scene();
    for method in [Method::Reference, Method::MinMax, Method::Prefiltered] {
        for (tolerance, downsample) in [(0.01, 1), (0.0, 1), (0.01, 2)] {
            let mut scene = base.clone();
            scene.render.method = method;
            scene.render.adaptive_tolerance = tolerance;
            scene.render.downsample = downsample;
            scene.render.supersampling = 1;
            let mut other = scene.clone();
            other.sun.direction = Vec3::new(-0.5, 0.4, -1.0).normalize();
            other.medium.extinction *= 3.0;
            // Another view and sun, so that the kept camera depth and shadow-map targets
            // hold other values.
            other.camera = pinhole(
                Vec3::new(-12.0, 4.0, 3.0),
                Vec3::new(1.0, -0.3, 0.1),
                35.0,
                96,
                54,
            );
            let first = render_scene(&scene, &RenderControl::new()).expect("render succeeds");
            let kept = (
                bits(&first.volume),
                bits(&first.visibility),
                bits(&first.depth),
            );
            drop(first);
            let between = render_scene(&other, &RenderControl::new()).expect("render succeeds");
            assert!(bits(&between.volume) != kept.0, "the other frame differs");
            drop(between);
            let again = render_scene(&scene, &RenderControl::new()).expect("render succeeds");
            let what = format!("{method:?}, tolerance {tolerance}, 1/{downsample}");
            for (layer, now, before) in [
                ("volume", bits(&again.volume), &kept.0),
                ("visibility", bits(&again.visibility), &kept.1),
                ("depth", bits(&again.depth), &kept.2),
            ] {
                let differs = now.iter().zip(before).position(|(a, b)| a != b);
                assert_eq!(differs, None, "{what}: {layer} differs first at this index");
            }
        }
    }
}
