//! Edge supersampling shades a pixel once where its depth samples agree (as MSAA does) and
//! per sample at depth edges: against full supersampling (the same scene rendered at twice
//! the resolution and box-filtered, whose pixel centres are exactly the depth samples),
//! edge pixels are the same and the image stays within a fraction of a percent.

use crepuscular::render::uniform_surface;
use crepuscular::scene::Method;
use crepuscular::{builtin_scene, render_scene, Layers, RenderControl, BUILTIN_SCENES};

/// The layers, and the scene's maximum distance (the depth layer's background value).
fn render(name: &str, width: u32, height: u32, supersampling: u32) -> (Layers, f32) {
    let mut scene = builtin_scene(name).expect("built-in scene");
    scene.camera.width = width;
    scene.camera.height = height;
    // The reference shades each ray on its own, whatever the image size.
    scene.render.method = Method::Reference;
    scene.render.steps = 256;
    scene.render.supersampling = supersampling;
    let layers = render_scene(&scene, &RenderControl::new()).expect("render succeeds");
    (layers, scene.render.max_distance)
}

#[test]
fn edge_supersampling_matches_full_supersampling() {
    let (width, height) = (96usize, 54usize);
    for name in BUILTIN_SCENES {
        let (msaa, _) = render(name, width as u32, height as u32, 2);
        let (full, max_distance) = render(name, 2 * width as u32, 2 * height as u32, 1);
        let (mut diff, mut total, mut edges) = (0.0f64, 0.0f64, 0);
        for y in 0..height {
            for x in 0..width {
                let samples = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .map(|(sx, sy)| (2 * y + sy) * 2 * width + 2 * x + sx);
                // The depth layer holds the maximum distance where there is no surface.
                let depths = samples.map(|i| match full.depth[i] {
                    d if d == max_distance => f32::INFINITY,
                    d => d,
                });
                let uniform = uniform_surface(depths.into_iter());
                for c in 0..4 {
                    let boxed: f64 = samples
                        .iter()
                        .map(|&i| full.volume[i * 4 + c] as f64)
                        .sum::<f64>()
                        / 4.0;
                    let got = msaa.volume[(y * width + x) * 4 + c] as f64;
                    if c < 3 {
                        diff += (got - boxed).abs();
                        total += boxed;
                    }
                    if uniform.is_none() {
                        edges += usize::from(c == 0);
                        assert!(
                            (got - boxed).abs() <= 1e-5 * boxed.abs().max(1.0),
                            "{name} edge pixel ({x}, {y}) channel {c}: {got} vs {boxed}"
                        );
                    }
                }
            }
        }
        let relative = diff / total;
        println!(
            "{name}: {edges} edge pixels of {}, error {:.3}%",
            width * height,
            relative * 100.0
        );
        assert!(edges > 0, "{name}: no depth edge found");
        assert!(relative < 0.01, "{name}: {:.3}%", relative * 100.0);
    }
}

#[test]
fn depth_samples_agree_within_the_spread() {
    let inf = f32::INFINITY;
    assert_eq!(
        uniform_surface([inf, inf, inf, inf].into_iter()),
        Some(f64::INFINITY)
    );
    assert_eq!(uniform_surface([2.0, 2.0, 2.0, 2.0].into_iter()), Some(2.0));
    assert!(uniform_surface([2.0, 2.02, 2.0, 2.0].into_iter()).is_some());
    assert_eq!(uniform_surface([2.0, 2.1, 2.0, 2.0].into_iter()), None);
    assert_eq!(uniform_surface([2.0, inf, 2.0, 2.0].into_iter()), None);
    assert_eq!(uniform_surface(std::iter::empty()), None);
}
