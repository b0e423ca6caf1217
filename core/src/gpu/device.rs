//! The logical device: one queue (compute, and graphics where the device has it), the
//! memory allocator, the buffers kept between frames, and the caches of compute and
//! graphics pipelines. Shared as `Arc<Device>`; everything created from it is destroyed
//! first.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use super::buffer::{BufferRole, KeptBuffer};
use super::buffer_pool::{kept_bytes_limit, BufferPool};
use super::compute_pipeline::{ComputePipeline, ComputePipelineDesc};
use super::error::{GpuError, GpuResult, VkContext};
use super::graphics_pipeline::{GraphicsPipeline, GraphicsPipelineDesc};
use super::instance::{Instance, InstanceDesc};
use super::physical_device::{DevicePolicy, PhysicalDevice};

pub struct Device {
    pub raw: ash::Device,
    pub physical: PhysicalDevice,
    pub queue: vk::Queue,
    /// Submissions to the queue need external synchronisation.
    queue_lock: Mutex<()>,
    /// `None` only while the device is being dropped.
    allocator: Mutex<Option<Allocator>>,
    kept_buffers: Mutex<BufferPool<KeptBuffer>>,
    pipelines: Mutex<HashMap<ComputePipelineDesc, Arc<ComputePipeline>>>,
    graphics_pipelines: Mutex<HashMap<GraphicsPipelineDesc, Arc<GraphicsPipeline>>>,
    /// Declared last: dropped after the device is destroyed.
    pub instance: Instance,
}

impl Device {
    /// Loads Vulkan and opens the device that `policy` picks.
    pub fn new(policy: DevicePolicy) -> GpuResult<Arc<Device>> {
        let instance = Instance::new(&InstanceDesc::headless())?;
        let physical = PhysicalDevice::select(&instance, policy)?;
        let priorities = [1.0f32];
        let queue_info = vk::DeviceQueueCreateInfo::default()
            .queue_family_index(physical.queue_family)
            .queue_priorities(&priorities);
        let features = vk::PhysicalDeviceFeatures::default().shader_float64(physical.float64);
        let mut clock =
            vk::PhysicalDeviceShaderClockFeaturesKHR::default().shader_subgroup_clock(true);
        let clock_extension = [ash::khr::shader_clock::NAME.as_ptr()];
        let mut info = vk::DeviceCreateInfo::default()
            .queue_create_infos(std::slice::from_ref(&queue_info))
            .enabled_features(&features);
        if physical.shader_clock {
            info = info
                .enabled_extension_names(&clock_extension)
                .push_next(&mut clock);
        }
        // SAFETY: `physical.raw` belongs to `instance`; `info` outlives the call.
        let raw = unsafe { instance.raw.create_device(physical.raw, &info, None) }
            .call("vkCreateDevice")?;
        // SAFETY: the queue family and index were requested above.
        let queue = unsafe { raw.get_device_queue(physical.queue_family, 0) };
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.raw.clone(),
            device: raw.clone(),
            physical_device: physical.raw,
            debug_settings: Default::default(),
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        });
        let allocator = match allocator {
            Ok(allocator) => allocator,
            Err(source) => {
                // SAFETY: nothing was created from the device yet.
                unsafe { raw.destroy_device(None) };
                return Err(GpuError::Allocation {
                    what: "the allocator".to_owned(),
                    source,
                });
            }
        };
        let kept_limit = kept_bytes_limit(physical.device_local_bytes);
        Ok(Arc::new(Device {
            raw,
            physical,
            queue,
            queue_lock: Mutex::new(()),
            allocator: Mutex::new(Some(allocator)),
            kept_buffers: Mutex::new(BufferPool::new(kept_limit)),
            pipelines: Mutex::new(HashMap::new()),
            graphics_pipelines: Mutex::new(HashMap::new()),
            instance,
        }))
    }

    /// Runs `f` with the allocator.
    pub(crate) fn with_allocator<T>(
        &self,
        f: impl FnOnce(&mut Allocator) -> GpuResult<T>,
    ) -> GpuResult<T> {
        let mut guard = lock(&self.allocator);
        match guard.as_mut() {
            Some(allocator) => f(allocator),
            None => Err(GpuError::Unsupported(
                "the device is shutting down".to_owned(),
            )),
        }
    }

    /// A buffer kept of `role` and `capacity`, if there is one.
    pub(crate) fn take_kept_buffer(&self, role: BufferRole, capacity: u64) -> Option<KeptBuffer> {
        lock(&self.kept_buffers).take(role, capacity)
    }

    /// Keeps a released buffer for the next request of its role and capacity, releasing
    /// what no longer fits the limit.
    pub(crate) fn keep_buffer(&self, role: BufferRole, capacity: u64, buffer: KeptBuffer) {
        let released = lock(&self.kept_buffers).keep(role, capacity, buffer);
        for buffer in released {
            self.release_buffer(buffer);
        }
    }

    /// The bytes of the buffers kept now.
    pub fn kept_buffer_bytes(&self) -> u64 {
        lock(&self.kept_buffers).kept_bytes()
    }

    /// Destroys a buffer that no command buffer uses any more, and frees its memory.
    pub(crate) fn release_buffer(&self, buffer: KeptBuffer) {
        // SAFETY: the buffer was created from this device, and its last submission has
        // completed (see `Buffer`'s Drop).
        unsafe { self.raw.destroy_buffer(buffer.raw, None) };
        // A failure to free leaks the block until the allocator goes; nothing to report to.
        let _ = self.with_allocator(|allocator| {
            allocator
                .free(buffer.allocation)
                .map_err(|source| GpuError::Allocation {
                    what: "a released buffer".to_owned(),
                    source,
                })
        });
    }

    pub(crate) fn queue_guard(&self) -> MutexGuard<'_, ()> {
        lock(&self.queue_lock)
    }

    /// The pipeline for `desc`, created on first use.
    pub fn pipeline(&self, desc: &ComputePipelineDesc) -> GpuResult<Arc<ComputePipeline>> {
        let mut pipelines = lock(&self.pipelines);
        if let Some(pipeline) = pipelines.get(desc) {
            return Ok(pipeline.clone());
        }
        let pipeline = Arc::new(ComputePipeline::new(&self.raw, desc)?);
        pipelines.insert(*desc, pipeline.clone());
        Ok(pipeline)
    }

    /// The graphics pipeline for `desc`, created on first use.
    pub fn graphics_pipeline(
        &self,
        desc: &GraphicsPipelineDesc,
    ) -> GpuResult<Arc<GraphicsPipeline>> {
        if !self.physical.graphics {
            return Err(GpuError::Unsupported(
                "graphics pipelines on a queue without graphics".to_owned(),
            ));
        }
        let mut pipelines = lock(&self.graphics_pipelines);
        if let Some(pipeline) = pipelines.get(desc) {
            return Ok(pipeline.clone());
        }
        let pipeline = Arc::new(GraphicsPipeline::new(&self.raw, desc)?);
        pipelines.insert(*desc, pipeline.clone());
        Ok(pipeline)
    }

    /// A line naming the device, for messages and bench output.
    pub fn describe(&self) -> String {
        format!("{} ({})", self.physical.name, self.physical.kind.name())
    }
}

/// A poisoned lock only means another thread panicked while holding it; the data it
/// guards (handles) stay valid.
fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Drop for Device {
    fn drop(&mut self) {
        // SAFETY: no other reference to the device exists any more (we are in its Drop),
        // so nothing is recording or submitting; waiting lets queued work finish.
        unsafe {
            let _ = self.raw.device_wait_idle();
        }
        for (_, pipeline) in lock(&self.pipelines).drain() {
            pipeline.destroy(&self.raw);
        }
        for (_, pipeline) in lock(&self.graphics_pipelines).drain() {
            pipeline.destroy(&self.raw);
        }
        let kept = lock(&self.kept_buffers).drain();
        for buffer in kept {
            self.release_buffer(buffer);
        }
        // The allocator frees its memory blocks through the device, so it goes first.
        drop(lock(&self.allocator).take());
        // SAFETY: every child object is destroyed above or by its owner's Drop, which
        // holds an `Arc<Device>` and so ran before this.
        unsafe { self.raw.destroy_device(None) };
    }
}
