//! Built-in scenes, EXR and PNG files, and compositing: the core's I/O entry points.

use std::collections::BTreeMap;
use std::path::PathBuf;

use crepuscular::exr_file::{
    read_exr as read_exr_file, read_pixel_aspect, write_channels, write_layers, ExrCompression,
    Precision,
};
use crepuscular::preview::{auto_exposure, write_png, ViewTransform};
use crepuscular::{composite::composite_over, Error, Layers};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};

use crate::errors::to_py_err;

/// The JSON description of a built-in scene.
#[pyfunction]
#[pyo3(signature = (name, /))]
pub fn builtin_scene_json(name: &str) -> PyResult<String> {
    crepuscular::builtin_scene(name)
        .map(|scene| scene.to_json())
        .map_err(to_py_err)
}

/// The names of the built-in scenes.
#[pyfunction]
pub fn builtin_scene_names() -> Vec<&'static str> {
    crepuscular::BUILTIN_SCENES.to_vec()
}

/// An EXR file's `pixelAspectRatio` (a pixel's width over its height), from its header.
#[pyfunction]
#[pyo3(signature = (path, /))]
pub fn read_exr_pixel_aspect(py: Python<'_>, path: PathBuf) -> PyResult<f32> {
    py.detach(|| read_pixel_aspect(&path)).map_err(to_py_err)
}

/// Reads every channel of every part of an EXR file.
///
/// Returns `(width, height, channels)` where `channels` maps full channel names to
/// `(height, width)` float32 arrays.
#[pyfunction]
#[pyo3(signature = (path, /))]
pub fn read_exr(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyTuple>> {
    let image = py.detach(|| read_exr_file(&path)).map_err(to_py_err)?;
    let (w, h) = (image.width as usize, image.height as usize);
    let channels = PyDict::new(py);
    let all: BTreeMap<String, Vec<f32>> = image.channels;
    for (name, values) in all {
        channels.set_item(name, PyArray1::from_vec(py, values).reshape([h, w])?)?;
    }
    (image.width, image.height, channels).into_pyobject(py)
}

fn contiguous<'a>(
    name: &str,
    slice: Result<&'a [f32], impl Sized>,
) -> crepuscular::Result<&'a [f32]> {
    slice.map_err(|_| Error::invalid(name, "must be a C-contiguous, aligned float32 array"))
}

/// Writes the layer set (`volume` (H, W, 4), `visibility` and `depth` (H, W)) as one
/// multi-layer EXR with the channels `volume.R/G/B/A`, `visibility` and `depth`, of
/// pixels `pixel_aspect` times as wide as tall.
#[pyfunction]
#[pyo3(signature = (
    path, volume, visibility, depth, /, *, half=false, compression="zip", pixel_aspect=1.0
))]
#[allow(clippy::too_many_arguments)]
pub fn write_layers_exr(
    py: Python<'_>,
    path: PathBuf,
    volume: PyReadonlyArray3<'_, f32>,
    visibility: PyReadonlyArray2<'_, f32>,
    depth: PyReadonlyArray2<'_, f32>,
    half: bool,
    compression: &str,
    pixel_aspect: f32,
) -> PyResult<()> {
    let compression: ExrCompression = compression.parse().map_err(to_py_err)?;
    let shape = volume.shape();
    let (h, w) = (shape[0], shape[1]);
    let layers = (|| {
        if shape[2] != 4 {
            return Err(Error::invalid(
                "volume",
                format!("must have shape (H, W, 4), got {shape:?}"),
            ));
        }
        for (name, array) in [("visibility", &visibility), ("depth", &depth)] {
            if array.shape() != [h, w] {
                return Err(Error::invalid(
                    name,
                    format!(
                        "must have shape ({h}, {w}) like volume, got {:?}",
                        array.shape()
                    ),
                ));
            }
        }
        Ok(Layers {
            width: w as u32,
            height: h as u32,
            volume: contiguous("volume", volume.as_slice())?.to_vec(),
            visibility: contiguous("visibility", visibility.as_slice())?.to_vec(),
            depth: contiguous("depth", depth.as_slice())?.to_vec(),
            pixel_aspect,
        })
    })()
    .map_err(to_py_err)?;
    let precision = if half { Precision::F16 } else { Precision::F32 };
    py.detach(|| write_layers(&path, &layers, precision, compression))
        .map_err(to_py_err)
}

/// Writes named (H, W) float32 planes as one single-part EXR, e.g. a composited
/// frame's `R`, `G`, `B`, `A`. Channel names are written as given, in the given order.
#[pyfunction]
#[pyo3(signature = (path, channels, /, *, half=false, compression="zip", pixel_aspect=1.0))]
pub fn write_channels_exr(
    py: Python<'_>,
    path: PathBuf,
    channels: Vec<(String, PyReadonlyArray2<'_, f32>)>,
    half: bool,
    compression: &str,
    pixel_aspect: f32,
) -> PyResult<()> {
    let compression: ExrCompression = compression.parse().map_err(to_py_err)?;
    let (h, w) = match channels.first() {
        Some((_, first)) => (first.shape()[0], first.shape()[1]),
        None => {
            return Err(to_py_err(Error::invalid(
                "channels",
                "no channels to write",
            )))
        }
    };
    let planes = channels
        .iter()
        .map(|(name, array)| {
            let field = format!("channels.{name}");
            if array.shape() != [h, w] {
                return Err(Error::invalid(
                    field,
                    format!(
                        "must have shape ({h}, {w}) like the first channel, got {:?}",
                        array.shape()
                    ),
                ));
            }
            Ok((
                name.as_str(),
                contiguous(&field, array.as_slice())?.to_vec(),
            ))
        })
        .collect::<crepuscular::Result<Vec<_>>>()
        .map_err(to_py_err)?;
    let precision = if half { Precision::F16 } else { Precision::F32 };
    py.detach(|| {
        let named: Vec<(&str, &[f32])> = planes.iter().map(|(n, v)| (*n, v.as_slice())).collect();
        write_channels(
            &path,
            w as u32,
            h as u32,
            &named,
            precision,
            compression,
            pixel_aspect,
        )
    })
    .map_err(to_py_err)
}

/// Premultiplied over: `volume.rgb + (1 − volume.a) · beauty`, both (H, W, 4).
#[pyfunction]
#[pyo3(signature = (volume, beauty, /))]
pub fn composite<'py>(
    py: Python<'py>,
    volume: PyReadonlyArray3<'py, f32>,
    beauty: PyReadonlyArray3<'py, f32>,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = volume.shape().to_vec();
    if beauty.shape() != shape.as_slice() {
        return Err(to_py_err(Error::invalid(
            "beauty",
            format!(
                "must have the volume's shape {shape:?}, got {:?}",
                beauty.shape()
            ),
        )));
    }
    let out = (|| {
        composite_over(
            contiguous("volume", volume.as_slice())?,
            contiguous("beauty", beauty.as_slice())?,
        )
    })()
    .map_err(to_py_err)?;
    Ok(PyArray1::from_vec(py, out).reshape(shape)?.into_any())
}

/// Writes an 8-bit sRGB PNG of premultiplied RGBA (H, W, 4) composited over black.
/// `exposure` is in stops; `None` picks one from the image.
#[pyfunction]
#[pyo3(signature = (path, rgba, /, *, exposure=None, tone_map=true))]
pub fn write_preview_png(
    py: Python<'_>,
    path: PathBuf,
    rgba: PyReadonlyArray3<'_, f32>,
    exposure: Option<f32>,
    tone_map: bool,
) -> PyResult<()> {
    let shape = rgba.shape();
    if shape[2] != 4 {
        return Err(to_py_err(Error::invalid(
            "rgba",
            format!("must have shape (H, W, 4), got {shape:?}"),
        )));
    }
    let pixels = contiguous("rgba", rgba.as_slice()).map_err(to_py_err)?;
    let view = ViewTransform {
        exposure: exposure.unwrap_or_else(|| auto_exposure(pixels)),
        tone_map,
    };
    py.detach(|| write_png(&path, shape[1] as u32, shape[0] as u32, pixels, &view))
        .map_err(to_py_err)
}
