//! Transfer-function benchmarks: applying a baked TF to 1920×1080 layers (both modes), and
//! the 256² diffusion solve behind a diffusion layer.

use crepuscular::diffusion::{self, Pin};
use crepuscular::transfer_function::{
    apply, bake_layers, ApplySettings, BlendMode, ColorStop, DepthRange, DiffusionConstraint,
    GradientShape, TfLayer, TfMode,
};
use crepuscular::Layers;
use criterion::{criterion_group, criterion_main, BatchSize, BenchmarkId, Criterion};

/// 1080p layers with smoothly varying visibility and depth, as a render gives.
fn layers_1080p() -> Layers {
    let (width, height) = (1920u32, 1080u32);
    let mut layers = Layers::new(width, height);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let i = y * width as usize + x;
            let (fx, fy) = (x as f32 / width as f32, y as f32 / height as f32);
            layers.visibility[i] = 0.5 + 0.5 * (fx * 40.0).sin() * (fy * 7.0).cos();
            layers.depth[i] = 2.0 + 60.0 * fy;
            let radiance = layers.visibility[i] * 0.02 * layers.depth[i];
            layers.volume[i * 4..i * 4 + 4].copy_from_slice(&[
                radiance,
                radiance * 0.9,
                radiance * 0.8,
                1.0 - (-0.02 * layers.depth[i]).exp(),
            ]);
        }
    }
    layers
}

fn stack() -> Vec<TfLayer> {
    vec![
        TfLayer::Gradient {
            opacity: 1.0,
            blend: BlendMode::Alpha,
            shape: GradientShape::Linear {
                from: [0.0, 0.0],
                to: [1.0, 1.0],
            },
            stops: vec![
                ColorStop {
                    position: 0.0,
                    color: [1.0, 0.4, 0.1, 1.0],
                },
                ColorStop {
                    position: 1.0,
                    color: [0.2, 0.4, 1.0, 1.0],
                },
            ],
        },
        TfLayer::Diffusion {
            opacity: 0.5,
            blend: BlendMode::Multiply,
            constraints: [
                ([0.1, 0.1], [1.0, 0.2, 0.2, 1.0]),
                ([0.9, 0.3], [0.2, 1.0, 0.2, 1.0]),
                ([0.5, 0.95], [0.2, 0.2, 1.0, 0.5]),
            ]
            .iter()
            .map(|&(position, color)| DiffusionConstraint {
                position,
                color,
                world_point: None,
            })
            .collect(),
        },
    ]
}

fn application(c: &mut Criterion) {
    let layers = layers_1080p();
    let texture = bake_layers(&stack(), 256, "layers").expect("valid stack");
    let mut group = c.benchmark_group("tf_apply_1080p");
    group.sample_size(30);
    for mode in [TfMode::Color, TfMode::Monochrome] {
        let settings = ApplySettings {
            mode,
            depth_range: DepthRange {
                near: 1.0,
                far: 50.0,
            },
            light_color: [1.0, 0.9, 0.8],
        };
        // In place, as the pipeline applies it, on a fresh copy each time (the copy is not
        // timed): re-applying would darken the values towards subnormals.
        group.bench_function(BenchmarkId::from_parameter(format!("{mode:?}")), |b| {
            b.iter_batched_ref(
                || layers.volume.clone(),
                |volume| {
                    apply(
                        &texture,
                        &settings,
                        1920,
                        &layers.visibility,
                        &layers.depth,
                        volume,
                    )
                    .expect("valid layers")
                },
                BatchSize::LargeInput,
            )
        });
    }
    group.finish();
}

fn diffusion_solve(c: &mut Criterion) {
    let pins = [
        Pin {
            x: 25,
            y: 25,
            value: [1.0, 0.2, 0.2, 1.0],
        },
        Pin {
            x: 230,
            y: 76,
            value: [0.2, 1.0, 0.2, 1.0],
        },
        Pin {
            x: 128,
            y: 243,
            value: [0.2, 0.2, 1.0, 0.5],
        },
        Pin {
            x: 60,
            y: 200,
            value: [1.0, 1.0, 0.0, 0.0],
        },
    ];
    let mut group = c.benchmark_group("diffusion");
    group.sample_size(20);
    group.bench_function("solve_256", |b| {
        b.iter(|| diffusion::solve(256, 256, &pins, diffusion::DEFAULT_TOLERANCE).expect("solve"))
    });
    group.bench_function("bake_stack_256", |b| {
        b.iter(|| bake_layers(&stack(), 256, "layers").expect("valid stack"))
    });
    group.finish();
}

criterion_group!(benches, application, diffusion_solve);
criterion_main!(benches);
