//! Physical devices: what each offers, and which one a backend request picks.

use ash::vk;

use super::error::{GpuError, GpuResult, VkContext};
use super::instance::Instance;

/// The kind of a physical device, as the driver reports it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DeviceKind {
    Discrete,
    Integrated,
    Virtual,
    /// A software rasterizer such as Mesa's lavapipe.
    Cpu,
    Other,
}

impl DeviceKind {
    pub fn from_vk(kind: vk::PhysicalDeviceType) -> Self {
        match kind {
            vk::PhysicalDeviceType::DISCRETE_GPU => DeviceKind::Discrete,
            vk::PhysicalDeviceType::INTEGRATED_GPU => DeviceKind::Integrated,
            vk::PhysicalDeviceType::VIRTUAL_GPU => DeviceKind::Virtual,
            vk::PhysicalDeviceType::CPU => DeviceKind::Cpu,
            _ => DeviceKind::Other,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DeviceKind::Discrete => "discrete GPU",
            DeviceKind::Integrated => "integrated GPU",
            DeviceKind::Virtual => "virtual GPU",
            DeviceKind::Cpu => "CPU implementation",
            DeviceKind::Other => "other device",
        }
    }
}

/// Which devices a request accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DevicePolicy {
    /// Real GPUs only (discrete first): what `--backend auto` uses. A software
    /// implementation is never faster than the CPU backend.
    HardwareOnly,
    /// Any device, real GPUs first: what an explicit `--backend vulkan` (and the parity
    /// tests on lavapipe) use.
    Any,
}

/// Index of the device `policy` picks among `kinds`, or `None`.
pub fn choose_device(kinds: &[DeviceKind], policy: DevicePolicy) -> Option<usize> {
    let rank = |kind: DeviceKind| match (kind, policy) {
        (DeviceKind::Discrete, _) => Some(0),
        (DeviceKind::Integrated, _) => Some(1),
        (_, DevicePolicy::HardwareOnly) => None,
        (DeviceKind::Virtual, DevicePolicy::Any) => Some(2),
        (DeviceKind::Other, DevicePolicy::Any) => Some(3),
        (DeviceKind::Cpu, DevicePolicy::Any) => Some(4),
    };
    kinds
        .iter()
        .enumerate()
        .filter_map(|(i, &kind)| rank(kind).map(|r| (r, i)))
        .min()
        .map(|(_, i)| i)
}

/// Index of the queue family to use: the first with compute and graphics, so that one
/// queue runs every stage, or else the first with compute.
pub fn choose_queue_family(families: &[vk::QueueFlags]) -> Option<usize> {
    let both = vk::QueueFlags::COMPUTE | vk::QueueFlags::GRAPHICS;
    families
        .iter()
        .position(|flags| flags.contains(both))
        .or_else(|| {
            families
                .iter()
                .position(|flags| flags.contains(vk::QueueFlags::COMPUTE))
        })
}

/// A physical device with the properties the backend uses.
#[derive(Clone, Debug)]
pub struct PhysicalDevice {
    pub raw: vk::PhysicalDevice,
    pub name: String,
    pub kind: DeviceKind,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period: f32,
    /// The queue family (compute, with graphics where a family offers both) and its valid
    /// timestamp bits (0: no timestamps).
    pub queue_family: u32,
    pub timestamp_valid_bits: u32,
    /// Whether the queue also runs graphics pipelines (the depth passes).
    pub graphics: bool,
    /// The largest render target: framebuffer and 2D image limits together.
    pub max_render_size: [u32; 2],
    pub max_viewport_dimensions: [u32; 2],
    /// The range viewport corners must lie in.
    pub viewport_bounds_range: [f32; 2],
    pub max_workgroup_count: [u32; 3],
    /// The most invocations a one-dimensional workgroup may have (Vulkan guarantees 128).
    pub max_workgroup_width: u32,
    pub max_storage_buffer_range: u32,
    /// Whether shaders may use double precision (silhouettes and hole creation place
    /// their samples in f64, as the CPU does).
    pub float64: bool,
    /// Whether shaders may read their subgroup's cycle counter (VK_KHR_shader_clock): the
    /// bench's clock probe.
    pub shader_clock: bool,
    /// The bytes of its device-local memory heaps: what bounds the buffers it keeps
    /// between frames ([`super::buffer_pool`]).
    pub device_local_bytes: u64,
}

impl PhysicalDevice {
    /// Every device with a compute queue.
    pub fn enumerate(instance: &Instance) -> GpuResult<Vec<PhysicalDevice>> {
        // SAFETY: the instance is valid for the duration of these queries.
        let raws = unsafe { instance.raw.enumerate_physical_devices() }
            .call("vkEnumeratePhysicalDevices")?;
        let mut devices = Vec::new();
        for raw in raws {
            // SAFETY: `raw` came from this instance.
            let properties = unsafe { instance.raw.get_physical_device_properties(raw) };
            // SAFETY: as above.
            let families = unsafe {
                instance
                    .raw
                    .get_physical_device_queue_family_properties(raw)
            };
            let Some(family) =
                choose_queue_family(&families.iter().map(|f| f.queue_flags).collect::<Vec<_>>())
            else {
                continue;
            };
            let queue = families[family];
            // SAFETY: as above.
            let features = unsafe { instance.raw.get_physical_device_features(raw) };
            let shader_clock = Self::has_shader_clock(instance, raw, properties.api_version);
            // SAFETY: as above.
            let memory = unsafe { instance.raw.get_physical_device_memory_properties(raw) };
            let device_local_bytes = memory
                .memory_heaps_as_slice()
                .iter()
                .filter(|heap| heap.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL))
                .map(|heap| heap.size)
                .sum();
            let name = properties
                .device_name_as_c_str()
                .map(|name| name.to_string_lossy().into_owned())
                .unwrap_or_else(|_| "unnamed device".to_owned());
            devices.push(PhysicalDevice {
                raw,
                name,
                kind: DeviceKind::from_vk(properties.device_type),
                timestamp_period: properties.limits.timestamp_period,
                queue_family: family as u32,
                timestamp_valid_bits: queue.timestamp_valid_bits,
                graphics: queue.queue_flags.contains(vk::QueueFlags::GRAPHICS),
                max_render_size: [
                    properties
                        .limits
                        .max_framebuffer_width
                        .min(properties.limits.max_image_dimension2_d),
                    properties
                        .limits
                        .max_framebuffer_height
                        .min(properties.limits.max_image_dimension2_d),
                ],
                max_viewport_dimensions: properties.limits.max_viewport_dimensions,
                viewport_bounds_range: properties.limits.viewport_bounds_range,
                max_workgroup_count: properties.limits.max_compute_work_group_count,
                max_workgroup_width: properties
                    .limits
                    .max_compute_work_group_invocations
                    .min(properties.limits.max_compute_work_group_size[0]),
                max_storage_buffer_range: properties.limits.max_storage_buffer_range,
                float64: features.shader_float64 == vk::TRUE,
                shader_clock,
                device_local_bytes,
            });
        }
        Ok(devices)
    }

    /// Whether `raw` offers VK_KHR_shader_clock with the subgroup clock. A failed query
    /// only means no clock probe.
    fn has_shader_clock(instance: &Instance, raw: vk::PhysicalDevice, api_version: u32) -> bool {
        if api_version < vk::API_VERSION_1_1 {
            return false;
        }
        // SAFETY: `raw` came from this instance.
        let extensions = unsafe { instance.raw.enumerate_device_extension_properties(raw) };
        let listed = extensions.is_ok_and(|extensions| {
            extensions.iter().any(|extension| {
                extension.extension_name_as_c_str() == Ok(ash::khr::shader_clock::NAME)
            })
        });
        if !listed {
            return false;
        }
        let mut clock = vk::PhysicalDeviceShaderClockFeaturesKHR::default();
        let mut features = vk::PhysicalDeviceFeatures2::default().push_next(&mut clock);
        // SAFETY: as above; the device supports Vulkan 1.1, and `features` chains only
        // structures of extensions it lists.
        unsafe {
            instance
                .raw
                .get_physical_device_features2(raw, &mut features)
        };
        clock.shader_subgroup_clock == vk::TRUE
    }

    /// The device `policy` picks, or an error listing what there is.
    pub fn select(instance: &Instance, policy: DevicePolicy) -> GpuResult<PhysicalDevice> {
        let devices = Self::enumerate(instance)?;
        let kinds: Vec<DeviceKind> = devices.iter().map(|d| d.kind).collect();
        match choose_device(&kinds, policy) {
            Some(index) => Ok(devices[index].clone()),
            None if devices.is_empty() => Err(GpuError::NoDevice(
                "the Vulkan loader lists no device with a compute queue".to_owned(),
            )),
            None => Err(GpuError::NoDevice(format!(
                "only {} present, and automatic selection takes real GPUs only",
                devices
                    .iter()
                    .map(|d| format!("{} ({})", d.name, d.kind.name()))
                    .collect::<Vec<_>>()
                    .join(", ")
            ))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use DeviceKind::*;

    #[test]
    fn automatic_selection_never_takes_a_cpu_device() {
        assert_eq!(choose_device(&[Cpu], DevicePolicy::HardwareOnly), None);
        assert_eq!(
            choose_device(&[Cpu, Virtual, Other], DevicePolicy::HardwareOnly),
            None
        );
        assert_eq!(
            choose_device(&[Cpu, Integrated], DevicePolicy::HardwareOnly),
            Some(1)
        );
        assert_eq!(choose_device(&[], DevicePolicy::HardwareOnly), None);
    }

    #[test]
    fn discrete_gpus_come_first() {
        assert_eq!(
            choose_device(&[Cpu, Integrated, Discrete], DevicePolicy::HardwareOnly),
            Some(2)
        );
        assert_eq!(
            choose_device(&[Integrated, Discrete, Cpu], DevicePolicy::Any),
            Some(1)
        );
    }

    #[test]
    fn the_queue_family_runs_graphics_where_one_can() {
        let compute = vk::QueueFlags::COMPUTE | vk::QueueFlags::TRANSFER;
        let both = vk::QueueFlags::COMPUTE | vk::QueueFlags::GRAPHICS;
        assert_eq!(choose_queue_family(&[compute, both]), Some(1));
        assert_eq!(
            choose_queue_family(&[vk::QueueFlags::TRANSFER, compute]),
            Some(1)
        );
        assert_eq!(choose_queue_family(&[vk::QueueFlags::GRAPHICS]), None);
    }

    #[test]
    fn an_explicit_request_takes_lavapipe_when_it_is_all_there_is() {
        assert_eq!(choose_device(&[Cpu], DevicePolicy::Any), Some(0));
        assert_eq!(choose_device(&[Cpu, Virtual], DevicePolicy::Any), Some(1));
    }
}
