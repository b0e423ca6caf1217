//! `crepuscular`: render scenes to layer EXRs, export built-in scenes, and benchmark.

mod bench;
mod gallery;
mod gpu_bench;
mod style_bench;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::mpsc::RecvTimeoutError;
use std::time::Duration;

use clap::{Args, Parser, Subcommand};
use crepuscular::builtin::{builtin_scene, BUILTIN_SCENES};
use crepuscular::exr_file::{write_layers, ExrCompression, Precision};
use crepuscular::preview::{auto_exposure, write_png, ViewTransform};
use crepuscular::scene::{ExactRayEnds, Method, Rectification, Scene};
use crepuscular::{render_scene, Backend, Error, Layers, RenderControl, Result, Style};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser)]
#[command(
    name = "crepuscular",
    version,
    about = "Stylized volumetric light shafts"
)]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render one frame to a multi-layer EXR (and optionally a PNG preview).
    Render(RenderArgs),
    /// Built-in scenes.
    #[command(subcommand)]
    Scene(SceneCommand),
    /// Time the scattering methods on the built-in scenes.
    Bench(bench::BenchArgs),
    /// Render every built-in scene to EXR and PNG, then print a timing table.
    Demo(DemoArgs),
}

#[derive(Subcommand)]
enum SceneCommand {
    /// Write a built-in scene's JSON description.
    Export {
        name: String,
        /// Output file (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// List the built-in scenes.
    List,
}

/// Overrides of a scene's camera and render settings.
#[derive(Args, Clone, Debug, Default)]
pub struct Overrides {
    #[arg(long)]
    width: Option<u32>,
    #[arg(long)]
    height: Option<u32>,
    /// Shadow-map side in texels.
    #[arg(long)]
    sm_size: Option<u32>,
    #[arg(long)]
    method: Option<Method>,
    /// How the fast methods rectify the shadow map: auto, epipolar or projective.
    #[arg(long)]
    rectification: Option<Rectification>,
    /// Ray-march steps of the reference method.
    #[arg(long)]
    steps: Option<u32>,
    /// Camera-depth samples per pixel along each axis.
    #[arg(long)]
    supersampling: Option<u32>,
    /// Evaluate at 1/1, 1/2 or 1/4 resolution and upsample.
    #[arg(long)]
    downsample: Option<u32>,
    /// Fast methods: interpolate pixels whose shaded neighbours agree within this fraction
    /// (0 shades every pixel).
    #[arg(long)]
    adaptive_tolerance: Option<f32>,
    /// Prefiltered method: Fourier bases M (even, 4 to 64).
    #[arg(long)]
    bases: Option<u32>,
    /// Prefiltered method: integrate exactly the stretch before each ray's end where the
    /// shadow map closes in on the ray (grazed ground, views near the light): auto (in box
    /// media), on (the flag alone) or off.
    #[arg(long, num_args = 0..=1, default_missing_value = "on", value_name = "auto|on|off")]
    exact_ray_ends: Option<ExactRayEnds>,
    /// The medium's extinction σ in 1/m, replacing the scene's (its albedo, phase and
    /// extent stay).
    #[arg(long)]
    extinction: Option<f32>,
    /// A style preset (JSON) replacing the scene's style.
    #[arg(long)]
    style: Option<PathBuf>,
    /// Where to compute: auto (a GPU if there is one), cpu, or vulkan (any Vulkan device,
    /// software ones included). Falls back to the CPU with a message when Vulkan fails.
    #[arg(long)]
    backend: Option<Backend>,
}

impl Overrides {
    pub fn apply(&self, scene: &mut Scene) -> Result<()> {
        if let Some(path) = &self.style {
            scene.style = Style::load(path)?;
        }
        if let Some(width) = self.width {
            scene.camera.width = width;
        }
        if let Some(height) = self.height {
            scene.camera.height = height;
        }
        if let Some(size) = self.sm_size {
            scene.render.shadow_map_size = size;
        }
        if let Some(method) = self.method {
            scene.render.method = method;
        }
        if let Some(rectification) = self.rectification {
            scene.render.rectification = rectification;
        }
        if let Some(steps) = self.steps {
            scene.render.steps = steps;
        }
        if let Some(ss) = self.supersampling {
            scene.render.supersampling = ss;
        }
        if let Some(factor) = self.downsample {
            scene.render.downsample = factor;
        }
        if let Some(tolerance) = self.adaptive_tolerance {
            scene.render.adaptive_tolerance = tolerance;
        }
        if let Some(bases) = self.bases {
            scene.render.bases = bases;
        }
        if let Some(backend) = self.backend {
            scene.render.backend = backend;
        }
        if let Some(setting) = self.exact_ray_ends {
            scene.render.exact_ray_ends = setting;
        }
        if let Some(extinction) = self.extinction {
            scene.medium.extinction = extinction;
        }
        Ok(())
    }
}

#[derive(Args)]
struct RenderArgs {
    /// A built-in scene name or a scene JSON file.
    #[arg(long)]
    scene: String,
    #[arg(long)]
    out: PathBuf,
    /// Also write a tone-mapped PNG preview.
    #[arg(long)]
    png: Option<PathBuf>,
    /// Write half floats instead of full floats.
    #[arg(long)]
    half: bool,
    /// The EXR codec: zip (default), zips, piz, rle, none, or pxr24 (lossy: f32 rounded
    /// to 24 bits)
    #[arg(long, default_value_t = ExrCompression::Zip)]
    exr_compression: ExrCompression,
    #[command(flatten)]
    overrides: Overrides,
}

#[derive(Args)]
struct DemoArgs {
    #[arg(long, default_value = "out/demo")]
    out_dir: PathBuf,
    #[command(flatten)]
    overrides: Overrides,
}

fn main() -> ExitCode {
    end_quietly_on_a_closed_pipe();
    let cli = Cli::parse();
    if let Some(threads) = cli.threads {
        if let Err(err) = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
        {
            eprintln!("error: cannot start {threads} threads: {err}");
            return ExitCode::FAILURE;
        }
    }
    let result = match cli.command {
        Command::Render(args) => run_render(&args),
        Command::Scene(SceneCommand::Export { name, out }) => export_scene(&name, out.as_deref()),
        Command::Scene(SceneCommand::List) => {
            BUILTIN_SCENES.iter().for_each(|name| println!("{name}"));
            Ok(())
        }
        Command::Bench(args) => bench::run(&args),
        Command::Demo(args) => run_demo(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err}");
            ExitCode::FAILURE
        }
    }
}

/// Piped into a reader that stops early (`crepuscular scene export tree | head`), the
/// command ends as other Unix tools do, on SIGPIPE, rather than panicking in `println!`:
/// Rust ignores the signal, and every write after the reader closed then fails.
fn end_quietly_on_a_closed_pipe() {
    #[cfg(target_os = "linux")]
    // SAFETY: restoring the default action of a signal, before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Loads a built-in scene by name, or a scene JSON file by path.
pub fn load_scene(source: &str) -> Result<Scene> {
    let path = Path::new(source);
    if source.ends_with(".json") || path.exists() {
        Scene::load(path)
    } else {
        builtin_scene(source)
    }
}

fn export_scene(name: &str, out: Option<&Path>) -> Result<()> {
    let json = builtin_scene(name)?.to_json();
    match out {
        Some(path) => std::fs::write(path, json + "\n").map_err(|err| Error::io(path, err)),
        None => {
            println!("{json}");
            Ok(())
        }
    }
}

/// Renders with a progress bar on standard error (hidden when it is not a terminal).
pub fn render_with_progress(scene: &Scene, label: &str) -> Result<Layers> {
    let control = RenderControl::new();
    let bar = ProgressBar::new(1000).with_message(label.to_owned());
    bar.set_style(
        ProgressStyle::with_template("{msg:>12} [{bar:40}] {percent:>3}% {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let layers = std::thread::scope(|scope| {
        let (finished, done) = std::sync::mpsc::channel();
        let control = &control;
        let worker = scope.spawn(move || {
            let layers = render_scene(scene, control);
            // Dropped unsent if the render panics, which also ends the wait below.
            let _ = finished.send(());
            layers
        });
        // Woken the moment the frame is done: a sleep between polls of the worker kept
        // every CLI frame waiting up to another 50 ms.
        while let Err(RecvTimeoutError::Timeout) = done.recv_timeout(Duration::from_millis(50)) {
            bar.set_position((control.fraction() * 1000.0) as u64);
        }
        worker
            .join()
            .unwrap_or_else(|_| Err(Error::Internal("a render worker panicked".to_owned())))
    });
    bar.finish_and_clear();
    layers
}

fn precision(half: bool) -> Precision {
    if half {
        Precision::F16
    } else {
        Precision::F32
    }
}

fn write_preview(path: &Path, layers: &Layers) -> Result<()> {
    let view = ViewTransform {
        exposure: auto_exposure(&layers.volume),
        ..ViewTransform::default()
    };
    write_png(path, layers.width, layers.height, &layers.volume, &view)
}

fn run_render(args: &RenderArgs) -> Result<()> {
    let mut scene = load_scene(&args.scene)?;
    args.overrides.apply(&mut scene)?;
    if let Some(warning) = scene.hole_objects_warning() {
        eprintln!("crepuscular: warning: {warning}");
    }
    let started = std::time::Instant::now();
    let layers = render_with_progress(&scene, &args.scene)?;
    let elapsed = started.elapsed();
    if scene.medium.box_unreached(&layers) {
        eprintln!(
            "crepuscular: warning: no view ray reaches medium.extent's box: the frame has no \
             fog (is it out of view, behind a surface or past render.max_distance?)"
        );
    }
    write_layers(
        &args.out,
        &layers,
        precision(args.half),
        args.exr_compression,
    )?;
    if let Some(png) = &args.png {
        write_preview(png, &layers)?;
    }
    eprintln!(
        "rendered {} ({}×{}, {}, shadow map {}²) in {:.0} ms → {}",
        args.scene,
        layers.width,
        layers.height,
        scene.render.method.name(),
        scene.render.shadow_map_size,
        elapsed.as_secs_f64() * 1e3,
        args.out.display()
    );
    Ok(())
}

fn run_demo(args: &DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out_dir).map_err(|err| Error::io(&args.out_dir, err))?;
    let mut rows = Vec::new();
    for name in BUILTIN_SCENES {
        let mut scene = builtin_scene(name)?;
        args.overrides.apply(&mut scene)?;
        let started = std::time::Instant::now();
        let layers = render_with_progress(&scene, name)?;
        let elapsed = started.elapsed();
        let exr = args.out_dir.join(format!("{name}.exr"));
        let png = args.out_dir.join(format!("{name}.png"));
        write_layers(&exr, &layers, Precision::F32, ExrCompression::Zip)?;
        write_preview(&png, &layers)?;
        rows.push(bench::DemoRow {
            scene: name,
            width: layers.width,
            height: layers.height,
            triangles: scene.triangle_count(),
            method: scene.render.method,
            steps: scene.render.steps,
            shadow_map_size: scene.render.shadow_map_size,
            milliseconds: elapsed.as_secs_f64() * 1e3,
            files: format!("{}, {}", exr.display(), png.display()),
        });
    }
    bench::print_demo_table(&rows);
    let gallery = gallery::render(&args.out_dir.join("gallery"), &args.overrides)?;
    println!(
        "\ngallery: {} before/after pairs (physical | styled) in {}",
        gallery.len(),
        args.out_dir.join("gallery").display()
    );
    Ok(())
}
