//! The Vulkan backend's error type: every variant says which call or stage failed.

use ash::vk;

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// The Vulkan loader library could not be loaded (no `libvulkan.so.1`).
    #[error("no Vulkan loader: {0}")]
    Loader(String),

    /// The loader works but offers no device that the request accepts.
    #[error("no usable Vulkan device: {0}")]
    NoDevice(String),

    /// An earlier attempt to open a device failed, for the reason given.
    #[error("{0}")]
    Unavailable(String),

    /// A Vulkan call returned an error.
    #[error("{call} failed: {result}")]
    Vulkan {
        call: &'static str,
        result: vk::Result,
    },

    /// The device was lost (driver reset, hang, removal) while a stage ran.
    #[error("the GPU was lost while running the {stage} stage ({call})")]
    DeviceLost { stage: String, call: &'static str },

    #[error("GPU memory for {what}: {source}")]
    Allocation {
        what: String,
        #[source]
        source: gpu_allocator::AllocationError,
    },

    #[error("shader {name}: {reason}")]
    Shader { name: &'static str, reason: String },

    /// The request exceeds what the device or this backend supports.
    #[error("unsupported: {0}")]
    Unsupported(String),

    /// The host failed, not the GPU: memory for the frame's results could not be
    /// allocated. It reaches the caller as the core's own error, without a fallback to the
    /// CPU backend, which would need the same memory.
    #[error("{0}")]
    Host(Box<crate::error::Error>),
}

impl From<vk::Result> for GpuError {
    fn from(result: vk::Result) -> Self {
        GpuError::Vulkan {
            call: "a Vulkan call",
            result,
        }
    }
}

impl GpuError {
    /// The host's `error`, carried through the backend ([`GpuError::Host`]).
    pub fn host(error: crate::error::Error) -> Self {
        GpuError::Host(Box::new(error))
    }

    /// Names the stage that was running; a lost device becomes [`GpuError::DeviceLost`].
    pub fn in_stage(self, stage: &str) -> Self {
        match self {
            GpuError::Vulkan {
                call,
                result: vk::Result::ERROR_DEVICE_LOST,
            } => GpuError::DeviceLost {
                stage: stage.to_owned(),
                call,
            },
            other => other,
        }
    }
}

/// Adds the name of the failed call to a raw Vulkan result.
pub trait VkContext<T> {
    fn call(self, call: &'static str) -> Result<T, GpuError>;
}

impl<T> VkContext<T> for Result<T, vk::Result> {
    fn call(self, call: &'static str) -> Result<T, GpuError> {
        self.map_err(|result| GpuError::Vulkan { call, result })
    }
}

pub type GpuResult<T> = Result<T, GpuError>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_lost_names_the_stage_and_the_call() {
        let err = Err::<(), _>(vk::Result::ERROR_DEVICE_LOST)
            .call("vkWaitForFences")
            .unwrap_err()
            .in_stage("reference ray march");
        let text = err.to_string();
        assert!(text.contains("reference ray march"), "{text}");
        assert!(text.contains("vkWaitForFences"), "{text}");
        assert!(matches!(err, GpuError::DeviceLost { .. }));
    }

    #[test]
    fn other_results_keep_their_call() {
        let err = Err::<(), _>(vk::Result::ERROR_OUT_OF_DEVICE_MEMORY)
            .call("vkAllocateMemory")
            .unwrap_err()
            .in_stage("transfer function");
        assert!(matches!(
            err,
            GpuError::Vulkan {
                call: "vkAllocateMemory",
                ..
            }
        ));
    }

    /// The host's own error leaves the backend as itself, so that it is not taken for a
    /// GPU failure and rendered again on the CPU; the backend's own become `Error::Gpu`.
    #[test]
    fn the_hosts_error_leaves_the_backend_as_itself() {
        use crate::error::Error;
        let host = Error::invalid("camera", "the volume layer needs 4.0 GiB");
        match Error::from(GpuError::host(host).in_stage("upsampling")) {
            Error::InvalidInput { field, reason } => {
                assert_eq!(
                    (field.as_str(), reason.as_str()),
                    ("camera", "the volume layer needs 4.0 GiB")
                );
            }
            other => panic!("expected the host's error, got {other:?}"),
        }
        let unsupported = GpuError::Unsupported("a test".into());
        assert!(matches!(
            Error::from(unsupported),
            Error::Gpu(GpuError::Unsupported(_))
        ));
    }
}
