//! The Vulkan backend against the CPU oracle, stage by stage and for whole frames of the
//! built-in scenes, on whatever Vulkan device there is (lavapipe in CI). Without a Vulkan
//! loader or device every test prints why it skips and passes.
//!
//! Errors are measured per layer as the mean relative error Σ|gpu − cpu| / Σ|cpu| (bound
//! 1e-3) and the largest absolute difference (bounds stated per test), which a few pixels
//! on edges may pass in the ways `edge_outliers` checks. `CREPUSCULAR_PARITY_FULL` runs
//! them at the benchmark's size, where those pixels occur (on lavapipe as on a real GPU).

mod common;

use std::sync::Arc;

use common::{
    camera_inside_a_fog_box, dilated_roof_in_a_thin_box, ground_lit_from_below, radiance_error,
    small_fog_box_far_off, SUNS_BELOW,
};
use crepuscular::builtin::{builtin_scene, BUILTIN_SCENES};
use crepuscular::camera::CameraModel;
use crepuscular::epipolar::{epipoles_in_image, EpipolarMap, RectifyDesc};
use crepuscular::gpu::GpuError;
use crepuscular::gpu::{self, Device, DeviceKind, DevicePolicy};
use crepuscular::holes::{HoleNoise, HolesDesc};
use crepuscular::morphology::{self, KernelShape, MorphologyDesc, MorphologyOp};
use crepuscular::prefiltered::{
    CpuPrefixSums, FilteredBasis, Prefiltered, PrefilteredDesc, PrefixPlan, PrefixSums,
};
use crepuscular::raster::{rasterize, DepthTarget, Rasterizer, NO_OBJECT};
use crepuscular::render::{camera_raster, render_timed_cpu, FlatGeometry, Frame};
use crepuscular::scene::{
    BasisStorage, Camera, ExactRayEnds, Extent, Method, Projection, Rectification, Scene,
};
use crepuscular::shadow_map::ShadowMap;
use crepuscular::silhouette::{self, Epipole, SilhouetteDesc};
use crepuscular::transfer_function::{self, ApplySettings, DepthRange, TfMode, TfTexture};
use crepuscular::upsample;
use crepuscular::{Backend, Error, Layers, RenderControl, Style};

const MEAN_RELATIVE: f64 = 1e-3;

fn device(test: &str) -> Option<Arc<Device>> {
    match gpu::shared_device(DevicePolicy::Any) {
        Ok(device) => {
            eprintln!("{test} on {}", device.describe());
            Some(device)
        }
        Err(err) => {
            eprintln!("skipping {test}: {err}");
            None
        }
    }
}

/// (mean relative error, max absolute error).
fn compare(gpu: &[f32], cpu: &[f32]) -> (f64, f64) {
    assert_eq!(gpu.len(), cpu.len());
    let (mut diff, mut total, mut max) = (0.0f64, 0.0f64, 0.0f64);
    for (&g, &c) in gpu.iter().zip(cpu) {
        assert!(g.is_finite() == c.is_finite(), "finite {g} against {c}");
        if !c.is_finite() {
            assert_eq!(g, c);
            continue;
        }
        let d = (g as f64 - c as f64).abs();
        diff += d;
        total += (c as f64).abs();
        max = max.max(d);
    }
    (if total > 0.0 { diff / total } else { diff }, max)
}

/// Checks every layer; `volume_abs` bounds the volume layer's largest absolute error
/// relative to its largest value, `visibility_abs` the visibility's. A few pixels may pass
/// the bounds on edges only (see [`edge_outliers`]).
fn check_layers(label: &str, gpu: &Layers, cpu: &Layers, volume_abs: f64, visibility_abs: f64) {
    assert_eq!((gpu.width, gpu.height), (cpu.width, cpu.height), "{label}");
    let peak = cpu.volume.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
    let layers = [
        (
            "volume",
            &gpu.volume,
            &cpu.volume,
            volume_abs * peak.max(1e-30),
        ),
        (
            "visibility",
            &gpu.visibility,
            &cpu.visibility,
            visibility_abs,
        ),
        ("depth", &gpu.depth, &cpu.depth, 1e-4 * 1000.0),
    ];
    // V̄ where either backend's ray crosses next to no medium is a ratio of vanishing
    // integrals, or 1 by convention for no medium at all: where geometry crosses the near
    // plane, the GPU's clipped triangles gave 3 pixels of 2,073,600 the near plane's depth
    // (no medium, V̄ 1) and the CPU a shadowed stretch beyond (V̄ 0).
    let no_medium = |pixel: usize| gpu.volume[pixel * 4 + 3].min(cpu.volume[pixel * 4 + 3]) < 1e-4;
    for (name, g, c, bound) in layers {
        let (mean, max) = compare(g, c);
        let exempt = |pixel: usize| name == "visibility" && no_medium(pixel);
        let outliers = edge_outliers(&format!("{label} {name}"), g, c, cpu, bound, &exempt);
        eprintln!(
            "{label} {name}: mean relative error {mean:.2e}, max abs error {max:.3e} \
             (bound {bound:.3e}; {outliers} edge pixels past it)"
        );
        assert!(
            mean <= MEAN_RELATIVE,
            "{label} {name}: mean relative error {mean:.3e}"
        );
    }
}

/// How far around a pixel [`edge_outliers`] looks for the value it took: a pixel's
/// neighbours, and at half resolution the low-resolution samples its upsampling reads.
const EDGE_RADIUS: usize = 2;

/// The pixels of one layer whose GPU and CPU values differ by more than `bound`. At full
/// size a handful do, on edges, where a small difference in the inputs flips which side a
/// pixel takes: the two rasterizers put a pixel's sample on either side of a silhouette
/// (they round vertices differently), the upsampling picks a side by depths a few ulps
/// apart, and a ray grazing a fog box's face marches a sliver whose visibility is a ratio
/// of two tiny integrals. Seen at 1920×1080 on an NVIDIA H200 and on lavapipe: 1 to 5
/// pixels of 2,073,600 per layer, and 103 where the sun runs parallel to a box's walls;
/// none at the size CI renders. Each such pixel must hold a GPU value the CPU has within
/// [`EDGE_RADIUS`] of it (give or take `bound`): the other side's value, not a wrong one.
/// Edges grow with the frame's side, not its area, so at most one pixel per 16 of width
/// and height together may differ so (187 at 1920×1080). Pixels `exempt` says so of are
/// not checked. Returns the number of those that differ.
fn edge_outliers(
    label: &str,
    gpu: &[f32],
    cpu: &[f32],
    frame: &Layers,
    bound: f64,
    exempt: &dyn Fn(usize) -> bool,
) -> usize {
    let (width, height) = (frame.width as usize, frame.height as usize);
    let channels = cpu.len() / (width * height);
    let mut pixels = std::collections::BTreeSet::new();
    for (index, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        if !c.is_finite() || (g as f64 - c as f64).abs() <= bound {
            continue;
        }
        let (pixel, channel) = (index / channels, index % channels);
        if exempt(pixel) {
            continue;
        }
        let (x, y) = (pixel % width, pixel / width);
        let (mut lowest, mut highest) = (f64::INFINITY, f64::NEG_INFINITY);
        for ny in y.saturating_sub(EDGE_RADIUS)..(y + EDGE_RADIUS + 1).min(height) {
            for nx in x.saturating_sub(EDGE_RADIUS)..(x + EDGE_RADIUS + 1).min(width) {
                let value = cpu[(ny * width + nx) * channels + channel] as f64;
                lowest = lowest.min(value);
                highest = highest.max(value);
            }
        }
        assert!(
            (lowest - bound..=highest + bound).contains(&(g as f64)),
            "{label}: pixel ({x}, {y}) holds {g} on the GPU and {c} on the CPU, whose values \
             around it span only {lowest}..{highest}"
        );
        pixels.insert(pixel);
    }
    let allowed = (width + height) / 16;
    assert!(
        pixels.len() <= allowed,
        "{label}: {} pixels on edges differ beyond {bound:.3e}, more than {allowed}",
        pixels.len()
    );
    pixels.len()
}

/// A built-in scene at a size lavapipe renders quickly, or at the benchmark's full size
/// (1920×1080, 1024² map, 1024 steps) when `CREPUSCULAR_PARITY_FULL` is set, for real GPUs.
fn small(name: &str) -> Scene {
    let mut scene = builtin_scene(name).unwrap();
    let full = std::env::var_os("CREPUSCULAR_PARITY_FULL").is_some();
    let (width, height, map, steps) = if full {
        (1920, 1080, 1024, 1024)
    } else {
        (128, 72, 256, 128)
    };
    scene.camera.width = width;
    scene.camera.height = height;
    scene.render.shadow_map_size = map;
    // The march; tests of the prefiltered method set it themselves.
    scene.render.method = Method::Reference;
    // The GPU shades every pixel; so does the CPU here, for the fast methods too.
    scene.render.adaptive_tolerance = 0.0;
    scene.render.steps = steps;
    scene
}

fn render_both(device: &Arc<Device>, scene: &Scene) -> (Layers, Layers, gpu::frame::GpuTimes) {
    let geometry = FlatGeometry::from_scene(scene);
    let frame = Frame::of_scene(scene, &geometry);
    let control = RenderControl::new();
    let (cpu, _) = render_timed_cpu(&frame, &control).unwrap();
    let (gpu, _, times) = gpu::frame::render_timed(device, &frame, &control).unwrap();
    (gpu, cpu, times)
}

fn stylized() -> Style {
    Style::from_json(
        r#"{
        "version": 1,
        "closing": { "operation": "close", "kernel": "disk", "radius": 0.4 },
        "silhouette": { "operation": "close", "length_texels": 6.0 },
        "holes": { "frequency": 0.05, "threshold": 0.45, "warp": 1.0, "objects": [0, 1, 2, 3, 4] },
        "time": 2.5,
        "tf": {
            "mode": "color",
            "depth_range": { "near": 0.0, "far": 60.0 },
            "layers": [{
                "kind": "gradient",
                "shape": { "kind": "linear", "from": [0.0, 0.0], "to": [1.0, 1.0] },
                "stops": [
                    { "position": 0.0, "color": [0.2, 0.1, 0.9, 0.3] },
                    { "position": 1.0, "color": [1.0, 0.6, 0.1, 0.9] }
                ]
            }]
        }
    }"#,
    )
    .unwrap()
}

/// The reference ray march alone: every built-in scene in its physical style. Visibility
/// is a step function sampled at 128 points per ray; f32 against f64 positions may move
/// a sample across an occluder's edge, so a pixel's visibility may differ by a few steps
/// (bound 0.05) and its radiance by a few percent of the image's peak (bound 0.05).
#[test]
fn reference_march_matches_the_cpu_on_the_builtin_scenes() {
    let Some(device) = device("the reference march parity test") else {
        return;
    };
    for name in BUILTIN_SCENES {
        let scene = small(name);
        let (gpu, cpu, times) = render_both(&device, &scene);
        assert!(times.ray_march.is_some() || device.physical.timestamp_valid_bits == 0);
        check_layers(&format!("march {name}"), &gpu, &cpu, 0.05, 0.05);
    }
}

/// `torus` at the parity tests' size in a turned box of fog around its subject.
fn torus_in_a_box() -> Scene {
    let mut boxed = small("torus");
    boxed.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::new(6.0, 5.0, 3.0),
            glam::Quat::from_rotation_z(0.3),
            glam::Vec3::new(0.0, 0.0, 2.0),
        ),
    };
    boxed
}

/// The march through a `box` medium, with supersampling, and at half resolution.
#[test]
fn reference_march_matches_in_a_box_supersampled_and_downsampled() {
    let Some(device) = device("the box/supersampling march parity test") else {
        return;
    };
    let boxed = torus_in_a_box();
    let (gpu, cpu, _) = render_both(&device, &boxed);
    check_layers("march torus in a box", &gpu, &cpu, 0.05, 0.05);
    let mut supersampled = small("colonnade");
    supersampled.render.supersampling = 2;
    let (gpu, cpu, _) = render_both(&device, &supersampled);
    check_layers("march colonnade 2×2 samples", &gpu, &cpu, 0.05, 0.05);
    let mut downsampled = small("tree");
    downsampled.render.downsample = 2;
    let (gpu, cpu, _) = render_both(&device, &downsampled);
    check_layers("march tree at 1/2", &gpu, &cpu, 0.05, 0.05);
    let mut anamorphic = small("plane");
    anamorphic.camera.pixel_aspect = 2.0;
    anamorphic.camera.width /= 2;
    let (gpu, cpu, _) = render_both(&device, &anamorphic);
    check_layers("march plane, pixels 2:1", &gpu, &cpu, 0.05, 0.05);
}

/// A box whose sunlight is not attenuated (a sun that casts no shadows), marched and
/// prefiltered: the GPU's layers as the CPU's, and not those of the attenuated box.
#[test]
fn a_box_that_does_not_dim_the_sun_matches() {
    let Some(device) = device("the undimmed box parity test") else {
        return;
    };
    let mut scene = torus_in_a_box();
    scene.medium.extinction = 0.3;
    for method in [Method::Reference, Method::Prefiltered] {
        scene.render.method = method;
        scene.sun.attenuated_by_medium = true;
        let (dimmed, _, _) = render_both(&device, &scene);
        scene.sun.attenuated_by_medium = false;
        let (gpu, cpu, _) = render_both(&device, &scene);
        check_layers(
            &format!("{method:?} in an undimming box"),
            &gpu,
            &cpu,
            0.05,
            0.05,
        );
        let brighter = radiance_error(&dimmed, &gpu);
        assert!(
            brighter > 0.1,
            "{method:?}: the attenuation moves the GPU frame by {brighter}"
        );
    }
}

/// Fog over a ground lit from below, marched and prefiltered: dark on the GPU as on the
/// CPU (the shaders end each ray's light where the bias's sliver behind the ground's
/// unlit side begins), with the opacity of the whole ray.
#[test]
fn fog_over_a_ground_lit_from_below_is_dark() {
    let Some(device) = device("the ground lit from below") else {
        return;
    };
    for (label, sun) in SUNS_BELOW {
        for method in [Method::Reference, Method::Prefiltered] {
            let mut scene = ground_lit_from_below(sun, method);
            let (gpu, cpu, _) = render_both(&device, &scene);
            scene.meshes[0].blocks_sun = false;
            let open = crepuscular::render_scene(&scene, &RenderControl::new()).unwrap();
            let red = |layers: &Layers| layers.volume.chunks(4).map(|v| v[0] as f64).sum::<f64>();
            let (dark, lit) = (red(&gpu), red(&open));
            eprintln!(
                "{label} {method:?}: GPU {dark:e} of open fog {lit:e}, CPU {:e}",
                red(&cpu)
            );
            assert!(dark <= 1e-5 * lit, "{label} {method:?}: {dark} of {lit}");
            let alpha = gpu
                .volume
                .chunks(4)
                .zip(cpu.volume.chunks(4))
                .fold(0.0f32, |m, (g, c)| m.max((g[3] - c[3]).abs()));
            assert!(alpha < 1e-4, "{label} {method:?}: alpha differs by {alpha}");
        }
    }
}

/// Hole filling: minimum and maximum are exact, so the GPU must equal the CPU bit for
/// bit (max abs error 0) for every operation and kernel.
#[test]
fn morphology_equals_the_cpu_exactly() {
    let Some(device) = device("the morphology parity test") else {
        return;
    };
    for name in BUILTIN_SCENES {
        let scene = small(name);
        let camera = CameraModel::new(&scene.camera);
        let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
        for (op, shape, radius) in [
            (MorphologyOp::Close, KernelShape::Disk, 4.5),
            (MorphologyOp::Open, KernelShape::Disk, 2.0),
            (MorphologyOp::Close, KernelShape::Box, 3.7),
            (MorphologyOp::Dilate, KernelShape::Box, 1.0),
            (MorphologyOp::Erode, KernelShape::Disk, 0.0),
        ] {
            let desc = MorphologyDesc::new(op, shape, radius);
            let cpu = morphology::apply(&shadow.depth, shadow.size, &desc).unwrap();
            let (gpu, _) =
                gpu::morphology::apply(&device, &shadow.depth, shadow.size, &desc).unwrap();
            let differing = gpu
                .iter()
                .zip(&cpu)
                .filter(|(g, c)| g.to_bits() != c.to_bits())
                .count();
            eprintln!("morphology {name} {desc:?}: {differing} texels differ");
            assert_eq!(differing, 0, "{name} {desc:?}");
        }
    }
}

/// (texels whose bits differ, largest absolute difference) between two depth maps; +∞
/// against a finite depth counts as an infinite difference.
fn depth_parity(gpu: &[f32], cpu: &[f32]) -> (usize, f64) {
    assert_eq!(gpu.len(), cpu.len());
    gpu.iter()
        .zip(cpu)
        .filter(|(g, c)| g.to_bits() != c.to_bits())
        .fold((0, 0.0f64), |(count, max), (&g, &c)| {
            let d = if g == c {
                0.0
            } else {
                (g as f64 - c as f64).abs()
            };
            (count + 1, max.max(d))
        })
}

/// A built-in scene seen through an orthographic camera.
fn orthographic(scene: &Scene) -> Scene {
    let mut scene = scene.clone();
    scene.camera.projection = Projection::orthographic(30.0);
    scene
}

/// Silhouette enhancement: the shader walks each texel's rays as `apply_naive` does, with
/// the CPU's line tables, in the CPU's precision and operation order, so the GPU must
/// equal the CPU bit for bit (0 texels differ, max abs error 0) for dilation and closure,
/// pinhole and orthographic cameras, and several lengths.
#[test]
fn silhouettes_equal_the_cpu_exactly() {
    let Some(device) = device("the silhouette parity test") else {
        return;
    };
    if !gpu::silhouette::supported(&device) {
        eprintln!("skipping the silhouette parity test: no double precision in shaders");
        return;
    }
    for name in BUILTIN_SCENES {
        let pinhole = small(name);
        for (kind, scene) in [
            ("pinhole", pinhole.clone()),
            ("orthographic", orthographic(&pinhole)),
        ] {
            let camera = CameraModel::new(&scene.camera);
            let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
            let epipole = Epipole::of_camera(&camera, &shadow.texel_from_world);
            for desc in [
                SilhouetteDesc::dilate(3.0),
                SilhouetteDesc::dilate(17.5),
                SilhouetteDesc::close(5.0),
                SilhouetteDesc::close(12.0),
            ] {
                let cpu = silhouette::apply(&shadow.depth, shadow.size, epipole, &desc).unwrap();
                let (gpu, _) =
                    gpu::silhouette::apply(&device, &shadow.depth, shadow.size, epipole, &desc)
                        .unwrap();
                let changed = cpu
                    .iter()
                    .zip(&shadow.depth)
                    .filter(|(a, b)| a != b)
                    .count();
                let (differing, max) = depth_parity(&gpu, &cpu);
                eprintln!(
                    "silhouettes {name} {kind} {desc:?}: {differing} of {} texels differ \
                     (max abs error {max:e}); the filter changed {changed}",
                    cpu.len()
                );
                assert_eq!(differing, 0, "{name} {kind} {desc:?}");
            }
        }
    }
}

/// Hole creation: the shader evaluates `HoleNoise` with the CPU's expressions, so the
/// holed depth must equal the CPU's bit for bit (0 texels differ) for several
/// thresholds, scales, grids (a power of two and not) and times, on one object and on
/// every object of each scene.
#[test]
fn hole_creation_equals_the_cpu_exactly() {
    let Some(device) = device("the hole-creation parity test") else {
        return;
    };
    if !gpu::silhouette::supported(&device) {
        eprintln!("skipping the hole-creation parity test: no double precision in shaders");
        return;
    }
    for name in BUILTIN_SCENES {
        let scene = small(name);
        let camera = CameraModel::new(&scene.camera);
        let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
        let mut all: Vec<u32> = shadow
            .ids
            .iter()
            .copied()
            .filter(|&id| id != NO_OBJECT)
            .collect();
        all.sort_unstable();
        all.dedup();
        assert!(!all.is_empty(), "{name} casts no shadow");
        let one = vec![all[all.len() / 2]];
        let settings = [
            HolesDesc::default(),
            HolesDesc {
                frequency: 0.1,
                threshold: 0.3,
                grid_size: 60,
                time: 7.5,
                warp: 2.0,
                seed: 11,
                ..HolesDesc::default()
            },
            HolesDesc {
                frequency: 0.02,
                persistence: 0.7,
                octaves: 6,
                threshold: 0.8,
                time: 3.0,
                speed: -0.3,
                pivot: [4.0, -2.0, 1.0],
                ..HolesDesc::default()
            },
            HolesDesc {
                frequency: 0.2,
                threshold: 0.5,
                grid_size: 7,
                warp: 0.0,
                ..HolesDesc::default()
            },
        ];
        for base in settings {
            for (which, objects) in [("one object", &one), ("every object", &all)] {
                let desc = HolesDesc {
                    objects: objects.clone(),
                    ..base.clone()
                };
                let noise = HoleNoise::for_map(&desc, &shadow).unwrap();
                let mut cpu = shadow.depth.clone();
                let opened = noise.apply(&mut cpu, &shadow.ids).unwrap();
                let (gpu, _) =
                    gpu::holes::apply(&device, &noise, &shadow.depth, &shadow.ids).unwrap();
                let (differing, _) = depth_parity(&gpu, &cpu);
                eprintln!(
                    "holes {name} {which} h={} f={} g={} t={}: {differing} of {} texels \
                     differ; the CPU opened {opened}",
                    desc.threshold,
                    desc.frequency,
                    desc.grid_size,
                    desc.time,
                    cpu.len()
                );
                assert_eq!(differing, 0, "{name} {which} {desc:?}");
            }
        }
    }
}

/// The TF application alone, on CPU-rendered layers: colour mode under a full light and
/// under a light without blue (channels mixed), and monochrome. Bilinear weights are
/// applied to the TF before (CPU) or after (GPU) the rule, which is the same in exact
/// arithmetic: max abs error 1e-5 of the peak radiance.
#[test]
fn transfer_function_matches_the_cpu() {
    let Some(device) = device("the transfer-function parity test") else {
        return;
    };
    let scene = small("colonnade");
    let geometry = FlatGeometry::from_scene(&scene);
    let frame = Frame::of_scene(&scene, &geometry);
    let (layers, _) = render_timed_cpu(&frame, &RenderControl::new()).unwrap();
    let texels: Vec<[f32; 4]> = (0..16 * 16)
        .map(|i| {
            let (x, y) = ((i % 16) as f32 / 15.0, (i / 16) as f32 / 15.0);
            [x, 0.5 * y, 1.0 - x * y, 0.2 + 0.7 * x]
        })
        .collect();
    let texture = TfTexture::from_texels(16, texels).unwrap();
    let range = DepthRange {
        near: 1.0,
        far: 40.0,
    };
    for (mode, light) in [
        (TfMode::Color, [1.0, 0.9, 0.8]),
        (TfMode::Color, [1.0, 0.5, 0.0]),
        (TfMode::Monochrome, [1.0, 0.9, 0.8]),
    ] {
        let settings = ApplySettings {
            mode,
            depth_range: range,
            light_color: light,
        };
        let mut cpu = layers.clone();
        transfer_function::apply_to_layers(&mut cpu, &texture, &settings).unwrap();
        let mut gpu_layers = layers.clone();
        gpu::transfer::apply(&device, &mut gpu_layers, &texture, &settings).unwrap();
        check_layers(
            &format!("TF {mode:?} {light:?}"),
            &gpu_layers,
            &cpu,
            1e-5,
            0.0,
        );
    }
}

/// Whole stylized frames (GPU shadow map and camera depth, hole filling, silhouettes, hole
/// creation, march and TF; CPU TF baking) of the four built-in scenes. Bounds as for the
/// march alone.
#[test]
fn stylized_frames_match_the_cpu_on_the_builtin_scenes() {
    let Some(device) = device("the full-frame parity test") else {
        return;
    };
    for name in BUILTIN_SCENES {
        let mut scene = small(name);
        scene.style = stylized();
        let (gpu, cpu, times) = render_both(&device, &scene);
        if device.physical.timestamp_valid_bits > 0 {
            assert!(times.hole_filling.is_some() && times.ray_march.is_some());
            if gpu::silhouette::supported(&device) {
                assert!(times.silhouettes.is_some() && times.hole_creation.is_some());
                assert!(
                    !times.cpu_stages.contains(&"silhouettes and hole creation"),
                    "{:?}",
                    times.cpu_stages
                );
            }
            assert!(times.transfer_function.is_some());
            assert!(times.shadow_map.is_some() && times.camera_depth.is_some());
            assert!(
                !times.cpu_stages.contains(&"shadow map"),
                "{:?}",
                times.cpu_stages
            );
        }
        check_layers(&format!("frame {name}"), &gpu, &cpu, 0.05, 0.05);
    }
}

/// Σ|a − b| / Σ|b| over the volume's RGB, and over the visibility.
fn adaptive_errors(a: &Layers, b: &Layers) -> (f64, f64) {
    let (mut diff, mut total) = (0.0f64, 0.0f64);
    for (x, y) in a.volume.chunks(4).zip(b.volume.chunks(4)) {
        for k in 0..3 {
            diff += (x[k] as f64 - y[k] as f64).abs();
            total += (y[k] as f64).abs();
        }
    }
    (
        diff / total.max(1e-30),
        compare(&a.visibility, &b.visibility).0,
    )
}

/// Adaptive shading on the GPU (its own order: a coarse grid, then midpoints at steps 4
/// and 2, shading what disagrees) against shading every pixel: it shades a share of the
/// pixels, and moves the radiance and the visibility by at most 0.15% (their mean
/// relative error; 0.004–0.06% at 1080p). The views: the built-in scenes, a box medium,
/// an orthographic camera, 2×2 samples and ½ size. The CPU's adaptive shading of the same
/// frame is printed beside.
#[test]
fn adaptive_shading_stays_near_every_pixel_shaded() {
    let Some(device) = device("the adaptive-shading test") else {
        return;
    };
    let full = std::env::var_os("CREPUSCULAR_PARITY_FULL").is_some();
    let sized = |name: &str| {
        let mut scene = builtin_scene(name).unwrap();
        (scene.camera.width, scene.camera.height) = if full { (1920, 1080) } else { (256, 144) };
        scene.render.shadow_map_size = if full { 1024 } else { 256 };
        scene.render.method = Method::Prefiltered;
        scene
    };
    let mut views: Vec<(String, Scene)> = BUILTIN_SCENES
        .iter()
        .map(|name| (name.to_string(), sized(name)))
        .collect();
    let mut boxed = sized("torus");
    boxed.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::new(6.0, 5.0, 3.0),
            glam::Quat::from_rotation_z(0.3),
            glam::Vec3::new(0.0, 0.0, 2.0),
        ),
    };
    views.push(("torus in a box".into(), boxed));
    views.push(("tree orthographic".into(), orthographic(&sized("tree"))));
    let mut supersampled = sized("colonnade");
    supersampled.render.supersampling = 2;
    views.push(("colonnade 2×2 samples".into(), supersampled));
    let mut downsampled = sized("plane");
    downsampled.render.downsample = 2;
    views.push(("plane at ½ size".into(), downsampled));
    for (name, scene) in views {
        let render = |tolerance: f32, on_gpu: bool| {
            let mut scene = scene.clone();
            scene.render.adaptive_tolerance = tolerance;
            let geometry = FlatGeometry::from_scene(&scene);
            let frame = Frame::of_scene(&scene, &geometry);
            let control = RenderControl::new();
            if on_gpu {
                let (layers, times, _) =
                    gpu::frame::render_timed(&device, &frame, &control).unwrap();
                (layers, times)
            } else {
                render_timed_cpu(&frame, &control).unwrap()
            }
        };
        let tolerance = crepuscular::adaptive::DEFAULT_TOLERANCE;
        // Adaptive first: the device keeps released buffers, and the every-pixel frame's
        // layers left in them would pass for whatever pixels the refinement failed to write.
        let (gpu_adaptive, times) = render(tolerance, true);
        let (gpu_every, every_times) = render(0.0, true);
        let (cpu_every, _) = render(0.0, false);
        let (cpu_adaptive, cpu_times) = render(tolerance, false);
        let share = times.shaded_pixels as f64 / times.pixels as f64;
        let cpu_share = cpu_times.shaded_pixels as f64 / cpu_times.pixels as f64;
        let (radiance, visibility) = adaptive_errors(&gpu_adaptive, &gpu_every);
        let (cpu_radiance, cpu_visibility) = adaptive_errors(&cpu_adaptive, &cpu_every);
        eprintln!(
            "{name}: GPU shaded {:.1}%, radiance {:.4}% and visibility {:.4}% off; \
             CPU {:.1}%, {:.4}% and {:.4}%",
            100.0 * share,
            100.0 * radiance,
            100.0 * visibility,
            100.0 * cpu_share,
            100.0 * cpu_radiance,
            100.0 * cpu_visibility
        );
        assert_eq!(every_times.shaded_pixels, every_times.pixels);
        assert!(share > 1.0 / 16.0 && share < 0.75, "{name}: shaded {share}");
        assert!(
            radiance < 1.5e-3 && visibility < 1.5e-3,
            "{name}: {radiance}, {visibility}"
        );
        // Interpolated pixels keep their own depth.
        assert_eq!(gpu_adaptive.depth, gpu_every.depth, "{name}");
    }
}

/// The device keeps released buffers for the next frame, contents and all: no stage may
/// read what it did not write. A stylized prefiltered frame of tree, rendered on a device
/// of its own, comes out bit for bit the same after colonnade's frames have filled the
/// kept buffers with their data; and the device keeps what the frames released, no more
/// than its limit.
#[test]
fn kept_buffers_do_not_leak_into_the_next_frame() {
    let Some(shared) = device("the kept-buffer test") else {
        return;
    };
    let device = Device::new(DevicePolicy::Any).unwrap();
    assert_eq!(device.physical.name, shared.physical.name);
    assert_eq!(device.kept_buffer_bytes(), 0);
    let frame_of = |name: &str, method: Method| {
        let mut scene = small(name);
        scene.style = stylized();
        scene.render.method = method;
        let geometry = FlatGeometry::from_scene(&scene);
        let frame = Frame::of_scene(&scene, &geometry);
        gpu::frame::render_timed(&device, &frame, &RenderControl::new())
            .unwrap()
            .0
    };
    let first = frame_of("tree", Method::Prefiltered);
    let kept = device.kept_buffer_bytes();
    assert!(kept > 0, "the frame released no buffer to keep");
    frame_of("colonnade", Method::Prefiltered);
    frame_of("colonnade", Method::Reference);
    let again = frame_of("tree", Method::Prefiltered);
    let limit = gpu::buffer_pool::kept_bytes_limit(device.physical.device_local_bytes);
    assert!(device.kept_buffer_bytes() <= limit);
    for (layer, a, b) in [
        ("volume", &first.volume, &again.volume),
        ("visibility", &first.visibility, &again.visibility),
        ("depth", &first.depth, &again.depth),
    ] {
        let differing = a
            .iter()
            .zip(b.iter())
            .filter(|(x, y)| x.to_bits() != y.to_bits())
            .count();
        assert_eq!(differing, 0, "{layer}: {differing} values changed");
    }
}

/// The clock probe runs where the device has VK_KHR_shader_clock (lavapipe does), and
/// reads a positive, finite rate; its counter and timestamps agree on real GPUs only, so
/// the rate itself is checked against nothing here.
#[test]
fn the_clock_probe_reads_a_rate() {
    let Some(device) = device("the clock probe test") else {
        return;
    };
    if !gpu::clock::supported(&device) {
        eprintln!("skipping the clock probe test: no subgroup clock or no timestamps");
        return;
    }
    let rate = gpu::clock::measure(&device, gpu::clock::CHAIN_LINKS)
        .unwrap()
        .expect("a rate from a device with the clock");
    eprintln!("clock probe: {rate:.0} MHz");
    assert!(rate.is_finite() && rate > 0.0, "{rate}");
}

/// `auto` takes real GPUs only: whatever this machine has, the device it opens is never a
/// CPU implementation; and a list holding only lavapipe gives none.
#[test]
fn auto_never_picks_a_cpu_device() {
    use crepuscular::gpu::physical_device::choose_device;
    assert_eq!(
        choose_device(&[DeviceKind::Cpu], DevicePolicy::HardwareOnly),
        None
    );
    assert_eq!(
        choose_device(
            &[DeviceKind::Cpu, DeviceKind::Integrated],
            DevicePolicy::HardwareOnly
        ),
        Some(1)
    );
    match gpu::shared_device(DevicePolicy::HardwareOnly) {
        Ok(device) => assert_ne!(device.physical.kind, DeviceKind::Cpu),
        Err(err) => eprintln!("auto takes the CPU backend here: {err}"),
    }
}

/// Explicit `vulkan` without a usable driver renders on the CPU after exactly one message.
#[test]
fn a_missing_driver_falls_back_to_the_cpu_with_one_message() {
    let out = std::env::temp_dir().join(format!("crepuscular-fallback-{}.exr", std::process::id()));
    // The CLI built beside this test, or the one `CREPUSCULAR_CLI` names where the test
    // binary runs on another machine than it was built on.
    let cli = std::env::var_os("CREPUSCULAR_CLI")
        .unwrap_or_else(|| env!("CARGO_BIN_EXE_crepuscular").into());
    let output = std::process::Command::new(cli)
        .args([
            "render", "--scene", "torus", "--width", "32", "--height", "18", "--steps", "16",
        ])
        .args(["--sm-size", "64", "--backend", "vulkan", "--out"])
        .arg(&out)
        .env("VK_DRIVER_FILES", "/nonexistent/icd.json")
        .env("VK_ICD_FILENAMES", "/nonexistent/icd.json")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    let _ = std::fs::remove_file(&out);
    assert!(output.status.success(), "{stderr}");
    let messages = stderr.matches("rendering on the CPU instead").count();
    assert_eq!(messages, 1, "{stderr}");
}

/// A frame whose filtered basis is larger than the device's storage-buffer range (a
/// 1080p frame at M = 64 in f32: about 200 MiB, against lavapipe's 128 MiB) is refused
/// with an error that says so, and rendering it with `vulkan` asked for gives the CPU
/// backend's layers. Devices whose range holds it skip.
#[test]
fn a_basis_past_the_storage_range_falls_back_to_the_cpu() {
    let Some(device) = device("the storage-range fallback test") else {
        return;
    };
    let mut scene = builtin_scene("tree").unwrap();
    scene.render.method = Method::Prefiltered;
    scene.render.bases = 64;
    scene.render.basis_storage = BasisStorage::F32;
    scene.render.backend = Backend::Vulkan;
    let geometry = FlatGeometry::from_scene(&scene);
    let frame = Frame::of_scene(&scene, &geometry);
    let control = RenderControl::new();
    match gpu::frame::render_timed(&device, &frame, &control) {
        Ok(_) => {
            eprintln!(
                "skipping the storage-range fallback test: {} bytes of range hold the basis",
                device.physical.max_storage_buffer_range
            );
            return;
        }
        Err(Error::Gpu(GpuError::Unsupported(reason))) => {
            assert!(reason.contains("storage-buffer range"), "{reason}");
        }
        Err(other) => panic!("{other}"),
    }
    let fallen_back = crepuscular::render(&frame, &control).unwrap();
    let (cpu, _) = render_timed_cpu(&frame, &control).unwrap();
    assert!(
        fallen_back.volume == cpu.volume
            && fallen_back.visibility == cpu.visibility
            && fallen_back.depth == cpu.depth
    );
}

/// The frame's rectified map of a scene and the prefix-sum plan prefiltering builds on it.
fn prefix_plan(scene: &Scene) -> PrefixPlan {
    let camera = CameraModel::new(&scene.camera);
    let geometry = FlatGeometry::from_scene(scene);
    let shadow = ShadowMap::of_scene_geometry(scene, &camera, &geometry).unwrap();
    let light_travel = scene.sun.direction.as_dvec3().normalize();
    let map = EpipolarMap::rectify(
        &camera,
        &shadow,
        &geometry.view(),
        light_travel,
        scene.render.max_distance as f64,
        scene.render.rectification,
        &RectifyDesc::prefiltered(scene.render.epipolar_slices),
    )
    .unwrap()
    .expect("the built-in views can be rectified");
    let epipoles: Vec<[f64; 2]> = epipoles_in_image(&camera, &shadow, f64::INFINITY).collect();
    Prefiltered::prefix_plan(
        &map,
        &camera,
        &epipoles,
        &PrefilteredDesc::from_settings(&scene.render),
        &scene.sun,
        &scene.medium,
    )
    .expect("memory for the plan")
}

/// Prefiltering's basis computation and prefix sums. The GPU sums each band in runs side
/// by side, each run in the CPU's order without contraction, and adds the runs before it:
/// the same sums in another order, so values differ by rounding. Both are held to the exact
/// means (summed in f64): the GPU's values may lie no farther from them than the CPU's
/// farthest plus one snorm16 step, and no farther on average than the CPU's (+10%).
/// Comparing the two directly failed at full size: the CPU's one serial chain per band
/// drifts further (colonnade at 1080p: CPU up to 5.5e-5 from the exact f32 means, GPU
/// 2.9e-6), so they differed by two snorm16 steps where the GPU was the closer.
#[test]
fn prefix_sums_match_the_cpu() {
    let Some(device) = device("the prefix-sum parity test") else {
        return;
    };
    let gpu_sums = gpu::prefix::GpuPrefixSums::new(&device);
    for name in BUILTIN_SCENES {
        for (storage, bases) in [(BasisStorage::Snorm16, 32), (BasisStorage::F32, 16)] {
            let mut scene = small(name);
            scene.render.method = Method::Prefiltered;
            scene.render.basis_storage = storage;
            scene.render.bases = bases;
            let plan = prefix_plan(&scene);
            let values = |basis: FilteredBasis| -> Vec<f32> {
                match basis {
                    FilteredBasis::Snorm16(v) => v.iter().map(|&x| x as f32 / 32767.0).collect(),
                    FilteredBasis::F32(v) => v,
                }
            };
            let cpu = values(CpuPrefixSums.prefix_sums(&plan).unwrap());
            let gpu = values(gpu_sums.prefix_sums(&plan).unwrap());
            assert_eq!(gpu.len(), plan.total_rows * plan.stride);
            let exact = exact_prefix_means(&plan);
            let differing = gpu.iter().zip(&cpu).filter(|(g, c)| g != c).count();
            let (mean_relative, max) = compare(&gpu, &cpu);
            let (gpu_mean, gpu_max) = distance_to(&gpu, &exact);
            let (cpu_mean, cpu_max) = distance_to(&cpu, &exact);
            eprintln!(
                "prefix sums {name} {storage:?} M={bases}: {differing} of {} values differ, \
                 mean relative error {mean_relative:.2e}, max abs error {max:.2e}; from the \
                 exact means: GPU mean {gpu_mean:.3e} max {gpu_max:.3e}, CPU mean \
                 {cpu_mean:.3e} max {cpu_max:.3e}",
                gpu.len()
            );
            assert!(
                mean_relative <= 1e-3,
                "{name} {storage:?}: {mean_relative:.3e}"
            );
            let step = match storage {
                BasisStorage::Snorm16 => 1.0 / 32767.0,
                BasisStorage::F32 => 0.0,
            };
            assert!(
                gpu_max <= cpu_max + step + 1e-6,
                "{name} {storage:?}: the GPU's values lie up to {gpu_max:.3e} from the exact \
                 means, the CPU's up to {cpu_max:.3e}"
            );
            assert!(
                gpu_mean <= cpu_mean * 1.1 + 1e-7,
                "{name} {storage:?}: the GPU's values lie {gpu_mean:.3e} from the exact means \
                 on average, the CPU's {cpu_mean:.3e}"
            );
        }
    }
}

/// The prefix sums in f64 with the plan's inputs (PrefixPlan's documentation): the exact
/// weighted means both backends round.
fn exact_prefix_means(plan: &PrefixPlan) -> Vec<f64> {
    let stride = plan.stride;
    let per_row = plan.samples_per_row;
    let mut means = vec![0.0; plan.total_rows * stride];
    for (index, band) in plan.bands.iter().enumerate() {
        let mut sums = vec![0.0f64; stride];
        for i in 0..band.rows - 1 {
            let k = band.sample_offset(index) + i;
            for n in k * per_row..(k + 1) * per_row {
                let row = &plan.table[plan.entries[n] as usize * stride..][..stride];
                for (sum, &value) in sums.iter_mut().zip(row) {
                    *sum += plan.weights[n] as f64 * value as f64;
                }
            }
            let out = &mut means[(band.first_row + 1 + i) * stride..][..stride];
            for (mean, sum) in out.iter_mut().zip(&sums) {
                *mean = sum * plan.scales[k] as f64;
            }
        }
    }
    means
}

/// (mean, max) absolute distance of `values` from `exact`.
fn distance_to(values: &[f32], exact: &[f64]) -> (f64, f64) {
    let (total, max) = values
        .iter()
        .zip(exact)
        .map(|(&v, &e)| (v as f64 - e).abs())
        .fold((0.0, 0.0f64), |(total, max), d| (total + d, max.max(d)));
    (total / values.len().max(1) as f64, max)
}

/// Whole prefiltered frames with the prefix sums on the GPU (planning and per-pixel
/// evaluation on the CPU): the same bounds as the march.
#[test]
fn prefiltered_frames_match_the_cpu_on_the_builtin_scenes() {
    let Some(device) = device("the prefiltered-frame parity test") else {
        return;
    };
    for name in BUILTIN_SCENES {
        let mut scene = small(name);
        scene.render.method = Method::Prefiltered;
        let (gpu, cpu, times) = render_both(&device, &scene);
        if device.physical.timestamp_valid_bits > 0 {
            assert!(times.prefix_sums.is_some() && times.prefiltered.is_some());
        }
        check_layers(&format!("prefiltered {name}"), &gpu, &cpu, 0.05, 0.05);
    }
    let mut anamorphic = small("tree");
    anamorphic.render.method = Method::Prefiltered;
    anamorphic.camera.pixel_aspect = 0.5;
    anamorphic.camera.width *= 2;
    let (gpu, cpu, _) = render_both(&device, &anamorphic);
    check_layers("prefiltered tree, pixels 1:2", &gpu, &cpu, 0.05, 0.05);
    let mut windowed = small("colonnade");
    windowed.render.method = Method::Prefiltered;
    let (width, height) = (windowed.camera.width, windowed.camera.height);
    windowed.camera.window = Some(crepuscular::scene::PixelWindow {
        x: width / 5,
        y: height / 3,
        width: width / 2 + 1,
        height: height / 2 + 1,
    });
    let (gpu, cpu, _) = render_both(&device, &windowed);
    assert_eq!((gpu.width, gpu.height), (width / 2 + 1, height / 2 + 1));
    check_layers("prefiltered colonnade, a window", &gpu, &cpu, 0.05, 0.05);
}

/// A nearly black frame (`plane` in fog of 0.6 /m under a dilated silhouette; see
/// `fast_methods::nearly_black_rays_keep_the_light_from_far_along`): the probe finds it
/// dark on the CPU, and the GPU's walks go on past e^−10 as the CPU's do. Without that,
/// the GPU frame read 13–14% dark against the reference.
#[test]
fn a_nearly_dark_frame_walks_on_as_on_the_cpu() {
    let Some(device) = device("the nearly dark frame's parity test") else {
        return;
    };
    let mut scene = Scene::from_json(include_str!("data/nearly_black_plane.json")).unwrap();
    scene.camera.width = 192;
    scene.camera.height = 108;
    scene.render.adaptive_tolerance = 0.0;
    check_both_against_the_reference(&device, scene, "nearly dark frame", 0.03);
}

/// `scene` on the GPU and the CPU, each within `bound` of the reference at 4096 steps
/// ([`radiance_error`]) and both within the usual bounds of each other.
fn check_both_against_the_reference(
    device: &Arc<Device>,
    mut scene: Scene,
    label: &str,
    bound: f64,
) {
    let (gpu, cpu, _) = render_both(device, &scene);
    scene.render.method = Method::Reference;
    scene.render.steps = 4096;
    let geometry = FlatGeometry::from_scene(&scene);
    let frame = Frame::of_scene(&scene, &geometry);
    let (reference, _) = render_timed_cpu(&frame, &RenderControl::new()).unwrap();
    let (gpu_off, cpu_off) = (
        radiance_error(&gpu, &reference),
        radiance_error(&cpu, &reference),
    );
    println!("{label} against the reference: GPU {gpu_off:.4}, CPU {cpu_off:.4}");
    assert!(
        gpu_off < bound && cpu_off < bound,
        "{label}: GPU {gpu_off}, CPU {cpu_off}"
    );
    check_layers(label, &gpu, &cpu, 0.05, 0.05);
}

/// `plane`'s roof dilated along the view rays in a thin fog box
/// (`common::dilated_roof_in_a_thin_box`): rays passing just by a slat are decided by the
/// series' blur all along its extrusion, and the GPU declines and walks them as the CPU
/// does. Without that, its frame read 8% dark against the reference.
#[test]
fn rays_decided_by_the_blur_are_walked_as_on_the_cpu() {
    let Some(device) = device("the blurred lookups' parity test") else {
        return;
    };
    let mut scene = builtin_scene("plane").unwrap();
    (scene.camera.width, scene.camera.height) = (384, 216);
    dilated_roof_in_a_thin_box(&mut scene);
    check_both_against_the_reference(&device, scene, "blurred lookups", 0.01);
}

/// Prefiltered evaluation across layouts and storage: a `box` medium, forced epipolar and
/// projective rectification, f32 storage at M = 16, an orthographic camera (parallel
/// slices), and 2×2 supersampling. Bounds as for the march.
#[test]
fn prefiltered_evaluation_matches_across_layouts() {
    let Some(device) = device("the prefiltered-layout parity test") else {
        return;
    };
    let prefiltered = |name: &str| {
        let mut scene = small(name);
        scene.render.method = Method::Prefiltered;
        scene
    };
    let mut variants = Vec::new();
    let mut boxed = prefiltered("torus");
    boxed.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::new(6.0, 5.0, 3.0),
            glam::Quat::from_rotation_z(0.3),
            glam::Vec3::new(0.0, 0.0, 2.0),
        ),
    };
    // Exact ray ends, by default in a box: rays ending inside it close in on their surface
    // in their last piece.
    variants.push(("torus in a box", boxed.clone()));
    let mut boxed_looked_up = boxed;
    boxed_looked_up.render.exact_ray_ends = ExactRayEnds::Off;
    variants.push(("torus in a box, exact ray ends off", boxed_looked_up));
    // Aligned with the axes: torus's sun has no x component, so it grazes the x walls.
    let mut aligned = prefiltered("torus");
    aligned.medium.extinction = 0.2;
    aligned.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_translation(glam::Vec3::new(0.0, 0.0, 4.0))
            * glam::Mat4::from_scale(glam::Vec3::new(3.5, 3.8, 4.0)),
    };
    variants.push(("torus in an aligned box", aligned));
    let mut epipolar = prefiltered("colonnade");
    epipolar.render.rectification = Rectification::Epipolar;
    epipolar.render.basis_storage = BasisStorage::F32;
    epipolar.render.bases = 16;
    variants.push(("colonnade epipolar f32 M=16", epipolar));
    let mut projective = prefiltered("torus");
    projective.render.rectification = Rectification::Projective;
    variants.push(("torus projective", projective.clone()));
    // The exact ends read the rectified map on the GPU too: rays' keys sit on the warps'
    // knots, and a width taken from the warp's slope there differed between f32 and f64.
    let mut exact_ends = projective;
    exact_ends.render.exact_ray_ends = ExactRayEnds::On;
    variants.push(("torus projective, exact ray ends", exact_ends));
    let mut grazing = prefiltered("plane");
    grazing.render.exact_ray_ends = ExactRayEnds::On;
    variants.push(("plane, exact ray ends", grazing));
    let mut orthographic = prefiltered("plane");
    orthographic.camera.projection = Projection::orthographic(30.0);
    variants.push(("plane orthographic", orthographic));
    // Looking up out of a box of fog: the stretches inside it are too short for the
    // prefix sums, and most rays take the exact walk through the box.
    let mut out_of_fog = prefiltered("colonnade");
    let eye = glam::Vec3::new(-2.73, 12.76, 5.38);
    let looking = glam::Vec3::new(-0.17, -0.09, 0.98);
    let (width, height) = (out_of_fog.camera.width, out_of_fog.camera.height);
    out_of_fog.camera = Camera::orthographic_looking_at(eye, eye + looking, 21.0, width, height);
    out_of_fog.sun.direction = glam::Vec3::new(0.22, -0.02, -0.97);
    out_of_fog.medium.extinction = 0.2;
    out_of_fog.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_translation(glam::Vec3::new(2.5, 2.4, 3.6))
            * glam::Mat4::from_scale(glam::Vec3::new(11.0, 7.0, 3.0)),
    };
    variants.push(("colonnade looking up out of a box", out_of_fog));
    // Orthographic, 6.7° off the light with the sun behind: every ray is walked.
    let mut along = prefiltered("plane");
    let eye = glam::Vec3::new(-8.23, 12.73, 7.47);
    let looking = glam::Vec3::new(-0.165, 0.706, -0.688);
    along.camera = Camera::orthographic_looking_at(eye, eye + looking, 11.05, width, height);
    along.sun.direction = glam::Vec3::new(-0.063, 0.728, -0.682);
    along.render.max_distance = 30.0;
    variants.push(("plane nearly along the light", along));
    // Dense fog towards the sun: rays crossing few texels within their first optical depth
    // are walked, the others looked up.
    let mut dense = prefiltered("colonnade");
    dense.medium.extinction = 0.6;
    variants.push(("colonnade in dense fog", dense));
    // A box 10 cm across through a long lens from 15 m: the epipole lies far off the map,
    // and slices start where they enter it (the spacing's first sample is past zero).
    let mut small_box = prefiltered("torus");
    small_fog_box_far_off(&mut small_box);
    variants.push(("a small box far off", small_box));
    // A camera inside a box without the near-plane correction: in a box the stretch before
    // the clip plane is subtracted all the same.
    let mut inside = prefiltered("plane");
    camera_inside_a_fog_box(&mut inside);
    variants.push(("a camera inside a box, near plane uncorrected", inside));
    let mut supersampled = prefiltered("tree");
    supersampled.render.supersampling = 2;
    variants.push(("tree 2×2 samples", supersampled));
    for (label, scene) in variants {
        let (gpu, cpu, times) = render_both(&device, &scene);
        if device.physical.timestamp_valid_bits > 0 {
            assert!(
                times.prefiltered.is_some(),
                "{label}: not evaluated on the GPU"
            );
        }
        check_layers(&format!("prefiltered {label}"), &gpu, &cpu, 0.05, 0.05);
    }
}

/// Joint-bilateral upsampling alone, on low-resolution samples of CPU-rendered layers
/// (every second and fourth pixel) guided by their full-size depth, and again with an
/// opacity guide: the same arithmetic in f32, so max abs error 1e-5 of the peak radiance
/// and 1e-5 in visibility.
#[test]
fn upsampling_matches_the_cpu() {
    let Some(device) = device("the upsampling parity test") else {
        return;
    };
    for name in BUILTIN_SCENES {
        let scene = small(name);
        let geometry = FlatGeometry::from_scene(&scene);
        let frame = Frame::of_scene(&scene, &geometry);
        let (full, _) = render_timed_cpu(&frame, &RenderControl::new()).unwrap();
        for factor in [2, 4] {
            let low = upsample::samples_of(&full, factor);
            let cpu =
                upsample::joint_bilateral(&low, &full.depth, None, full.width, full.height, factor)
                    .unwrap();
            let (gpu, _) = gpu::upsample::joint_bilateral(
                &device,
                &low,
                &full.depth,
                None,
                full.width,
                full.height,
                factor,
            )
            .unwrap();
            check_layers(
                &format!("upsampling {name} 1/{factor}"),
                &gpu,
                &cpu,
                1e-5,
                1e-5,
            );
            // Guided by the exact opacity where the samples' opacities spread (at depth
            // edges here, where the fog's opacity changes with its length).
            let (width, height) = (full.width, full.height);
            let guide = upsample::opacity_guide(&low, width, height, factor, |x, y| {
                full.volume[((y * width + x) * 4 + 3) as usize]
            })
            .unwrap()
            .expect("samples whose opacities spread");
            assert!(guide.iter().any(|&o| o >= 0.0), "{name}: nothing guided");
            let cpu =
                upsample::joint_bilateral(&low, &full.depth, Some(&guide), width, height, factor)
                    .unwrap();
            let (gpu, _) = gpu::upsample::joint_bilateral(
                &device,
                &low,
                &full.depth,
                Some(&guide),
                width,
                height,
                factor,
            )
            .unwrap();
            check_layers(
                &format!("opacity-guided upsampling {name} 1/{factor}"),
                &gpu,
                &cpu,
                1e-5,
                1e-5,
            );
        }
    }
}

/// A downsampled prefiltered frame: evaluation and upsampling on the GPU.
#[test]
fn downsampled_prefiltered_frames_match_the_cpu() {
    let Some(device) = device("the downsampled prefiltered parity test") else {
        return;
    };
    let mut boxed = small("torus");
    boxed.medium.extinction = 0.6;
    boxed.medium.extent = Extent::Box {
        world_from_cube: glam::Mat4::from_scale_rotation_translation(
            glam::Vec3::new(3.0, 2.5, 2.0),
            glam::Quat::from_rotation_z(0.6),
            glam::Vec3::new(1.5, -1.0, 2.5),
        ),
    };
    // In a box, upsampling also takes an opacity guide at the box's silhouette.
    let scenes = [
        ("torus", small("torus")),
        ("colonnade", small("colonnade")),
        ("torus in a dense box", boxed),
    ];
    for (name, mut scene) in scenes {
        scene.render.method = Method::Prefiltered;
        scene.render.downsample = 2;
        let (gpu, cpu, times) = render_both(&device, &scene);
        if device.physical.timestamp_valid_bits > 0 {
            assert!(times.upsampling.is_some());
        }
        check_layers(
            &format!("prefiltered {name} at 1/2"),
            &gpu,
            &cpu,
            0.05,
            0.05,
        );
    }
}

/// Epipolar rectification alone, for prefiltering's and min-max's sample densities. The
/// GPU places samples in f32: a sample centre within ~1e-4 texel of a texel edge may read
/// the neighbouring texel, so at most 0.2% of samples may differ beyond 1e-3 relative;
/// every other value agrees to 1e-3 relative, and unoccluded (+∞) samples exactly.
#[test]
fn rectification_matches_the_cpu() {
    let Some(device) = device("the rectification parity test") else {
        return;
    };
    let resampler = gpu::rectify::GpuResampler::new(&device);
    for name in BUILTIN_SCENES {
        let scene = small(name);
        let camera = CameraModel::new(&scene.camera);
        let shadow = ShadowMap::of_scene(&scene, &camera).unwrap();
        for desc in [RectifyDesc::prefiltered(0), RectifyDesc::min_max(0)] {
            let cpu = EpipolarMap::build(&camera, &shadow, &desc)
                .expect("memory for the map")
                .expect("rectifiable view");
            let gpu = EpipolarMap::build_with(&camera, &shadow, &desc, &resampler)
                .unwrap()
                .expect("rectifiable view");
            assert_eq!(gpu.values.len(), cpu.values.len());
            let mut differing = 0;
            for (&g, &c) in gpu.values.iter().zip(&cpu.values) {
                if c.is_infinite() || g.is_infinite() {
                    differing += (g != c) as usize;
                } else if (g - c).abs() > 1e-3 * c.abs().max(1.0) {
                    differing += 1;
                }
            }
            let total = cpu.values.len();
            eprintln!(
                "rectification {name} {}×{}: {differing} of {total} samples differ",
                cpu.slices, cpu.samples
            );
            assert!(differing * 500 <= total, "{name}: {differing} of {total}");
        }
    }
}

/// How a GPU depth target differs from the CPU's.
#[derive(Debug, Default)]
struct RasterParity {
    samples: usize,
    /// Samples covered by one target only, or by different objects (shadow map).
    id_mismatches: usize,
    /// Samples covered by both (by the same object, where there are ids) whose depths
    /// differ by more than `DEPTH_BOUND` of the depth range.
    depth_mismatches: usize,
    /// The largest depth difference where both cover a sample with the same object,
    /// relative to the depth range.
    max_depth_error: f64,
    /// The same, over samples off every edge.
    max_interior_error: f64,
    /// Mismatching samples that are not on an edge.
    off_edge: usize,
}

/// Depth agreement bound where both targets cover a sample, relative to the depth range.
const DEPTH_BOUND: f64 = 1e-4;

/// How far (in pixels) the geometry moves to find the samples on edges: four times the
/// 1/256-pixel snapping grid, well above the f32 vertex transform's error (~1e-4 pixel).
const EDGE_SHIFT: f64 = 1.0 / 64.0;

/// The CPU's target, and the same with the geometry moved by ±`EDGE_SHIFT` along x and y.
fn cpu_targets(
    geometry: &crepuscular::Geometry,
    pixel_from_world: &glam::DMat4,
    desc: &crepuscular::raster::RasterDesc,
) -> (DepthTarget, Vec<DepthTarget>) {
    let shifted = [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]
        .into_iter()
        .map(|(dx, dy)| {
            let shift = glam::DMat4::from_cols(
                glam::DVec4::X,
                glam::DVec4::Y,
                glam::DVec4::Z,
                glam::DVec4::new(dx * EDGE_SHIFT, dy * EDGE_SHIFT, 0.0, 1.0),
            );
            rasterize(geometry, &(shift * *pixel_from_world), desc).unwrap()
        })
        .collect();
    (
        rasterize(geometry, pixel_from_world, desc).unwrap(),
        shifted,
    )
}

/// Compares targets sample by sample. A sample is on an edge when moving the geometry by
/// `EDGE_SHIFT` changes the CPU's own result there: its object or coverage, or its depth
/// by more than `DEPTH_BOUND` (a depth discontinuity, such as overlapping leaves of one
/// mesh, or a surface so steep that sub-pixel snapping moves its depth that much).
fn raster_parity(gpu: &DepthTarget, cpu: &DepthTarget, shifted: &[DepthTarget]) -> RasterParity {
    assert_eq!((gpu.width, gpu.height), (cpu.width, cpu.height));
    let finite = cpu.depth.iter().filter(|d| d.is_finite());
    let (low, high) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &d| {
        (l.min(d as f64), h.max(d as f64))
    });
    let range = (high - low).max(1e-9);
    let with_ids = !gpu.ids.is_empty();
    // The object at a sample, or only whether it is covered for a depth-only target.
    let object = |target: &DepthTarget, i: usize| match target.depth[i].is_finite() {
        false => None,
        true if with_ids => Some(target.ids[i]),
        true => Some(0),
    };
    let depth_error = |a: f32, b: f32| (a as f64 - b as f64).abs() / range;
    let on_edge = |i: usize| {
        shifted.iter().any(|moved| {
            object(moved, i) != object(cpu, i)
                || (cpu.depth[i].is_finite()
                    && depth_error(moved.depth[i], cpu.depth[i]) > DEPTH_BOUND)
        })
    };
    let mut parity = RasterParity {
        samples: cpu.depth.len(),
        ..Default::default()
    };
    for i in 0..cpu.depth.len() {
        let (g, c) = (gpu.depth[i], cpu.depth[i]);
        if with_ids {
            assert_eq!(gpu.ids[i] == NO_OBJECT, g.is_infinite(), "sample {i}");
        }
        let mismatch = if object(gpu, i) != object(cpu, i) {
            parity.id_mismatches += 1;
            true
        } else if c.is_finite() {
            let error = depth_error(g, c);
            parity.max_depth_error = parity.max_depth_error.max(error);
            if !on_edge(i) {
                parity.max_interior_error = parity.max_interior_error.max(error);
            }
            parity.depth_mismatches += usize::from(error > DEPTH_BOUND);
            error > DEPTH_BOUND
        } else {
            false
        };
        if mismatch && !on_edge(i) {
            parity.off_edge += 1;
        }
    }
    parity
}

/// Asserts `RasterParity`'s bounds: ids (and coverage) agree on ≥ 99.9% of samples, depth
/// within `DEPTH_BOUND` of the range on ≥ 99.9% of the samples both cover, and every
/// mismatch lies on an edge.
fn check_raster(label: &str, parity: &RasterParity) {
    let fraction = |count: usize| count as f64 / parity.samples as f64;
    eprintln!(
        "{label}: ids differ on {} of {} samples ({:.1e}), depth beyond {DEPTH_BOUND:.0e} on {} \
         ({:.1e}); max depth error {:.2e} of the range ({:.2e} off edges); {} mismatches off edges",
        parity.id_mismatches,
        parity.samples,
        fraction(parity.id_mismatches),
        parity.depth_mismatches,
        fraction(parity.depth_mismatches),
        parity.max_depth_error,
        parity.max_interior_error,
        parity.off_edge,
    );
    assert!(
        fraction(parity.id_mismatches) <= 1e-3,
        "{label}: {parity:?}"
    );
    assert!(
        fraction(parity.depth_mismatches) <= 1e-3,
        "{label}: {parity:?}"
    );
    assert!(
        parity.max_interior_error <= DEPTH_BOUND,
        "{label}: {parity:?}"
    );
    assert_eq!(parity.off_edge, 0, "{label}: {parity:?}");
}

/// The shadow map's depth pass against the CPU rasterizer on the four built-in scenes at
/// their own 1024² size. Measured on lavapipe: ids differ on at most 1 texel in 10⁶
/// (`tree`), always on an edge; depth agrees within 1.5e-5 of the range off edges, and
/// within 2.8e-4 anywhere both maps hold the same object (on edges: overlapping leaves,
/// the plane's steep sides), beyond 1e-4 on at most 6e-5 of the texels.
#[test]
fn shadow_maps_match_the_cpu_rasterizer() {
    let Some(device) = device("the shadow-map raster parity test") else {
        return;
    };
    let rasterizer = gpu::raster::GpuRasterizer::shadow_map(&device);
    for name in BUILTIN_SCENES {
        let scene = builtin_scene(name).unwrap();
        let camera = CameraModel::new(&scene.camera);
        let geometry = FlatGeometry::from_scene(&scene);
        let cpu = ShadowMap::of_scene_geometry(&scene, &camera, &geometry).unwrap();
        let gpu = ShadowMap::build_with(
            &camera,
            &scene.sun,
            &scene.medium,
            &scene.render,
            &geometry.view(),
            &rasterizer,
        )
        .unwrap();
        assert_eq!(gpu.texel_from_world, cpu.texel_from_world);
        if device.physical.timestamp_valid_bits > 0 {
            assert!(rasterizer.milliseconds().is_some());
        }
        let desc = crepuscular::raster::RasterDesc::orthographic(cpu.size, cpu.size);
        let (target, shifted) = cpu_targets(&geometry.view(), &cpu.texel_from_world, &desc);
        assert_eq!((&target.depth, &target.ids), (&cpu.depth, &cpu.ids));
        let gpu = DepthTarget {
            width: gpu.size,
            height: gpu.size,
            depth: gpu.depth,
            ids: gpu.ids,
        };
        let parity = raster_parity(&gpu, &target, &shifted);
        check_raster(&format!("shadow map {name} {}²", cpu.size), &parity);
    }
}

/// The camera's depth pass against the CPU rasterizer: pinhole (w, clipped at near and
/// far) and orthographic (planar depth in the clip range) cameras, 1 and 2×2 samples per
/// pixel, at 640×360. Measured on lavapipe: coverage differs on at most 9e-6 of the samples,
/// always on an edge; depth agrees within 3.8e-5 of the range off edges; on edges (a
/// column or leaf in front of another surface of the same coverage) up to 3e-2, beyond
/// 1e-4 on at most 7e-4 of the samples (`tree`, pinhole, 1×1).
#[test]
fn camera_depth_matches_the_cpu_rasterizer() {
    let Some(device) = device("the camera-depth raster parity test") else {
        return;
    };
    let rasterizer = gpu::raster::GpuRasterizer::camera_depth(&device);
    for name in BUILTIN_SCENES {
        let mut scene = builtin_scene(name).unwrap();
        scene.camera.width = 640;
        scene.camera.height = 360;
        let mut orthographic = scene.clone();
        orthographic.camera.projection = Projection::orthographic(30.0);
        let geometry = FlatGeometry::from_scene(&scene);
        for (kind, scene) in [("pinhole", &scene), ("orthographic", &orthographic)] {
            let camera = CameraModel::new(&scene.camera);
            for ss in [1, 2] {
                let (pixel_from_world, desc) = camera_raster(&camera, ss);
                let (cpu, shifted) = cpu_targets(&geometry.view(), &pixel_from_world, &desc);
                let gpu = rasterizer
                    .rasterize(&geometry.view(), &pixel_from_world, &desc)
                    .unwrap();
                assert!(gpu.ids.is_empty(), "a depth-only pass");
                let parity = raster_parity(&gpu, &cpu, &shifted);
                check_raster(&format!("camera depth {name} {kind} {ss}×{ss}"), &parity);
            }
        }
    }
}

/// Coverage and id mismatches between two depth targets, as fractions of the samples.
fn coverage_mismatches(gpu: &DepthTarget, cpu: &DepthTarget) -> (f64, f64) {
    let samples = cpu.depth.len() as f64;
    let coverage = gpu
        .depth
        .iter()
        .zip(&cpu.depth)
        .filter(|(g, c)| g.is_finite() != c.is_finite())
        .count();
    let ids = gpu.ids.iter().zip(&cpu.ids).filter(|(g, c)| g != c).count();
    (coverage as f64 / samples, ids as f64 / samples)
}

/// Every triangle of `tree` cut by a checker of 1 m squares in world x and y (its texture
/// coordinates), in the shadow map and in a pinhole and an orthographic camera's depth:
/// the GPU's cut passes against the CPU rasterizer. Measured on lavapipe: coverage differs
/// on 1.9e-6 of the shadow map's texels and ids on 3.8e-6 (where f32 coordinates round to
/// the other side of a square's edge), and nowhere in the cameras' depth; the checker
/// itself removes 35% of the map's texels and 7% and 20% of the cameras' samples. Then the
/// triangles take turns among six masks of one uneven 3×2 texture, each read with another
/// wrap and filter (the clipped one past a border of alpha 1).
#[test]
fn alpha_cut_triangles_match_the_cpu_rasterizer() {
    use crepuscular::cutout::{AlphaMask, MaskFilter, Wrap};
    let Some(device) = device("the alpha-cut raster parity test") else {
        return;
    };
    let mut scene = builtin_scene("tree").unwrap();
    scene.camera.width = 640;
    scene.camera.height = 360;
    let flat = FlatGeometry::from_scene(&scene);
    let origin = flat.origin;
    let uvs: Vec<[f32; 2]> = flat
        .positions
        .iter()
        .map(|p| {
            let (x, y) = (p[0] as f64 + origin.x, p[1] as f64 + origin.y);
            [(x / 2.0) as f32, (y / 2.0) as f32]
        })
        .collect();
    let checker: Vec<f32> = (0..4).map(|k| ((k % 2 + k / 2) % 2) as f32).collect();
    let uneven = [0.0, 1.0, 0.3, 1.0, 0.8, 0.0];
    let sampled = |wrap: [Wrap; 2], filter| AlphaMask {
        wrap,
        filter,
        ..AlphaMask::repeating(3, 2, std::borrow::Cow::Borrowed(&uneven), 0.5)
    };
    let checkers = [AlphaMask::repeating(
        2,
        2,
        std::borrow::Cow::Borrowed(&checker),
        0.5,
    )];
    let sampling = [
        sampled([Wrap::Repeat; 2], MaskFilter::Linear),
        sampled([Wrap::Extend; 2], MaskFilter::Linear),
        sampled([Wrap::Mirror; 2], MaskFilter::Linear),
        AlphaMask {
            border: 1.0,
            ..sampled([Wrap::Clip; 2], MaskFilter::Linear)
        },
        sampled([Wrap::Mirror, Wrap::Clip], MaskFilter::Closest),
        sampled([Wrap::Repeat, Wrap::Extend], MaskFilter::Closest),
    ];
    for (masks, kind) in [
        (&checkers[..], "checker"),
        (&sampling[..], "wrap and filter"),
    ] {
        alpha_cuts_match(&device, &scene, &flat, &uvs, masks, kind);
    }
}

/// [`alpha_cut_triangles_match_the_cpu_rasterizer`] for one set of masks, which the
/// triangles take in turn.
fn alpha_cuts_match(
    device: &Arc<Device>,
    scene: &crepuscular::scene::Scene,
    flat: &FlatGeometry,
    uvs: &[[f32; 2]],
    masks: &[crepuscular::cutout::AlphaMask<'_>],
    kind: &str,
) {
    use crepuscular::cutout::Cutouts;
    let triangle_masks: Vec<u32> = (0..flat.triangles.len())
        .map(|k| (k % masks.len()) as u32)
        .collect();
    let geometry = crepuscular::render::Geometry {
        cutouts: Some(Cutouts {
            uvs,
            triangle_masks: &triangle_masks,
            masks,
        }),
        ..flat.view()
    };
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene_geometry(scene, &camera, flat).unwrap();
    let map_desc = crepuscular::raster::RasterDesc::orthographic(shadow.size, shadow.size);
    let mut orthographic = scene.clone();
    orthographic.camera.projection = Projection::orthographic(30.0);
    let mut targets = vec![("shadow map", shadow.texel_from_world, map_desc, true)];
    for (projection, scene) in [("pinhole", scene), ("orthographic", &orthographic)] {
        let (pixel_from_world, desc) = camera_raster(&CameraModel::new(&scene.camera), 1);
        targets.push((projection, pixel_from_world, desc, false));
    }
    for (label, pixel_from_world, desc, ids) in targets {
        let rasterizer = match ids {
            true => gpu::raster::GpuRasterizer::shadow_map(device),
            false => gpu::raster::GpuRasterizer::camera_depth(device),
        };
        let cpu = rasterize(&geometry, &pixel_from_world, &desc).unwrap();
        let gpu = rasterizer
            .rasterize(&geometry, &pixel_from_world, &desc)
            .unwrap();
        let opaque = rasterize(&flat.view(), &pixel_from_world, &desc).unwrap();
        let (cut_away, _) = coverage_mismatches(&cpu, &opaque);
        let (coverage, id_errors) = coverage_mismatches(&gpu, &cpu);
        println!("{kind}, {label}: the masks remove {cut_away:.3}; coverage {coverage:.2e}, ids {id_errors:.2e}");
        assert!(
            cut_away > 0.05,
            "{kind}, {label}: the masks cut nothing ({cut_away})"
        );
        assert!(
            coverage <= 1e-4,
            "{kind}, {label}: coverage differs on {coverage}"
        );
        assert!(
            id_errors <= 1e-4,
            "{kind}, {label}: ids differ on {id_errors}"
        );
    }
}
