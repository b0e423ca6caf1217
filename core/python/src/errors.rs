//! The Python exception hierarchy and the one conversion from core errors into it.
//!
//! ```text
//! CrepuscularError(Exception)
//! ├── InvalidInputError(CrepuscularError, ValueError)   Error::{InvalidInput, SceneFormat, UnknownScene}
//! ├── ExrError(CrepuscularError, OSError)                Error::{Exr, Png, Io}
//! └── CancelledError(CrepuscularError)                   Error::Cancelled
//! ```
//!
//! `create_exception!` takes a single base class, so the two classes that also derive from a
//! built-in exception are made once per interpreter by calling `type(name, bases, dict)`.

use std::any::Any;
use std::path::Path;

use crepuscular::Error;
use pyo3::create_exception;
use pyo3::exceptions::{PyBaseException, PyException, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyTuple, PyType};

/// The module every exception class reports as its `__module__`.
const MODULE: &str = "crepuscular._core";

create_exception!(
    crepuscular._core,
    CrepuscularError,
    PyException,
    "Base class of every error raised by crepuscular."
);

create_exception!(
    crepuscular._core,
    CancelledError,
    CrepuscularError,
    "The render was cancelled before it finished."
);

static INVALID_INPUT_ERROR: PyOnceLock<Py<PyType>> = PyOnceLock::new();
static EXR_ERROR: PyOnceLock<Py<PyType>> = PyOnceLock::new();

const INVALID_INPUT_DOC: &str = "A value the caller gave is unusable: a scene field, a JSON \
document, an array argument or a built-in scene name.\n\n`field` names the offending value \
(for example 'camera.width' or 'positions') when it is known, and is None otherwise.";

const EXR_ERROR_DOC: &str = "Reading or writing a file (EXR, PNG or other I/O) failed. \
`filename` holds the path.";

/// `InvalidInputError(CrepuscularError, ValueError)`.
pub fn invalid_input_error(py: Python<'_>) -> PyResult<&Bound<'_, PyType>> {
    INVALID_INPUT_ERROR
        .get_or_try_init(py, || {
            let extra = PyDict::new(py);
            extra.set_item("field", py.None())?;
            new_exception_type(
                py,
                "InvalidInputError",
                INVALID_INPUT_DOC,
                py.get_type::<PyValueError>(),
                Some(extra),
            )
        })
        .map(|ty| ty.bind(py))
}

/// `ExrError(CrepuscularError, OSError)`.
pub fn exr_error(py: Python<'_>) -> PyResult<&Bound<'_, PyType>> {
    EXR_ERROR
        .get_or_try_init(py, || {
            // OSError's own __str__ prints "[Errno None] None: 'path'" once `filename` is
            // set, dropping the message that says what went wrong.
            let extra = PyDict::new(py);
            extra.set_item(
                "__str__",
                py.get_type::<PyBaseException>().getattr("__str__")?,
            )?;
            new_exception_type(
                py,
                "ExrError",
                EXR_ERROR_DOC,
                py.get_type::<PyOSError>(),
                Some(extra),
            )
        })
        .map(|ty| ty.bind(py))
}

/// `class name(CrepuscularError, builtin): ...` with the given docstring and class attributes.
fn new_exception_type<'py>(
    py: Python<'py>,
    name: &str,
    doc: &str,
    builtin: Bound<'py, PyType>,
    extra: Option<Bound<'py, PyDict>>,
) -> PyResult<Py<PyType>> {
    let namespace = extra.unwrap_or_else(|| PyDict::new(py));
    namespace.set_item("__module__", MODULE)?;
    namespace.set_item("__doc__", doc)?;
    let bases = PyTuple::new(py, [py.get_type::<CrepuscularError>(), builtin])?;
    let ty = py
        .get_type::<PyType>()
        .call1((name, bases, namespace))?
        .cast_into::<PyType>()?;
    Ok(ty.unbind())
}

/// Adds the exception classes to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = module.py();
    module.add("CrepuscularError", py.get_type::<CrepuscularError>())?;
    module.add("InvalidInputError", invalid_input_error(py)?)?;
    module.add("ExrError", exr_error(py)?)?;
    module.add("CancelledError", py.get_type::<CancelledError>())?;
    Ok(())
}

/// The one place a core error becomes a Python exception.
pub fn to_py_err(err: Error) -> PyErr {
    Python::attach(|py| {
        let message = err.to_string();
        let built = match err {
            Error::InvalidInput { field, .. } => invalid_input(py, &message, Some(&field)),
            Error::SceneFormat(text) => invalid_input(py, &message, format_error_field(&text)),
            Error::UnknownScene { .. } => invalid_input(py, &message, None),
            Error::Exr { path, .. } | Error::Png { path, .. } => {
                file_error(py, &message, &path, None)
            }
            Error::Io { path, source } => file_error(py, &message, &path, source.raw_os_error()),
            Error::Cancelled => Ok(CancelledError::new_err(message)),
            Error::Internal(_) | Error::Gpu(_) => Ok(CrepuscularError::new_err(message)),
        };
        // Building the exception itself can only fail on interpreter trouble (out of memory);
        // the error from that attempt is then the more useful one to raise.
        built.unwrap_or_else(|failure| failure)
    })
}

/// An `InvalidInputError` with its `field` set.
pub fn invalid_input(py: Python<'_>, message: &str, field: Option<&str>) -> PyResult<PyErr> {
    let instance = invalid_input_error(py)?.call1((message,))?;
    instance.setattr("field", field)?;
    Ok(PyErr::from_value(instance))
}

fn file_error(py: Python<'_>, message: &str, path: &Path, errno: Option<i32>) -> PyResult<PyErr> {
    let instance = exr_error(py)?.call1((message,))?;
    instance.setattr("filename", path.to_string_lossy())?;
    if let Some(errno) = errno {
        instance.setattr("errno", errno)?;
    }
    Ok(PyErr::from_value(instance))
}

/// The path in a parse error such as `at 'camera.foo': unknown field ...`.
fn format_error_field(text: &str) -> Option<&str> {
    let rest = text.strip_prefix("at '")?;
    let end = rest.find("':")?;
    Some(&rest[..end])
}

/// A panic on a worker thread, reported instead of crossing into Python.
pub fn internal_error(payload: &(dyn Any + Send)) -> PyErr {
    let detail = payload
        .downcast_ref::<&str>()
        .map(|text| text.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "the render thread panicked".to_string());
    to_py_err(Error::Internal(detail))
}
