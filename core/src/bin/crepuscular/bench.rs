//! `crepuscular bench`: whole-frame timings of each method on the built-in scenes,
//! measured side by side in one run so that ratios are meaningful on noisy machines.

use std::time::Instant;

use clap::Args;
use crepuscular::builtin::{builtin_scene, BUILTIN_SCENES};
use crepuscular::scene::Method;
use crepuscular::{render_scene, RenderControl, Result};

use crate::Overrides;

#[derive(Args)]
pub struct BenchArgs {
    /// Comma-separated scene names (default: all built-in scenes).
    #[arg(long, value_delimiter = ',')]
    scenes: Vec<String>,
    /// Timed runs per row (after one warm-up run).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    #[command(flatten)]
    overrides: Overrides,
}

struct Row {
    scene: String,
    method: Method,
    downsample: u32,
    detail: String,
    times_ms: Vec<f64>,
}

impl Row {
    fn label(&self) -> String {
        match self.downsample {
            1 => self.method.name().to_owned(),
            factor => format!("{} 1/{factor}", self.method.name()),
        }
    }
}

/// The methods timed by default: each at full resolution, plus the fast one at half.
fn default_variants() -> Vec<(Method, u32)> {
    let mut variants: Vec<(Method, u32)> = Method::ALL.iter().map(|&m| (m, 1)).collect();
    variants.push((Method::MinMax, 2));
    variants
}

fn median(sorted: &[f64]) -> f64 {
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
    let mut rows = Vec::new();
    for name in &names {
        let mut scene = builtin_scene(name)?;
        overrides.apply(&mut scene);
        let variants = match overrides.method {
            Some(method) => vec![(method, overrides.downsample.unwrap_or(1))],
            None => default_variants(),
        };
        for (method, downsample) in variants {
            scene.render.method = method;
            scene.render.downsample = downsample;
            render_scene(&scene, &RenderControl::new())?;
            let mut times_ms = Vec::with_capacity(runs);
            for _ in 0..runs {
                let started = Instant::now();
                render_scene(&scene, &RenderControl::new())?;
                times_ms.push(started.elapsed().as_secs_f64() * 1e3);
            }
            times_ms.sort_by(f64::total_cmp);
            let row = Row {
                scene: name.clone(),
                method,
                downsample,
                detail: format!(
                    "{}×{} sm {}² steps {}",
                    scene.camera.width,
                    scene.camera.height,
                    scene.render.shadow_map_size,
                    scene.render.steps
                ),
                times_ms,
            };
            eprintln!(
                "{name} {}: median {:.1} ms",
                row.label(),
                median(&row.times_ms)
            );
            rows.push(row);
        }
    }
    println!(
        "\n{:<10} {:<12} {:<32} {:>11} {:>21} {:>9}",
        "scene", "method", "frame", "median ms", "min–max ms", "speed-up"
    );
    for row in &rows {
        let reference = rows
            .iter()
            .find(|r| r.scene == row.scene && r.method == Method::Reference && r.downsample == 1)
            .map(|r| median(&r.times_ms));
        let med = median(&row.times_ms);
        let speedup = reference.map_or("-".to_owned(), |r| format!("{:.2}×", r / med));
        let range = format!(
            "{:.1}–{:.1}",
            row.times_ms[0],
            row.times_ms[row.times_ms.len() - 1]
        );
        println!(
            "{:<10} {:<12} {:<32} {:>11.1} {:>21} {:>9}",
            row.scene,
            row.label(),
            row.detail,
            med,
            range,
            speedup
        );
    }
    println!(
        "\n{} runs per row after one warm-up; {} threads; peak resident memory {}",
        runs,
        rayon::current_num_threads(),
        peak_memory()
    );
    Ok(())
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
        "\n{} threads; peak resident memory {}",
        rayon::current_num_threads(),
        peak_memory()
    );
}

/// Peak resident set size of this process, from the kernel's accounting.
fn peak_memory() -> String {
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
