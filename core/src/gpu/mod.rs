//! The Vulkan backend (ash): headless compute and depth-only graphics on a device loaded
//! at run time, running the frame's stages from the GLSL shaders in `shaders/`. The CPU
//! backend stays the oracle; [`frame`] says which stages run where.
//!
//! One file per Vulkan concept: [`instance`], [`physical_device`], [`device`], [`buffer`],
//! [`buffer_pool`] (buffers kept between frames), [`image`], [`shader`],
//! [`compute_pipeline`], [`graphics_pipeline`] (render passes and framebuffers),
//! [`command`] (recording and submission), [`barrier`], [`query`] (timestamps),
//! [`layer_buffers`] (the layers' device buffers and read-back), [`host_time`] (host-side
//! time by kind of work), [`dispatch`] (workgroup counts and parameter packing), and one
//! per ported stage: [`raster`] (shadow map and camera depth), [`march`], [`morphology`],
//! [`silhouette`], [`holes`], [`transfer`], [`prefix`], [`prefiltered`], [`upsample`],
//! [`rectify`]; and [`clock`], the bench's probe of the shader cores' clock rate.

pub mod barrier;
pub mod buffer;
pub mod buffer_pool;
pub mod clock;
pub mod command;
pub mod compute_pipeline;
pub mod device;
pub mod dispatch;
pub mod error;
pub mod frame;
pub mod graphics_pipeline;
pub mod holes;
pub mod host_time;
pub mod image;
pub mod instance;
pub mod layer_buffers;
pub mod march;
pub mod morphology;
pub mod physical_device;
pub mod prefiltered;
pub mod prefix;
pub mod query;
pub mod raster;
pub mod rectify;
pub mod shader;
pub mod silhouette;
pub mod transfer;
pub mod upsample;

use std::sync::{Arc, Mutex};

pub use device::Device;
pub use error::{GpuError, GpuResult};
pub use physical_device::{DeviceKind, DevicePolicy};

/// The process-wide device per policy, opened on first use; a failure is remembered, so
/// that a machine without Vulkan pays for the probe once.
pub fn shared_device(policy: DevicePolicy) -> GpuResult<Arc<Device>> {
    type Slot = Mutex<Option<Result<Arc<Device>, String>>>;
    static HARDWARE: Slot = Mutex::new(None);
    static ANY: Slot = Mutex::new(None);
    let slot = match policy {
        DevicePolicy::HardwareOnly => &HARDWARE,
        DevicePolicy::Any => &ANY,
    };
    let mut guard = slot.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let entry = guard.get_or_insert_with(|| Device::new(policy).map_err(|err| err.to_string()));
    match entry {
        Ok(device) => Ok(device.clone()),
        Err(reason) => Err(GpuError::Unavailable(reason.clone())),
    }
}
