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
}
