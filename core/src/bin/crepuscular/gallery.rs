//! The demo's before/after gallery: each shipped preset and each operator on its own,
//! rendered beside the physically based frame at one shared exposure, so that what the
//! style adds or removes is visible and not hidden by auto exposure.

use std::path::Path;

use crepuscular::builtin::builtin_scene;
use crepuscular::holes::HolesDesc;
use crepuscular::morphology::{KernelShape, MorphologyOp};
use crepuscular::preview::{auto_exposure, write_png, ViewTransform};
use crepuscular::silhouette::SilhouetteOp;
use crepuscular::style::{HoleFilling, Silhouette};
use crepuscular::transfer_function::{
    DepthRange, DiffusionConstraint, TfLayer, TfMode, TransferFunction,
};
use crepuscular::{render_scene, Error, Layers, RenderControl, Result, Style};

use crate::Overrides;

/// The shipped presets, embedded so that the demo does not depend on the working directory.
const PRESETS: [(&str, &str, &str); 4] = [
    (
        "hole-filled-torus",
        "torus",
        include_str!("../../../../examples/presets/hole-filled-torus.json"),
    ),
    (
        "extruded-colonnade",
        "colonnade",
        include_str!("../../../../examples/presets/extruded-colonnade.json"),
    ),
    (
        "holes-in-tree",
        "tree",
        include_str!("../../../../examples/presets/holes-in-tree.json"),
    ),
    (
        "alarm",
        "colonnade",
        include_str!("../../../../examples/presets/alarm.json"),
    ),
];

/// Pixels of black between the two halves.
const GUTTER: u32 = 6;

struct Entry {
    name: String,
    scene: &'static str,
    style: Style,
}

fn operators() -> Vec<Entry> {
    let entry = |name: &str, scene, style| Entry {
        name: name.to_owned(),
        scene,
        style,
    };
    let closing = |operation, kernel, radius| Style {
        closing: Some(HoleFilling {
            operation,
            kernel,
            radius,
            radius_texels: None,
        }),
        ..Style::default()
    };
    let silhouette = |operation, length| Style {
        silhouette: Some(Silhouette {
            operation,
            length,
            length_texels: None,
        }),
        ..Style::default()
    };
    let holes = |time| Style {
        time,
        holes: Some(HolesDesc {
            threshold: 0.5,
            speed: 0.05,
            objects: vec![2, 3, 4],
            ..HolesDesc::default()
        }),
        ..Style::default()
    };
    // Monochrome: a diffusion field that brightens near, dim shafts and darkens far ones.
    let pin = |position: [f32; 2], value: f32| DiffusionConstraint {
        position,
        color: [value, value, value, 1.0],
        world_point: None,
    };
    let diffusion = TfLayer::Diffusion {
        opacity: 1.0,
        blend: Default::default(),
        constraints: vec![
            pin([0.0, 0.0], 3.0),
            pin([1.0, 0.0], 1.0),
            pin([0.5, 1.0], 0.2),
        ],
    };
    let tf = Style {
        tf: Some(TransferFunction::new(
            TfMode::Monochrome,
            DepthRange {
                near: 0.0,
                far: 40.0,
            },
            vec![diffusion],
        )),
        ..Style::default()
    };
    vec![
        entry(
            "closing-box",
            "torus",
            closing(MorphologyOp::Close, KernelShape::Box, 1.6),
        ),
        entry(
            "opening-disk",
            "tree",
            closing(MorphologyOp::Open, KernelShape::Disk, 0.3),
        ),
        entry(
            "dilation-disk",
            "colonnade",
            closing(MorphologyOp::Dilate, KernelShape::Disk, 0.4),
        ),
        entry(
            "epipolar-dilation",
            "colonnade",
            silhouette(SilhouetteOp::Dilate, 0.15),
        ),
        entry("holes-t0", "colonnade", holes(0.0)),
        entry("holes-t40", "colonnade", holes(40.0)),
        entry("tf-monochrome-diffusion", "tree", tf),
    ]
}

/// Renders every gallery entry as `<name>.png` (physical | styled) into `dir`.
pub fn render(dir: &Path, overrides: &Overrides) -> Result<Vec<String>> {
    std::fs::create_dir_all(dir).map_err(|err| Error::io(dir, err))?;
    let mut entries = Vec::new();
    for (name, scene, json) in PRESETS {
        entries.push(Entry {
            name: name.to_owned(),
            scene,
            style: Style::from_json(json)?,
        });
    }
    entries.extend(operators());
    let mut written = Vec::new();
    for entry in &entries {
        let mut scene = builtin_scene(entry.scene)?;
        overrides.apply(&mut scene)?;
        // Half the demo's resolution: two frames side by side stay a readable size.
        scene.camera.width = (scene.camera.width / 2).max(1);
        scene.camera.height = (scene.camera.height / 2).max(1);
        scene.style = Style::default();
        let before = render_scene(&scene, &RenderControl::new())?;
        scene.style = entry.style.clone();
        let after = render_scene(&scene, &RenderControl::new())?;
        let path = dir.join(format!("{}.png", entry.name));
        write_side_by_side(&path, &before, &after)?;
        eprintln!(
            "gallery: {} on {} → {}",
            entry.name,
            entry.scene,
            path.display()
        );
        written.push(path.display().to_string());
    }
    Ok(written)
}

fn write_side_by_side(path: &Path, before: &Layers, after: &Layers) -> Result<()> {
    let (w, h) = (before.width as usize, before.height as usize);
    let width = 2 * w + GUTTER as usize;
    let mut rgba = vec![0.0f32; width * h * 4];
    for y in 0..h {
        let row = &mut rgba[y * width * 4..(y + 1) * width * 4];
        row[..w * 4].copy_from_slice(&before.volume[y * w * 4..(y + 1) * w * 4]);
        row[(w + GUTTER as usize) * 4..].copy_from_slice(&after.volume[y * w * 4..(y + 1) * w * 4]);
    }
    let view = ViewTransform {
        exposure: auto_exposure(&before.volume),
        ..ViewTransform::default()
    };
    write_png(path, width as u32, h as u32, &rgba, &view)
}
