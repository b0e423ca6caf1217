//! The Vulkan loader and instance, loaded at run time so that nothing links libvulkan at
//! build time and a machine without a loader gets a clean error.

use std::ffi::CStr;

use ash::vk;

use super::error::{GpuError, GpuResult, VkContext};

/// What the instance is created with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct InstanceDesc {
    pub application_name: &'static CStr,
    /// The Vulkan API version the backend is written against.
    pub api_version: u32,
}

impl InstanceDesc {
    /// Headless compute: no surface or window extensions.
    pub fn headless() -> Self {
        Self {
            application_name: c"crepuscular",
            api_version: vk::API_VERSION_1_1,
        }
    }
}

pub struct Instance {
    /// Keeps the loader library loaded for as long as the instance lives.
    pub entry: ash::Entry,
    pub raw: ash::Instance,
}

impl Instance {
    pub fn new(desc: &InstanceDesc) -> GpuResult<Self> {
        // SAFETY: loading the system's Vulkan loader runs its initialisers; that is the
        // documented way to use a loader that is not linked at build time.
        let entry =
            unsafe { ash::Entry::load() }.map_err(|err| GpuError::Loader(err.to_string()))?;
        // SAFETY: the entry is valid; the call takes no pointers from us.
        let available = unsafe { entry.try_enumerate_instance_version() }
            .call("vkEnumerateInstanceVersion")?
            .unwrap_or(vk::API_VERSION_1_0);
        if available < desc.api_version {
            return Err(GpuError::NoDevice(format!(
                "the Vulkan loader offers API {}.{}, the backend needs {}.{}",
                vk::api_version_major(available),
                vk::api_version_minor(available),
                vk::api_version_major(desc.api_version),
                vk::api_version_minor(desc.api_version),
            )));
        }
        let application = vk::ApplicationInfo::default()
            .application_name(desc.application_name)
            .engine_name(desc.application_name)
            .api_version(desc.api_version);
        let info = vk::InstanceCreateInfo::default().application_info(&application);
        // SAFETY: `info` and what it points to live until the call returns.
        let raw = unsafe { entry.create_instance(&info, None) }.call("vkCreateInstance")?;
        Ok(Self { entry, raw })
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: every object created from the instance is destroyed before it (the
        // device owns the instance and destroys itself first).
        unsafe { self.raw.destroy_instance(None) };
    }
}
