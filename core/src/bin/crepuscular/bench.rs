//! `crepuscular bench`: whole-frame and scattering-stage timings of each method on the
//! built-in scenes, measured side by side in one run so that ratios are meaningful on
//! noisy machines.

use std::sync::Arc;

use clap::Args;
use crepuscular::adaptive::AdaptivePasses;
use crepuscular::builtin::{builtin_scene, BUILTIN_SCENES};
use crepuscular::gpu::Device;
use crepuscular::scene::{Extent, Method, Scene};
use crepuscular::{render_scene_timed, Backend, Error, RenderControl, Result, StageTimes};
use glam::{Mat4, Vec3};

use crate::{style_bench, Overrides};

#[derive(Args)]
pub struct BenchArgs {
    /// Comma-separated scene names (default: all built-in scenes).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Timed runs per row; the rows take turns, each run after an untimed frame of its
    /// own row (the reference, and a lone row, warm up once).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Instead of the method table, time prefiltering on the first scene across image
    /// sizes (720p, 1080p, 2160p) and shadow-map sizes (512² to 4096²).
    #[arg(long)]
    scaling: bool,
    /// Only the stylization table: occluder operators on each scene's shadow map and the
    /// transfer function on its rendered layers.
    #[arg(long)]
    stylize: bool,
    /// With `--backend vulkan`: skip the CPU backend's run of each frame beside the GPU's.
    #[arg(long)]
    no_cpu: bool,
    /// Confine each scene's medium to a box around its subject, as a fog cube in Blender
    /// does, at the same extinction.
    #[arg(long)]
    fog_box: bool,
    #[command(flatten)]
    overrides: Overrides,
}

/// The device a GPU bench runs on: `None` for the CPU table (the default, and `auto`
/// without a GPU). An explicit `vulkan` that cannot open a device is an error here,
/// since timing the CPU in its place would mislabel the numbers.
fn bench_device(backend: Option<Backend>) -> Result<Option<Arc<Device>>> {
    match backend {
        None | Some(Backend::Cpu) => Ok(None),
        Some(Backend::Auto) => Ok(crepuscular::backend::vulkan_device(Backend::Auto)),
        Some(Backend::Vulkan) => Ok(Some(
            crepuscular::gpu::shared_device(crepuscular::gpu::DevicePolicy::Any)
                .map_err(Error::Gpu)?,
        )),
    }
}

/// One timed configuration.
#[derive(Clone, Copy)]
struct Variant {
    method: Method,
    downsample: u32,
    bases: Option<u32>,
    /// 0 shades every pixel; `None` keeps the scene's.
    adaptive_tolerance: Option<f32>,
    size: Option<(u32, u32)>,
    shadow_map_size: Option<u32>,
}

impl Variant {
    fn of(method: Method) -> Self {
        Self {
            method,
            downsample: 1,
            bases: None,
            adaptive_tolerance: None,
            size: None,
            shadow_map_size: None,
        }
    }

    fn apply(&self, scene: &mut Scene) {
        scene.render.method = self.method;
        scene.render.downsample = self.downsample;
        if let Some(bases) = self.bases {
            scene.render.bases = bases;
        }
        if let Some(tolerance) = self.adaptive_tolerance {
            scene.render.adaptive_tolerance = tolerance;
        }
        if let Some((width, height)) = self.size {
            scene.camera.width = width;
            scene.camera.height = height;
        }
        if let Some(size) = self.shadow_map_size {
            scene.render.shadow_map_size = size;
        }
    }

    fn label(&self, scene: &Scene) -> String {
        let mut label = self.method.name().to_owned();
        if self.method == Method::Prefiltered {
            label += &format!(" M={}", scene.render.bases);
        }
        if self.downsample > 1 {
            label += &format!(" 1/{}", self.downsample);
        }
        if self.method != Method::Reference && scene.render.adaptive_tolerance == 0.0 {
            label += " every px";
        }
        label
    }
}

struct Row {
    scene: String,
    label: String,
    is_reference: bool,
    detail: String,
    frame_ms: Vec<f64>,
    scattering_ms: Vec<f64>,
}

/// The table: every method at full size, prefiltering at M = 16/32/64, and the
/// fast methods at half resolution with upsampling; then the fast methods shading every
/// pixel instead of adaptively.
fn method_variants() -> Vec<Variant> {
    let prefiltered = |bases: u32, downsample: u32| Variant {
        bases: Some(bases),
        downsample,
        ..Variant::of(Method::Prefiltered)
    };
    vec![
        Variant::of(Method::Reference),
        Variant::of(Method::MinMax),
        prefiltered(16, 1),
        prefiltered(32, 1),
        prefiltered(64, 1),
        prefiltered(32, 2),
        Variant {
            downsample: 2,
            ..Variant::of(Method::MinMax)
        },
        Variant {
            adaptive_tolerance: Some(0.0),
            ..Variant::of(Method::MinMax)
        },
        Variant {
            adaptive_tolerance: Some(0.0),
            ..prefiltered(32, 1)
        },
    ]
}

/// Prefiltering across image and shadow-map sizes: the O(w·h + a·d) of §4.5.
fn scaling_variants() -> Vec<Variant> {
    let mut variants: Vec<Variant> = [(1280, 720), (1920, 1080), (3840, 2160)]
        .into_iter()
        .map(|size| Variant {
            size: Some(size),
            shadow_map_size: Some(1024),
            ..Variant::of(Method::Prefiltered)
        })
        .collect();
    variants.extend([512, 2048, 4096].into_iter().map(|sm| Variant {
        size: Some((1920, 1080)),
        shadow_map_size: Some(sm),
        ..Variant::of(Method::Prefiltered)
    }));
    variants
}

/// A box around the scene's subject (everything but the ground, object 1): its
/// footprint half as wide again on each side, from the ground to a fifth above its top.
fn fog_box_around_subject(scene: &Scene) -> Extent {
    let points = |subject_only: bool| {
        scene
            .meshes
            .iter()
            .filter(move |m| !subject_only || m.object_id != 1)
            .flat_map(|m| {
                m.positions
                    .iter()
                    .map(|&p| m.world_from_object.transform_point3(Vec3::from(p)))
            })
    };
    let bounds = |points: &mut dyn Iterator<Item = Vec3>| {
        points.fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(low, high), p| (low.min(p), high.max(p)),
        )
    };
    let (mut low, mut high) = bounds(&mut points(true));
    if low.x > high.x {
        (low, high) = bounds(&mut points(false));
    }
    let centre = 0.5 * (low + high);
    let half = 0.5 * (high - low);
    let low = Vec3::new(
        centre.x - 1.5 * half.x,
        centre.y - 1.5 * half.y,
        low.z.min(0.0),
    );
    let high = Vec3::new(
        centre.x + 1.5 * half.x,
        centre.y + 1.5 * half.y,
        high.z + 0.2 * (high.z - low.z),
    );
    Extent::Box {
        world_from_cube: Mat4::from_translation(0.5 * (low + high))
            * Mat4::from_scale((0.5 * (high - low)).max(Vec3::splat(0.5))),
    }
}

/// With `fog_box`, confines `scene`'s medium to [`fog_box_around_subject`]; the name its
/// rows go by either way.
pub fn in_fog_box_if(fog_box: bool, scene: &mut Scene, name: &str) -> String {
    if fog_box {
        scene.medium.extent = fog_box_around_subject(scene);
        format!("{name} (box)")
    } else {
        name.to_owned()
    }
}

pub fn median(sorted: &[f64]) -> f64 {
    let n = sorted.len();
    if n % 2 == 1 {
        sorted[n / 2]
    } else {
        0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
    }
}

pub fn run(args: &BenchArgs) -> Result<()> {
    let names: Vec<String> = if args.scenes.is_empty() {
        BUILTIN_SCENES.iter().map(|s| s.to_string()).collect()
    } else {
        args.scenes.clone()
    };
    // Benchmarks default to the design's standard frame: 1920×1080, 1024² shadow map, 1024 steps.
    let mut overrides = args.overrides.clone();
    overrides.width.get_or_insert(1920);
    overrides.height.get_or_insert(1080);
    overrides.sm_size.get_or_insert(1024);
    overrides.steps.get_or_insert(1024);
    let runs = args.runs.max(1);
    if let Some(device) = bench_device(overrides.backend)? {
        return crate::gpu_bench::run(
            &device,
            &names,
            &overrides,
            runs,
            !args.no_cpu,
            args.fog_box,
        );
    }
    let (names, variants) = if args.scaling {
        (names[..1].to_vec(), scaling_variants())
    } else {
        let variants = match overrides.method {
            Some(method) => vec![Variant {
                downsample: overrides.downsample.unwrap_or(1),
                ..Variant::of(method)
            }],
            None => method_variants(),
        };
        (names, variants)
    };
    if args.stylize {
        return stylization_table(&names, &overrides, runs);
    }
    let mut rows = Vec::new();
    for name in &names {
        let mut base = builtin_scene(name)?;
        overrides.apply(&mut base)?;
        base.render.backend = Backend::Cpu;
        let name = &in_fog_box_if(args.fog_box, &mut base, name);
        let scenes: Vec<Scene> = variants
            .iter()
            .map(|variant| {
                let mut scene = base.clone();
                variant.apply(&mut scene);
                scene
            })
            .collect();
        let is_reference =
            |variant: &Variant| variant.method == Method::Reference && variant.downsample == 1;
        let mut timed: Vec<Vec<(f64, StageTimes)>> = vec![Vec::with_capacity(runs); scenes.len()];
        // The rows take turns, run by run, so that a slow minute on a shared machine slows
        // every row alike rather than one. Each timed frame follows an untimed one of its
        // own row, so that it finds the kept buffers (see `crepuscular::spare`) sized for
        // it rather than for the row before; the reference, whose frames take seconds,
        // and a lone row warm up once.
        let takes_turns = variants.len() > 1;
        for run in 0..runs {
            for ((variant, scene), timed) in variants.iter().zip(&scenes).zip(&mut timed) {
                if run == 0 || (takes_turns && !is_reference(variant)) {
                    render_scene_timed(scene, &RenderControl::new())?;
                }
                let started = std::time::Instant::now();
                let (_, times) = render_scene_timed(scene, &RenderControl::new())?;
                timed.push((started.elapsed().as_secs_f64() * 1e3, times));
            }
        }
        for ((variant, scene), timed) in variants.iter().zip(&scenes).zip(timed) {
            let mut frame_ms: Vec<f64> = timed.iter().map(|(ms, _)| *ms).collect();
            let mut scattering_ms: Vec<f64> = timed
                .iter()
                .map(|(_, times)| times.scattering() * 1e3)
                .collect();
            let mut stages: Vec<StageTimes> = timed.into_iter().map(|(_, times)| times).collect();
            stages.sort_by(|a, b| a.scattering().total_cmp(&b.scattering()));
            let stage = stages[stages.len() / 2];
            frame_ms.sort_by(f64::total_cmp);
            scattering_ms.sort_by(f64::total_cmp);
            let row = Row {
                scene: name.clone(),
                label: variant.label(scene),
                is_reference: is_reference(variant),
                detail: format!(
                    "{}×{} sm {}²",
                    scene.camera.width, scene.camera.height, scene.render.shadow_map_size,
                ),
                frame_ms,
                scattering_ms,
            };
            eprintln!(
                "{name} {} {}: scattering median {:.1} ms (rectify {:.1}, prepare {:.1}{}, shading {:.1}{}; shadow map {:.1}, camera depth {:.1}; rectified map {:.1} MiB, method structure {:.1} MiB; shaded {:.1}% of {} pixels{})",
                row.label,
                row.detail,
                median(&row.scattering_ms),
                stage.rectify * 1e3,
                stage.prepare * 1e3,
                preparation_split(&stage),
                stage.shading * 1e3,
                shading_split(&stage),
                stage.shadow_map * 1e3,
                stage.camera_depth * 1e3,
                stage.rectified_bytes as f64 / (1 << 20) as f64,
                stage.structure_bytes as f64 / (1 << 20) as f64,
                100.0 * stage.shaded_pixels as f64 / stage.pixels.max(1) as f64,
                stage.pixels,
                walked_share(&stage),
            );
            rows.push(row);
        }
    }
    print_table(&rows);
    let order = if variants.len() > 1 {
        "the rows taking turns, each run after an untimed frame of its own row (the reference's after one)"
    } else {
        "after one warm-up"
    };
    println!(
        "\n{} runs per row, {order}; {} threads on {}; reference at {} steps; peak resident memory {}",
        runs,
        rayon::current_num_threads(),
        processor(),
        overrides.steps.unwrap_or(1024),
        peak_memory()
    );
    if args.scaling {
        return Ok(());
    }
    stylization_table(&names, &overrides, runs)
}

/// Of a frame's preparation, prefiltering's plan and then its filtered basis (the prefix
/// sums and the tables over them), where planned.
fn preparation_split(stage: &StageTimes) -> String {
    if stage.planning == 0.0 {
        return String::new();
    }
    format!(
        " [plan {:.1}, filtered basis {:.1}]",
        stage.planning * 1e3,
        (stage.prepare - stage.planning) * 1e3
    )
}

/// Of a frame's shading, adaptive shading's passes, where it shaded adaptively; the rest
/// of the shading (upsampling) is not counted in them.
fn shading_split(stage: &StageTimes) -> String {
    let passes = stage.passes;
    if passes == AdaptivePasses::default() {
        return String::new();
    }
    format!(
        " [lattice {:.1} ({} shaded), finer grid {:.1} ({}), between {:.1} ({})]",
        passes.lattice * 1e3,
        passes.lattice_shaded,
        passes.finer_grid * 1e3,
        passes.finer_grid_shaded,
        passes.between * 1e3,
        passes.between_shaded,
    )
}

/// Of the rays a fast method was asked for, the share it declined and the exact walk
/// computed, where it counted them.
fn walked_share(stage: &StageTimes) -> String {
    if stage.fast_rays == 0 {
        return String::new();
    }
    format!(
        ", {:.1}% of their rays walked exactly",
        100.0 * stage.walked_rays as f64 / stage.fast_rays as f64
    )
}

fn stylization_table(names: &[String], overrides: &Overrides, runs: usize) -> Result<()> {
    let mut rows = Vec::new();
    for name in names {
        let mut scene = builtin_scene(name)?;
        overrides.apply(&mut scene)?;
        rows.extend(style_bench::rows(name, &scene, runs)?);
    }
    style_bench::print_table(&rows);
    Ok(())
}

/// Width of a table's scene column: its longest name ("colonnade (box)" with
/// `--fog-box`), at least 10.
pub fn scene_column<'s>(names: impl Iterator<Item = &'s str>) -> usize {
    names.map(|name| name.chars().count()).fold(10, usize::max)
}

fn print_table(rows: &[Row]) {
    let width = scene_column(rows.iter().map(|row| row.scene.as_str()));
    println!(
        "\n{:<width$} {:<26} {:<22} {:>10} {:>16} {:>9} {:>10} {:>9}",
        "scene", "method", "frame", "scatter ms", "min–max", "speed-up", "frame ms", "speed-up"
    );
    for row in rows {
        let reference = rows.iter().find(|r| r.scene == row.scene && r.is_reference);
        let ratio = |of: fn(&Row) -> &Vec<f64>| {
            reference.map_or("-".to_owned(), |r| {
                format!("{:.1}×", median(of(r)) / median(of(row)))
            })
        };
        let scattering = median(&row.scattering_ms);
        let range = format!(
            "{:.1}–{:.1}",
            row.scattering_ms[0],
            row.scattering_ms[row.scattering_ms.len() - 1]
        );
        println!(
            "{:<width$} {:<26} {:<22} {:>10.1} {:>16} {:>9} {:>10.1} {:>9}",
            row.scene,
            row.label,
            row.detail,
            scattering,
            range,
            ratio(|r| &r.scattering_ms),
            median(&row.frame_ms),
            ratio(|r| &r.frame_ms),
        );
    }
}

pub struct DemoRow {
    pub scene: &'static str,
    pub width: u32,
    pub height: u32,
    pub triangles: usize,
    pub method: Method,
    pub steps: u32,
    pub shadow_map_size: u32,
    pub milliseconds: f64,
    pub files: String,
}

pub fn print_demo_table(rows: &[DemoRow]) {
    println!(
        "\n{:<10} {:>11} {:>10} {:<10} {:>6} {:>8} {:>10}  files",
        "scene", "resolution", "triangles", "method", "steps", "sm", "ms"
    );
    for row in rows {
        println!(
            "{:<10} {:>11} {:>10} {:<10} {:>6} {:>8} {:>10.1}  {}",
            row.scene,
            format!("{}×{}", row.width, row.height),
            row.triangles,
            row.method.name(),
            row.steps,
            format!("{}²", row.shadow_map_size),
            row.milliseconds,
            row.files
        );
    }
    println!(
        "\n{} threads on {}; peak resident memory {}",
        rayon::current_num_threads(),
        processor(),
        peak_memory()
    );
}

/// The processor's model name, from the kernel: the machines benchmarks run on change
/// between runs (one CPU model's table may be 1.7× another's), so tables name theirs.
pub fn processor() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|line| line.starts_with("model name"))
                .and_then(|line| line.split_once(':'))
                .map(|(_, name)| name.trim().to_owned())
        })
        .unwrap_or_else(|| "an unknown processor".to_owned())
}

/// Peak resident set size of this process, from the kernel's accounting.
pub fn peak_memory() -> String {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            status
                .lines()
                .find(|line| line.starts_with("VmHWM:"))
                .map(|line| line["VmHWM:".len()..].trim().to_owned())
        })
        .unwrap_or_else(|| "unknown".to_owned())
}
