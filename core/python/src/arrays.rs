//! numpy ↔ core data, without copies in either direction.
//!
//! Inputs are borrowed from C-contiguous, aligned arrays of the right dtype (the Python layer
//! converts anything else with `np.ascontiguousarray`, which copies only when it must).
//! Outputs are the core's `Vec`s lent to numpy as they are and reshaped into views; when
//! numpy lets go of them they go back to the core for a later frame.

use bytemuck::Pod;
use crepuscular::layers::LayerBuffer;
use crepuscular::scene::Camera;
use crepuscular::{Error, Layers, Result};
use numpy::ndarray::ArrayView1;
use numpy::{
    Element, PyArray1, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

/// Borrows an `(N, COLUMNS)` array as `N` rows.
pub fn rows<'a, T: Element + Pod, const COLUMNS: usize>(
    name: &str,
    array: &'a PyReadonlyArray2<'_, T>,
) -> Result<&'a [[T; COLUMNS]]>
where
    [T; COLUMNS]: Pod,
{
    let shape = array.shape();
    if shape[1] != COLUMNS {
        return Err(Error::invalid(
            name,
            format!(
                "must have shape (N, {COLUMNS}), got ({}, {})",
                shape[0], shape[1]
            ),
        ));
    }
    Ok(bytemuck::cast_slice(flat(name, array.as_slice())?))
}

/// Borrows a one-dimensional array.
pub fn values<'a, T: Element>(name: &str, array: &'a PyReadonlyArray1<'_, T>) -> Result<&'a [T]> {
    flat(name, array.as_slice())
}

/// Borrows a two-dimensional array's values, row after row.
pub fn values_2d<'a, T: Element>(
    name: &str,
    array: &'a PyReadonlyArray2<'_, T>,
) -> Result<&'a [T]> {
    flat(name, array.as_slice())
}

fn flat<'a, T, E>(name: &str, slice: std::result::Result<&'a [T], E>) -> Result<&'a [T]> {
    slice.map_err(|_| Error::invalid(name, "must be a C-contiguous, aligned array"))
}

/// A camera depth map borrowed with its `(rows, columns)` shape.
#[derive(Clone, Copy, Debug)]
pub struct DepthMap<'a> {
    pub values: &'a [f32],
    pub shape: [usize; 2],
}

impl<'a> DepthMap<'a> {
    pub fn borrow(array: &'a PyReadonlyArray2<'_, f32>) -> Result<Self> {
        let shape = array.shape();
        Ok(DepthMap {
            values: flat("camera_depth", array.as_slice())?,
            shape: [shape[0], shape[1]],
        })
    }

    /// The map must have the camera's image shape (its window's, where it has one); the
    /// core checks the values.
    pub fn check(&self, camera: &Camera) -> Result<()> {
        let (width, height) = camera.image_size();
        let (width, height) = (width as usize, height as usize);
        if self.shape != [height, width] {
            return Err(Error::invalid(
                "camera_depth",
                format!(
                    "must have shape (height, width) = ({height}, {width}), got ({}, {})",
                    self.shape[0], self.shape[1]
                ),
            ));
        }
        Ok(())
    }
}

/// One layer's buffer behind the numpy array that views it. When numpy lets go of it, the
/// buffer goes back to the core for a later frame's layers, as dropping the layers does
/// in Rust: fresh pages for 1080p layers cost a tenth of a frame in page faults.
#[pyclass(frozen)]
struct LentLayer {
    buffer: LayerBuffer,
    values: Vec<f32>,
}

impl Drop for LentLayer {
    fn drop(&mut self) {
        Layers::keep_buffer(self.buffer, std::mem::take(&mut self.values));
    }
}

/// `values` as a one-dimensional numpy array without a copy, kept alive by its owner.
fn lend(
    py: Python<'_>,
    buffer: LayerBuffer,
    values: Vec<f32>,
) -> PyResult<Bound<'_, PyArray1<f32>>> {
    let owner = Bound::new(py, LentLayer { buffer, values })?;
    let view = ArrayView1::from(owner.get().values.as_slice());
    // SAFETY: the array views `owner`'s buffer, which numpy keeps alive as the array's base
    // and which nothing else reads, writes or moves while it lives.
    Ok(unsafe { PyArray1::borrow_from_array(&view, owner.clone().into_any()) })
}

/// `(width, height, volume, visibility, depth)`: the layers' buffers become numpy arrays
/// without a copy, shaped `(H, W, 4)`, `(H, W)` and `(H, W)`.
pub fn layers_to_py(py: Python<'_>, mut layers: Layers) -> PyResult<Bound<'_, PyTuple>> {
    // Taken rather than destructured: `Layers` keeps its buffers for reuse when dropped.
    let (width, height, pixel_aspect) = (layers.width, layers.height, layers.pixel_aspect);
    let volume = std::mem::take(&mut layers.volume);
    let visibility = std::mem::take(&mut layers.visibility);
    let depth = std::mem::take(&mut layers.depth);
    let (w, h) = (width as usize, height as usize);
    let volume = lend(py, LayerBuffer::Volume, volume)?.reshape([h, w, 4])?;
    let visibility = lend(py, LayerBuffer::Visibility, visibility)?.reshape([h, w])?;
    let depth = lend(py, LayerBuffer::Depth, depth)?.reshape([h, w])?;
    (width, height, volume, visibility, depth, pixel_aspect).into_pyobject(py)
}
