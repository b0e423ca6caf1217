//! `crepuscular._core`: the thin native layer under the `crepuscular` Python package.
//!
//! Every function here parses its arguments into core types, runs the core with the GIL
//! released where the work can be long, and converts the core's errors once, through
//! `errors::to_py_err`. The friendly Python API (dicts, paths, dtype conversion, the
//! `Layers` dataclass) lives in `python/crepuscular/__init__.py`; keep this layer one
//! function per core entry point.

mod arrays;
mod errors;
mod files;
mod run;

use crepuscular::cutout::{AlphaMask, Cutouts};
use crepuscular::exr_file::ExrCompression;
use crepuscular::render::FlatGeometry;
use crepuscular::scene::{parse_json_at, Camera, Medium, RenderSettings, Sun, SCENE_VERSION};
use crepuscular::style::STYLE_VERSION;
use crepuscular::visibility::VisibilitySplit;
use crepuscular::{
    CameraDepth, DepthKind, Error, Frame, Geometry, Layers, RenderControl, Scene, Style,
};
use std::path::PathBuf;

use numpy::{PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{layers_to_py, rows, values, values_2d, DepthMap};
use crate::errors::to_py_err;
use crate::run::run_detached;

/// Lets go of the buffers kept from earlier frames for the next.
#[pyfunction]
fn release_kept_buffers() {
    crepuscular::release_kept_buffers();
}

/// Renders a JSON scene description; relative file paths in its style are made relative
/// to `base_dir` (the directory of the file the text came from) when given.
///
/// Returns `(width, height, volume, visibility, depth)` with arrays shaped `(H, W, 4)`,
/// `(H, W)` and `(H, W)`.
#[pyfunction]
#[pyo3(signature = (
    scene_json, /, *, base_dir=None, style_json=None, camera_depth=None, depth_kind="planar",
    progress=None,
))]
fn render_json<'py>(
    py: Python<'py>,
    scene_json: &str,
    base_dir: Option<PathBuf>,
    style_json: Option<&str>,
    camera_depth: Option<PyReadonlyArray2<'py, f32>>,
    depth_kind: &str,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyTuple>> {
    let (kind, depth) = depth_input(depth_kind, camera_depth.as_ref()).map_err(to_py_err)?;
    let (layers, hole_objects_warning) = run_detached(py, progress.as_ref(), |control| {
        let mut scene = Scene::from_json(scene_json)?;
        if let Some(base) = &base_dir {
            scene.rebase_paths(base);
        }
        if let Some(style) = style_json {
            scene.style = Style::from_json(style)?;
        }
        let mut geometry = FlatGeometry::from_scene(&scene);
        geometry.load_cutouts(&scene)?;
        geometry.split_visibility(&scene)?;
        let parts = Parts {
            camera: &scene.camera,
            sun: &scene.sun,
            medium: &scene.medium,
            settings: &scene.render,
            style: &scene.style,
        };
        let layers = parts.render(
            geometry.view(),
            geometry.camera_view(),
            depth,
            kind,
            control,
        )?;
        Ok((layers, scene.hole_objects_warning()))
    })?;
    if let Some(warning) = hole_objects_warning {
        let category = py.get_type::<pyo3::exceptions::PyUserWarning>();
        // The message is built from digits and ASCII text, so it holds no NUL.
        if let Ok(message) = std::ffi::CString::new(warning) {
            PyErr::warn(py, category.as_any(), &message, 2)?;
        }
    }
    layers_to_py(py, layers)
}

/// An alpha mask as `render_arrays` takes it: its alpha, threshold, wrap along u and v,
/// filter and border alpha.
type MaskArgs<'py> = (PyReadonlyArray2<'py, f32>, f32, String, String, String, f32);

/// The value of a setting that the scene description spells `name` (`"clip"`), for
/// `field`.
fn named_value<T: serde::de::DeserializeOwned>(field: &str, name: &str) -> crepuscular::Result<T> {
    serde_json::from_value(serde_json::Value::String(name.to_owned()))
        .map_err(|error| Error::invalid(field, error.to_string()))
}

/// Renders borrowed geometry with the camera, sun, medium and render settings given as JSON
/// objects (the `camera`, `sun`, `medium` and `render` members of a scene description).
///
/// `positions` (N, 3) float32, `triangles` (M, 3) uint32 and `object_ids` (M,) uint32 must
/// be C-contiguous and aligned; they are read in place, never copied. `origin` is the world
/// point the positions are relative to (the world's origin when `None`).
/// `triangle_visibility` (M,) uint8 flags which triangles block the sun (1) and which the
/// camera sees (2).
#[pyfunction]
#[pyo3(signature = (
    positions, triangles, object_ids, camera_json, sun_json, medium_json, settings_json, /,
    *, style_json=None, camera_depth=None, depth_kind="planar", progress=None, origin=None,
    uvs=None, triangle_masks=None, masks=None, triangle_visibility=None,
))]
#[allow(clippy::too_many_arguments)]
fn render_arrays<'py>(
    py: Python<'py>,
    positions: PyReadonlyArray2<'py, f32>,
    triangles: PyReadonlyArray2<'py, u32>,
    object_ids: PyReadonlyArray1<'py, u32>,
    camera_json: &str,
    sun_json: &str,
    medium_json: &str,
    settings_json: &str,
    style_json: Option<&str>,
    camera_depth: Option<PyReadonlyArray2<'py, f32>>,
    depth_kind: &str,
    progress: Option<Bound<'py, PyAny>>,
    origin: Option<[f64; 3]>,
    uvs: Option<PyReadonlyArray2<'py, f32>>,
    triangle_masks: Option<PyReadonlyArray1<'py, u32>>,
    masks: Option<Vec<MaskArgs<'py>>>,
    triangle_visibility: Option<PyReadonlyArray1<'py, u8>>,
) -> PyResult<Bound<'py, PyTuple>> {
    let alpha_masks = masks
        .as_deref()
        .unwrap_or_default()
        .iter()
        .enumerate()
        .map(|(k, (alpha, threshold, wrap_u, wrap_v, filter, border))| {
            let shape = alpha.shape();
            Ok(AlphaMask {
                width: shape[1] as u32,
                height: shape[0] as u32,
                alpha: std::borrow::Cow::Borrowed(values_2d(&format!("masks[{k}]"), alpha)?),
                threshold: *threshold,
                wrap: [
                    named_value(&format!("masks[{k}].wrap"), wrap_u)?,
                    named_value(&format!("masks[{k}].wrap"), wrap_v)?,
                ],
                filter: named_value(&format!("masks[{k}].filter"), filter)?,
                border: *border,
            })
        })
        .collect::<crepuscular::Result<Vec<_>>>()
        .map_err(to_py_err)?;
    let prepared = (|| {
        let origin = glam::DVec3::from(origin.unwrap_or_default());
        if !origin.is_finite() {
            return Err(Error::invalid(
                "origin",
                format!("must be finite, got {origin}"),
            ));
        }
        let camera: Camera = parse_json_at("camera", camera_json)?;
        let sun: Sun = parse_json_at("sun", sun_json)?;
        let medium: Medium = parse_json_at("medium", medium_json)?;
        let settings: RenderSettings = parse_json_at("render", settings_json)?;
        let style = match style_json {
            Some(text) => Style::from_json(text)?,
            None => Style::default(),
        };
        let geometry = Geometry {
            positions: rows("positions", &positions)?,
            triangles: rows("triangles", &triangles)?,
            object_ids: values("object_ids", &object_ids)?,
            origin,
            cutouts: match (&uvs, &triangle_masks) {
                (Some(uvs), Some(triangle_masks)) => Some(Cutouts {
                    uvs: rows("uvs", uvs)?,
                    triangle_masks: values("triangle_masks", triangle_masks)?,
                    masks: &alpha_masks,
                }),
                (None, None) => None,
                _ => {
                    return Err(Error::invalid(
                        "triangle_masks",
                        "uvs and triangle_masks come together (give both or neither)",
                    ))
                }
            },
        };
        let (kind, depth) = depth_input(depth_kind, camera_depth.as_ref())?;
        let split = match &triangle_visibility {
            Some(flags) => VisibilitySplit::new(
                &geometry,
                values("triangle_visibility", flags)?,
                "triangle_visibility",
            )?,
            None => None,
        };
        Ok((
            camera, sun, medium, settings, style, geometry, split, kind, depth,
        ))
    })();
    let (camera, sun, medium, settings, style, geometry, split, kind, depth) =
        prepared.map_err(to_py_err)?;
    let layers = run_detached(py, progress.as_ref(), |control| {
        let parts = Parts {
            camera: &camera,
            sun: &sun,
            medium: &medium,
            settings: &settings,
            style: &style,
        };
        match &split {
            Some(split) => parts.render(
                split.sun.view(&geometry),
                Some(split.camera.view(&geometry)),
                depth,
                kind,
                control,
            ),
            None => parts.render(geometry, None, depth, kind, control),
        }
    })?;
    layers_to_py(py, layers)
}

/// Parses and validates a JSON scene description and returns it re-serialized with every
/// default filled in; relative file paths in its style are made relative to `base_dir`
/// (the directory of the file the text came from) when given.
#[pyfunction]
#[pyo3(signature = (scene_json, /, *, base_dir=None))]
fn normalize_scene_json(
    py: Python<'_>,
    scene_json: &str,
    base_dir: Option<PathBuf>,
) -> PyResult<String> {
    py.detach(|| {
        let mut scene = Scene::from_json(scene_json)?;
        if let Some(base) = &base_dir {
            scene.rebase_paths(base);
        }
        Ok::<_, crepuscular::Error>(scene.to_json())
    })
    .map_err(to_py_err)
}

/// Parses and validates a JSON style preset and returns it re-serialized with every
/// default filled in; relative file paths are made relative to `base_dir` when given.
#[pyfunction]
#[pyo3(signature = (style_json, /, *, base_dir=None))]
fn normalize_style_json(
    py: Python<'_>,
    style_json: &str,
    base_dir: Option<PathBuf>,
) -> PyResult<String> {
    py.detach(|| {
        let mut style = Style::from_json(style_json)?;
        if let Some(base) = &base_dir {
            style.rebase_paths(base);
        }
        Ok::<_, crepuscular::Error>(style.to_json())
    })
    .map_err(to_py_err)
}

/// Bakes a style preset's transfer function at `time` into its texture.
///
/// Returns `(size, size, 4)` premultiplied linear RGBA; row `j` holds `u = (j + 0.5)/size`
/// (depth rising), column `i` holds `V̄ = (i + 0.5)/size`.
#[pyfunction]
#[pyo3(signature = (style_json, /, *, time=0.0))]
fn bake_tf<'py>(py: Python<'py>, style_json: &str, time: f32) -> PyResult<Bound<'py, PyAny>> {
    let texture = py
        .detach(|| {
            let style = Style::from_json(style_json)?;
            let tf = style
                .tf
                .ok_or_else(|| Error::invalid("style.tf", "the style has no transfer function"))?;
            tf.bake(time)
        })
        .map_err(to_py_err)?;
    let size = texture.size() as usize;
    let flat: Vec<f32> = texture.texels().iter().flatten().copied().collect();
    Ok(numpy::PyArray1::from_vec(py, flat)
        .reshape([size, size, 4])?
        .into_any())
}

/// The frame-wide parts of a render, borrowed.
struct Parts<'a> {
    camera: &'a Camera,
    sun: &'a Sun,
    medium: &'a Medium,
    settings: &'a RenderSettings,
    style: &'a Style,
}

impl Parts<'_> {
    /// Checks the depth map's shape, then renders (the core validates everything else).
    fn render(
        &self,
        geometry: Geometry<'_>,
        camera_geometry: Option<Geometry<'_>>,
        depth: Option<DepthMap<'_>>,
        kind: DepthKind,
        control: &RenderControl,
    ) -> crepuscular::Result<Layers> {
        let frame = Frame {
            camera: self.camera,
            sun: self.sun,
            medium: self.medium,
            settings: self.settings,
            style: self.style,
            geometry,
            camera_geometry,
            camera_depth: depth.map(|map| CameraDepth {
                values: map.values,
                kind,
            }),
        };
        if let Some(map) = &depth {
            map.check(self.camera)?;
        }
        crepuscular::render(&frame, control)
    }
}

fn depth_input<'a>(
    depth_kind: &str,
    camera_depth: Option<&'a PyReadonlyArray2<'_, f32>>,
) -> crepuscular::Result<(DepthKind, Option<DepthMap<'a>>)> {
    let kind = match depth_kind {
        "planar" => DepthKind::Planar,
        "ray_distance" => DepthKind::RayDistance,
        other => {
            return Err(Error::invalid(
                "depth_kind",
                format!("unknown depth kind '{other}' (known: planar, ray_distance)"),
            ))
        }
    };
    let depth = camera_depth.map(DepthMap::borrow).transpose()?;
    Ok((kind, depth))
}

/// The native half of the `crepuscular` package.
#[pymodule]
fn _core(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add("__version__", env!("CARGO_PKG_VERSION"))?;
    module.add("SCENE_VERSION", SCENE_VERSION)?;
    // The EXR codecs by name, the default first, as `write_exr` documents them.
    let default = ExrCompression::default();
    let others = ExrCompression::ALL
        .into_iter()
        .filter(|&codec| codec != default);
    let codecs: Vec<&str> = std::iter::once(default)
        .chain(others)
        .map(ExrCompression::name)
        .collect();
    module.add("EXR_COMPRESSIONS", PyTuple::new(module.py(), codecs)?)?;
    errors::register(module)?;
    module.add_function(wrap_pyfunction!(release_kept_buffers, module)?)?;
    module.add_function(wrap_pyfunction!(render_json, module)?)?;
    module.add_function(wrap_pyfunction!(render_arrays, module)?)?;
    module.add_function(wrap_pyfunction!(normalize_scene_json, module)?)?;
    module.add_function(wrap_pyfunction!(normalize_style_json, module)?)?;
    module.add_function(wrap_pyfunction!(bake_tf, module)?)?;
    module.add("STYLE_VERSION", STYLE_VERSION)?;
    module.add_function(wrap_pyfunction!(files::builtin_scene_json, module)?)?;
    module.add_function(wrap_pyfunction!(files::builtin_scene_names, module)?)?;
    module.add_function(wrap_pyfunction!(files::read_exr, module)?)?;
    module.add_function(wrap_pyfunction!(files::read_exr_pixel_aspect, module)?)?;
    module.add_function(wrap_pyfunction!(files::write_layers_exr, module)?)?;
    module.add_function(wrap_pyfunction!(files::write_channels_exr, module)?)?;
    module.add_function(wrap_pyfunction!(files::composite, module)?)?;
    module.add_function(wrap_pyfunction!(files::write_preview_png, module)?)?;
    Ok(())
}
