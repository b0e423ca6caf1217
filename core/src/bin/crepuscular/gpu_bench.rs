//! `crepuscular bench --backend vulkan`: per-stage GPU timestamps of the Vulkan backend on
//! the built-in scenes, physically based and stylized, next to the CPU backend's times
//! for the same frames, with the shader cores' clock rate each row ran at.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crepuscular::builtin::{builtin_scene, torus_tessellated};
use crepuscular::gpu::frame::{render_timed, GpuTimes};
use crepuscular::gpu::host_time::{self, HostTimes};
use crepuscular::gpu::{clock, Device, DeviceKind, GpuError};
use crepuscular::render::{render_timed_cpu, FlatGeometry, Frame};
use crepuscular::scene::{Method, Rectification, Scene};
use crepuscular::{Backend, Error, RenderControl, Result, StageTimes, Style};

use crate::bench::{median, peak_memory, processor, scene_column};
use crate::Overrides;

/// The stylized rows' look when no `--style` is given: a disk closing of 0.25 scene units
/// and a colour TF over (V̄, depth).
const BENCH_STYLE: &str = r#"{
  "version": 1,
  "closing": { "operation": "close", "kernel": "disk", "radius": 0.25 },
  "tf": {
    "mode": "color",
    "depth_range": { "near": 0.0, "far": 60.0 },
    "layers": [{
      "kind": "gradient",
      "shape": { "kind": "linear", "from": [0.0, 0.0], "to": [1.0, 1.0] },
      "stops": [
        { "position": 0.0, "color": [0.2, 0.1, 0.9, 0.5] },
        { "position": 1.0, "color": [1.0, 0.6, 0.1, 1.0] }
      ]
    }]
  }
}"#;

/// How long each row first keeps the device busy, so that its clock can rise from idle
/// before the timed runs.
const CLOCK_WARM_UP: Duration = Duration::from_millis(300);

/// Whether the bench reads the clock: CPU implementations have a counter, but their
/// timestamps do not time the probe (see [`print_table`]).
fn reads_clock(device: &Device) -> bool {
    clock::supported(device) && device.physical.kind != DeviceKind::Cpu
}

/// Keeps the device busy for [`CLOCK_WARM_UP`] where the bench reads its clock.
fn warm_up(device: &Arc<Device>) {
    if reads_clock(device) {
        if let Err(err) = clock::warm_up(device, CLOCK_WARM_UP) {
            eprintln!("the clock warm-up failed: {err}");
        }
    }
}

/// The shader cores' clock in MHz now, or `None` where the bench cannot tell; a probe
/// that fails says so once and the bench goes on without it.
fn clock_now(device: &Arc<Device>) -> Option<f64> {
    static REPORTED: AtomicBool = AtomicBool::new(false);
    if !reads_clock(device) {
        return None;
    }
    clock::measure(device, clock::CHAIN_LINKS)
        .map_err(|err| {
            if !REPORTED.swap(true, Ordering::Relaxed) {
                eprintln!("the clock probe failed, so rows show no clock rate: {err}");
            }
        })
        .ok()
        .flatten()
}

struct Row {
    scene: String,
    method: &'static str,
    look: &'static str,
    /// The shader cores' clock after each timed run, median MHz.
    clock: Option<f64>,
    shadow_map: Option<f64>,
    camera_depth: Option<f64>,
    hole_filling: Option<f64>,
    silhouettes: Option<f64>,
    hole_creation: Option<f64>,
    march: Option<f64>,
    rectify: Option<f64>,
    prefix: Option<f64>,
    upsampling: Option<f64>,
    transfer: Option<f64>,
    /// The scattering stages' GPU time ([`GpuTimes::scattering`]), median ms.
    scattering: f64,
    /// A lower bound on the scattering stages' memory traffic, MiB ([`least_traffic`]).
    traffic: f64,
    gpu_total: f64,
    /// Wall time of the Vulkan path's depth maps and rectification (GPU passes with their
    /// uploads and read-backs, CPU work such as projective rasterization), median ms.
    cpu_side: f64,
    frame: f64,
    cpu: Option<(StageTimes, f64)>,
    cpu_stages: Vec<&'static str>,
}

fn median_of(values: impl Iterator<Item = f64>) -> f64 {
    let mut values: Vec<f64> = values.collect();
    values.sort_by(f64::total_cmp);
    median(&values)
}

/// The median of `values`, or `None` where there are none.
fn median_if_any(values: Vec<f64>) -> Option<f64> {
    (!values.is_empty()).then(|| median_of(values.into_iter()))
}

fn median_option(times: &[GpuTimes], of: fn(&GpuTimes) -> Option<f64>) -> Option<f64> {
    median_if_any(times.iter().filter_map(of).collect())
}

pub fn run(
    device: &Arc<Device>,
    names: &[String],
    overrides: &Overrides,
    runs: usize,
    compare_cpu: bool,
    fog_box: bool,
) -> Result<()> {
    let stylized = match &overrides.style {
        Some(_) => None,
        None => Some(Style::from_json(BENCH_STYLE)?),
    };
    let mut rows = Vec::new();
    let mut skipped = Vec::new();
    for name in names {
        let mut base = builtin_scene(name)?;
        overrides.apply(&mut base)?;
        base.render.backend = Backend::Vulkan;
        let name = &crate::bench::in_fog_box_if(fog_box, &mut base, name);
        let mut looks = vec![(
            if overrides.style.is_some() {
                "--style"
            } else {
                "physical"
            },
            base.clone(),
        )];
        if let Some(style) = &stylized {
            let mut scene = base.clone();
            scene.style = style.clone();
            looks.push(("stylized", scene));
        }
        if overrides.method.is_none() {
            let mut scene = base.clone();
            scene.render.method = Method::Prefiltered;
            // The built-in scenes' own method is prefiltering: no second row of it.
            if base.render.method != Method::Prefiltered {
                looks.push(("physical", scene.clone()));
            }
            if overrides.downsample.is_none() && scene.render.supersampling == 1 {
                scene.render.downsample = 2;
                looks.push(("phys. 1/2", scene));
            }
        }
        for (look, scene) in looks {
            let geometry = FlatGeometry::from_scene(&scene);
            let frame = Frame::of_scene(&scene, &geometry);
            // A frame past this device's limits is reported and the others still run: the
            // render itself would fall back to the CPU, which is not what is timed here.
            match render_timed(device, &frame, &RenderControl::new()) {
                Err(Error::Gpu(GpuError::Unsupported(reason))) => {
                    let frame = format!("{name} {} {look}: {reason}", scene.render.method.name());
                    eprintln!("not run on this device: {frame}");
                    skipped.push(frame);
                    continue;
                }
                other => other?,
            };
            let mut gpu = Vec::new();
            let mut cpu_side = Vec::new();
            let mut wall = Vec::new();
            let mut walls: Vec<StageTimes> = Vec::new();
            let mut clocks = Vec::new();
            let mut host: Vec<HostTimes> = Vec::new();
            warm_up(device);
            for _ in 0..runs {
                host_time::take();
                let started = std::time::Instant::now();
                let (_, stages, times) = render_timed(device, &frame, &RenderControl::new())?;
                host.push(host_time::take());
                wall.push(started.elapsed().as_secs_f64() * 1e3);
                walls.push(stages);
                cpu_side.push((stages.shadow_map + stages.camera_depth + stages.rectify) * 1e3);
                gpu.push(times);
                clocks.extend(clock_now(device));
            }
            let cpu = if compare_cpu {
                let started = std::time::Instant::now();
                let (_, stages) = render_timed_cpu(&frame, &RenderControl::new())?;
                Some((stages, started.elapsed().as_secs_f64() * 1e3))
            } else {
                None
            };
            let row = Row {
                scene: name.clone(),
                method: scene.render.method.name(),
                look,
                clock: median_if_any(clocks),
                shadow_map: median_option(&gpu, |t| t.shadow_map),
                camera_depth: median_option(&gpu, |t| t.camera_depth),
                hole_filling: median_option(&gpu, |t| t.hole_filling),
                silhouettes: median_option(&gpu, |t| t.silhouettes),
                hole_creation: median_option(&gpu, |t| t.hole_creation),
                march: median_option(&gpu, |t| t.ray_march.or(t.prefiltered)),
                rectify: median_option(&gpu, |t| t.rectification),
                prefix: median_option(&gpu, |t| t.prefix_sums),
                upsampling: median_option(&gpu, |t| t.upsampling),
                transfer: median_option(&gpu, |t| t.transfer_function),
                scattering: median_of(gpu.iter().map(GpuTimes::scattering)),
                traffic: least_traffic(&scene, &walls[0]) as f64 / (1024.0 * 1024.0),
                gpu_total: median_of(gpu.iter().map(GpuTimes::total)),
                cpu_side: median_of(cpu_side.into_iter()),
                frame: median_of(wall.into_iter()),
                cpu,
                cpu_stages: gpu[0].cpu_stages.clone(),
            };
            // Where the frame's wall time goes (GPU stages include their copies here), and
            // the Vulkan path's host work within it.
            let wall_of = |of: fn(&StageTimes) -> f64| median_of(walls.iter().map(|s| of(s) * 1e3));
            let host_of = |of: fn(&HostTimes) -> f64| median_of(host.iter().map(|h| of(h) * 1e3));
            eprintln!(
                "{name} {} {look}: GPU {:.3} ms, frame {:.1} ms; wall ms: shadow map {:.1}, \
                 occluders {:.1}, camera depth {:.1}, rectify {:.1}, prepare {:.1}, shading {:.1}, \
                 TF {:.1}; host ms: buffers {:.1}, uploads {:.1} ({:.0} MB), waits {:.1}, \
                 read-backs {:.1} ({:.0} MB); {}",
                row.method,
                row.gpu_total,
                row.frame,
                wall_of(|s| s.shadow_map),
                wall_of(|s| s.occluders),
                wall_of(|s| s.camera_depth),
                wall_of(|s| s.rectify),
                wall_of(|s| s.prepare),
                wall_of(|s| s.shading),
                wall_of(|s| s.transfer_function),
                host_of(|h| h.allocation),
                host_of(|h| h.writes),
                host_of(|h| h.bytes_written as f64 * 1e-9),
                host_of(|h| h.waits),
                host_of(|h| h.reads),
                host_of(|h| h.bytes_read as f64 * 1e-9),
                match walls[0].pixels {
                    0 => "every pixel shaded".to_owned(),
                    pixels => format!(
                        "shaded {:.1}% of {pixels} pixels",
                        100.0 * walls[0].shaded_pixels as f64 / pixels as f64
                    ),
                },
            );
            rows.push(row);
        }
    }
    print_table(device, &rows, overrides, runs);
    for frame in &skipped {
        println!("not run on this device: {frame}");
    }
    raster_row(device, overrides, runs, compare_cpu)
}

/// Quads around and across the tube of the rasterization row's torus: 2·1024·512 =
/// 1,048,576 triangles in the ring.
const DENSE_TORUS_SEGMENTS: (u32, u32) = (1024, 512);

/// Times the two depth passes on the `torus` scene tessellated into a million triangles.
/// The rectification is epipolar so that no pass rasterizes on the CPU.
fn raster_row(
    device: &Arc<Device>,
    overrides: &Overrides,
    runs: usize,
    compare_cpu: bool,
) -> Result<()> {
    let mut scene = torus_tessellated(DENSE_TORUS_SEGMENTS.0, DENSE_TORUS_SEGMENTS.1);
    overrides.apply(&mut scene)?;
    scene.render.backend = Backend::Vulkan;
    scene.render.method = Method::Prefiltered;
    scene.render.rectification = Rectification::Epipolar;
    let geometry = FlatGeometry::from_scene(&scene);
    let frame = Frame::of_scene(&scene, &geometry);
    render_timed(device, &frame, &RenderControl::new())?;
    let mut gpu = Vec::new();
    let mut walls = Vec::new();
    let mut clocks = Vec::new();
    warm_up(device);
    for _ in 0..runs {
        let (_, stages, times) = render_timed(device, &frame, &RenderControl::new())?;
        gpu.push(times);
        walls.push(stages);
        clocks.extend(clock_now(device));
    }
    let clock = median_if_any(clocks);
    let wall = |of: fn(&StageTimes) -> f64| median_of(walls.iter().map(|s| of(s) * 1e3));
    println!(
        "\nRasterization of {} triangles (torus at {}×{} segments, and the ground), {}×{}, {}² map; \
         GPU timestamp medians of {runs}: shadow map {} ms, camera depth {} ms (clock {} MHz); \
         wall with the geometry upload and read-backs: shadow map {:.1} ms, camera depth {:.1} ms",
        geometry.triangles.len(),
        DENSE_TORUS_SEGMENTS.0,
        DENSE_TORUS_SEGMENTS.1,
        scene.camera.width,
        scene.camera.height,
        scene.render.shadow_map_size,
        gpu_ms(median_option(&gpu, |t| t.shadow_map)),
        gpu_ms(median_option(&gpu, |t| t.camera_depth)),
        megahertz(clock),
        wall(|s| s.shadow_map),
        wall(|s| s.camera_depth),
    );
    if compare_cpu {
        let (_, stages) = render_timed_cpu(&frame, &RenderControl::new())?;
        println!(
            "CPU backend, one run with {} threads: shadow map {:.1} ms, camera depth {:.1} ms",
            rayon::current_num_threads(),
            stages.shadow_map * 1e3,
            stages.camera_depth * 1e3,
        );
    }
    Ok(())
}

/// The least memory traffic of `scene`'s scattering stages, in bytes: the shadow map
/// and the camera depth read once, the rectified map and the method's structure (the
/// filtered basis) written once and read once, and the layers (RGBA, visibility, depth,
/// four bytes each) written once. `stages` gives the structures' sizes.
fn least_traffic(scene: &Scene, stages: &StageTimes) -> usize {
    const FLOAT: usize = 4;
    let render = &scene.render;
    let map = render.shadow_map_size as usize;
    let pixels = scene.camera.width as usize * scene.camera.height as usize;
    let depth_samples = pixels * (render.supersampling as usize).pow(2);
    map * map * FLOAT
        + depth_samples * FLOAT
        + 2 * (stages.rectified_bytes + stages.structure_bytes)
        + pixels * 6 * FLOAT
}

/// A clock rate in whole MHz, or "-" where the device cannot tell.
fn megahertz(rate: Option<f64>) -> String {
    rate.map_or("-".to_owned(), |rate| format!("{rate:.0}"))
}

/// A GPU time in ms, or "-" for a stage that did not run.
fn gpu_ms(v: Option<f64>) -> String {
    v.map_or("-".to_owned(), |v| format!("{v:.3}"))
}

fn print_table(device: &Device, rows: &[Row], overrides: &Overrides, runs: usize) {
    let ms = gpu_ms;
    let cpu_ms = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.1}"));
    println!(
        "\nVulkan backend on {}; GPU columns are timestamp medians in ms",
        device.describe()
    );
    if device.physical.kind == DeviceKind::Cpu {
        // Seen on lavapipe: 0.01–0.09 ms for single-dispatch stages that take hundreds of
        // ms of wall time (its end-of-pipe timestamp does not wait for the dispatch); stages
        // with barriers inside (hole filling) read plausibly.
        println!(
            "(a CPU implementation: its compute-stage timestamps are not reliable; compare \
             wall times)"
        );
    }
    let width = scene_column(rows.iter().map(|row| row.scene.as_str()));
    println!(
        "{:<width$} {:<11} {:<9} {:>5} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8} {:>8} {:>8} {:>7} | {:>9} {:>10} {:>9} {:>10} {:>9}",
        "scene",
        "method",
        "look",
        "MHz",
        "smap",
        "cdepth",
        "holes",
        "silh",
        "hcreate",
        "rect",
        "shade",
        "prefix",
        "up",
        "TF",
        "scatter",
        "min MiB",
        "GPU sum",
        "maps",
        "frame",
        "cpu holes",
        "cpu shade",
        "cpu TF",
        "cpu frame",
        "speed-up"
    );
    for row in rows {
        let cpu = row.cpu.as_ref();
        let speed_up = match (cpu, row.march) {
            (Some((stages, _)), Some(shade)) if shade > 0.0 => {
                format!("{:.1}×", stages.shading * 1e3 / shade)
            }
            _ => "-".to_owned(),
        };
        let march_column = cpu.map(|(s, _)| s.shading * 1e3);
        println!(
            "{:<width$} {:<11} {:<9} {:>5} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8.3} {:>8.1} {:>8.3} {:>8.1} {:>7.1} | {:>9} {:>10} {:>9} {:>10} {:>9}",
            row.scene,
            row.method,
            row.look,
            megahertz(row.clock),
            ms(row.shadow_map),
            ms(row.camera_depth),
            ms(row.hole_filling),
            ms(row.silhouettes),
            ms(row.hole_creation),
            ms(row.rectify),
            ms(row.march),
            ms(row.prefix),
            ms(row.upsampling),
            ms(row.transfer),
            row.scattering,
            row.traffic,
            row.gpu_total,
            row.cpu_side,
            row.frame,
            cpu_ms(cpu.map(|(s, _)| s.occluders * 1e3).filter(|v| *v > 0.0)),
            cpu_ms(march_column),
            cpu_ms(cpu.map(|(s, _)| s.transfer_function * 1e3).filter(|v| *v > 0.0)),
            cpu_ms(cpu.map(|(_, frame)| *frame)),
            speed_up,
        );
    }
    let mut on_cpu: Vec<&str> = rows.iter().flat_map(|r| r.cpu_stages.clone()).collect();
    on_cpu.sort();
    on_cpu.dedup();
    println!(
        "\nMHz = the shader cores' clock rate after each timed run (median), read by a probe \
         (VK_KHR_shader_clock; '-' where the device lacks it, and on CPU implementations): GPUs lower their clock when \
         lightly loaded, and stages timed at a lowered clock take longer in proportion, so \
         compare rows at like clocks; each row first keeps the device busy for {} ms. \
         smap = shadow-map depth pass (depth and object ids); cdepth = camera depth pass; holes = hole filling (2D closing); silh = silhouette enhancement (1D epipolar dilation or closure); hcreate = hole creation (noise holes in chosen objects); rect = epipolar rectification; shade = per-pixel scattering (the reference march, or \
         prefiltered evaluation with the exact texel walk near on-screen epipoles and for the rays it declines); prefix = \
         prefiltering's basis computation and prefix sums; up = joint-bilateral upsampling of \
         evaluation at 1/2 size; TF = transfer-function application; scatter = rect + prefix + shade + up, \
         the scattering stages after the depth maps and occluder operators; min MiB = the least \
         memory traffic those stages can have (the shadow map and camera depth read once, the \
         rectified map and the filtered basis written and read once, the layers written once): \
         divided by the device's memory bandwidth, the time they cannot beat. Uploads and read-backs lie outside the GPU columns but inside `frame`, the \
         wall time of the whole Vulkan-path frame. `maps` = wall time of the shadow map, camera \
         depth and rectification stages (GPU passes with their transfers, and CPU work). Stages the Vulkan path still runs on the CPU: {}.",
        CLOCK_WARM_UP.as_millis(),
        on_cpu.join(", ")
    );
    let clocks: Vec<f64> = rows.iter().filter_map(|row| row.clock).collect();
    let highest = clocks.iter().copied().fold(0.0, f64::max);
    let slowed = clocks.iter().filter(|&&rate| rate < 0.9 * highest).count();
    if slowed > 0 {
        println!(
            "{slowed} of {} rows ran below 90% of the highest clock read ({highest:.0} MHz): \
             their GPU columns overstate the stages' time at full clock",
            clocks.len()
        );
    }
    println!(
        "{} runs per row after one warm-up; reference at {} steps; speed-up = cpu shade / GPU \
         shade; CPU columns from one run with {} threads on {}; peak resident memory {}",
        runs,
        overrides.steps.unwrap_or(1024),
        rayon::current_num_threads(),
        processor(),
        peak_memory()
    );
}
