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
    Gpu(crate::gpu::GpuError),

    /// A bug: a worker panicked. The panic was caught so that the host keeps running.
    #[error("internal error: {0}")]
    Internal(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Which settings size a frame's buffer: what [`Error::out_of_memory`] asks to lower.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Sizing {
    /// The shadow map, the rectified map and what the methods build over them.
    Rectified,
    /// The image: the camera depth, the layers and adaptive shading's grids.
    Image,
}

impl From<crate::gpu::GpuError> for Error {
    /// The backend's error, except the host's own that it carried ([`GpuError::Host`]).
    ///
    /// [`GpuError::Host`]: crate::gpu::GpuError::Host
    fn from(error: crate::gpu::GpuError) -> Self {
        match error {
            crate::gpu::GpuError::Host(error) => *error,
            other => Error::Gpu(other),
        }
    }
}

impl Error {
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidInput {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// A buffer (`gib` of it) that could not be allocated: the settings that size it are
    /// named, as the values to change.
    pub fn out_of_memory(what: &str, gib: f64, sizing: Sizing) -> Self {
        let (field, lower) = match sizing {
            Sizing::Rectified => (
                "render",
                "render.epipolar_slices or render.shadow_map_size (for the prefiltered method \
                 also render.bases, or render.basis_storage 'snorm16')",
            ),
            Sizing::Image => (
                "camera",
                "camera.width and camera.height, or render.supersampling",
            ),
        };
        Error::invalid(
            field,
            format!(
                "{what} needs {gib:.1} GiB, more memory than could be allocated; lower {lower}"
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
