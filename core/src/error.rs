//! The crate's one error type. Every variant names what was wrong so that hosts
//! (CLI, Python, Blender) can show it to the user unchanged.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A value the caller gave is unusable; `field` is its path in the scene description.
    #[error("invalid {field}: {reason}")]
    InvalidInput { field: String, reason: String },

    /// The scene description could not be parsed (syntax, unknown key, wrong type).
    #[error("scene description: {0}")]
    SceneFormat(String),

    #[error("unknown built-in scene '{name}' (available: {available})")]
    UnknownScene { name: String, available: String },

    #[error("EXR file {path}: {reason}")]
    Exr { path: PathBuf, reason: String },

    #[error("PNG file {path}: {reason}")]
    Png { path: PathBuf, reason: String },

    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("render cancelled")]
    Cancelled,

    /// The Vulkan backend failed; hosts fall back to the CPU backend.
    #[error("Vulkan backend: {0}")]
    Gpu(#[from] crate::gpu::GpuError),

    /// A bug: a worker panicked. The panic was caught so that the host keeps running.
    #[error("internal error: {0}")]
    Internal(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidInput {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// A buffer the render settings size (`gib` of it) that could not be allocated: the
    /// settings that size the rectified data are named, as the values to change.
    pub fn out_of_memory(what: &str, gib: f64) -> Self {
        Error::invalid(
            "render",
            format!(
                "{what} needs {gib:.1} GiB, more memory than could be allocated; lower \
                 render.epipolar_slices or render.shadow_map_size (for the prefiltered \
                 method also render.bases, or render.basis_storage 'snorm16')"
            ),
        )
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }
}
