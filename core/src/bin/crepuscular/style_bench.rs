//! The stylization rows of `crepuscular bench`: each operator timed alone on the scene's
//! own shadow map, and the transfer function on its own rendered layers, so that the
//! numbers compare with the per-operator budgets rather than with whole frames.

use std::time::Instant;

use crepuscular::camera::CameraModel;
use crepuscular::holes::{HoleNoise, HolesDesc};
use crepuscular::morphology::{self, KernelShape, MorphologyDesc, MorphologyOp};
use crepuscular::scene::Scene;
use crepuscular::shadow_map::ShadowMap;
use crepuscular::silhouette::{self, Epipole, SilhouetteDesc, SilhouetteOp};
use crepuscular::transfer_function;
use crepuscular::{render_scene, Error, RenderControl, Result, Style};

use crate::bench::median;

/// The alarm preset's transfer function: quantized gradients, the paper's Fig. 6 look.
const TF_PRESET: &str = include_str!("../../../../examples/presets/alarm.json");

pub struct StyleRow {
    scene: String,
    operator: &'static str,
    detail: String,
    budget_ms: Option<f64>,
    sorted_ms: Vec<f64>,
}

fn time(runs: usize, work: impl FnMut() -> Result<()>) -> Result<Vec<f64>> {
    time_prepared(runs, || {}, work)
}

/// [`time`] with `prepare` run, untimed, before every run of `work`: restoring the
/// input an operator works in place on is not the operator's time.
fn time_prepared(
    runs: usize,
    mut prepare: impl FnMut(),
    mut work: impl FnMut() -> Result<()>,
) -> Result<Vec<f64>> {
    prepare();
    work()?;
    let mut ms = Vec::with_capacity(runs);
    for _ in 0..runs {
        prepare();
        let started = Instant::now();
        work()?;
        ms.push(started.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    Ok(ms)
}

/// Times every operator on `scene`, whose camera and shadow-map size are already set.
pub fn rows(name: &str, scene: &Scene, runs: usize) -> Result<Vec<StyleRow>> {
    let camera = CameraModel::new(&scene.camera);
    let shadow = ShadowMap::of_scene(scene, &camera)?;
    let size = shadow.size;
    let row = |operator, detail: String, budget_ms, sorted_ms| StyleRow {
        scene: name.to_owned(),
        operator,
        detail,
        budget_ms,
        sorted_ms,
    };
    let mut rows = Vec::new();

    for (shape, label) in [(KernelShape::Disk, "disk"), (KernelShape::Box, "box")] {
        let desc = MorphologyDesc::new(MorphologyOp::Close, shape, 20.0);
        let ms = time(runs, || {
            morphology::apply(&shadow.depth, size, &desc).map(drop)
        })?;
        let budget = (shape == KernelShape::Disk).then_some(15.0);
        rows.push(row(
            "closing",
            format!("{label} 41 texels, {size}²"),
            budget,
            ms,
        ));
    }

    let epipole = Epipole::of_camera(&camera, &shadow.texel_from_world);
    let desc = SilhouetteDesc {
        op: SilhouetteOp::Close,
        length_texels: 60.0,
    };
    let ms = time(runs, || {
        silhouette::apply(&shadow.depth, size, epipole, &desc).map(drop)
    })?;
    rows.push(row(
        "epipolar closure",
        format!("60 texels, {size}²"),
        Some(20.0),
        ms,
    ));

    // Every occluder opening is the worst case; sparing the ground is the usual one.
    let every: Vec<u32> = scene.meshes.iter().map(|mesh| mesh.object_id).collect();
    let above_ground: Vec<u32> = scene
        .meshes
        .iter()
        .filter(|mesh| mesh.name != "ground")
        .map(|mesh| mesh.object_id)
        .collect();
    for (objects, label) in [(every, "every occluder"), (above_ground, "all but ground")] {
        let covered = shadow.ids.iter().filter(|id| objects.contains(id)).count();
        let desc = HolesDesc {
            objects,
            ..HolesDesc::default()
        };
        let depth = std::cell::RefCell::new(shadow.depth.clone());
        let ms = time_prepared(
            runs,
            || depth.borrow_mut().copy_from_slice(&shadow.depth),
            || {
                HoleNoise::for_map(&desc, &shadow)?.apply(&mut depth.borrow_mut(), &shadow.ids)?;
                Ok(())
            },
        )?;
        rows.push(row(
            "hole creation",
            format!(
                "{label}, {:.0}% of {size}²",
                100.0 * covered as f64 / shadow.ids.len() as f64
            ),
            Some(5.0),
            ms,
        ));
    }

    let style = Style::from_json(TF_PRESET)?;
    let Some(tf) = style.tf.as_ref() else {
        return Err(Error::Internal(
            "the embedded alarm preset has no transfer function".into(),
        ));
    };
    let texture = tf.bake(style.time)?;
    let settings = tf.apply_settings([1.0, 0.9, 0.8]);
    let physical = render_scene(scene, &RenderControl::new())?;
    let layers = std::cell::RefCell::new(physical.clone());
    let ms = time_prepared(
        runs,
        || layers.borrow_mut().volume.copy_from_slice(&physical.volume),
        || transfer_function::apply_to_layers(&mut layers.borrow_mut(), &texture, &settings),
    )?;
    let (w, h) = (scene.camera.width, scene.camera.height);
    rows.push(row("TF application", format!("{w}×{h}"), Some(10.0), ms));
    let ms = time(runs, || tf.bake(style.time).map(drop))?;
    rows.push(row(
        "TF bake",
        format!("{0}² texture", tf.resolution),
        None,
        ms,
    ));
    Ok(rows)
}

pub fn print_table(rows: &[StyleRow]) {
    println!(
        "\n{:<10} {:<17} {:<30} {:>9} {:>14} {:>8}",
        "scene", "operator", "size", "median ms", "min–max", "budget"
    );
    for row in rows {
        let ms = &row.sorted_ms;
        println!(
            "{:<10} {:<17} {:<30} {:>9.1} {:>14} {:>8}",
            row.scene,
            row.operator,
            row.detail,
            median(ms),
            format!("{:.1}–{:.1}", ms[0], ms[ms.len() - 1]),
            row.budget_ms
                .map_or("-".to_owned(), |budget| format!("≤{budget:.0}")),
        );
    }
}
