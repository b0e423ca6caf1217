//! Buffers with their memory from gpu-allocator: device-local storage, and host-visible
//! staging for uploads and read-backs.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use super::buffer_pool::pooled_capacity;
use super::device::Device;
use super::error::{GpuError, GpuResult, VkContext};
use super::host_time::{self, timed, HostWork};

/// Where a buffer lives and what it is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BufferRole {
    /// Device-local shader storage, filled and read through copies; shaders may also
    /// write an indirect dispatch's workgroup counts into it.
    Storage,
    /// Host-visible, written by the CPU and copied to storage.
    Upload,
    /// Host-visible, copied into from storage and read by the CPU.
    Readback,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BufferDesc {
    pub size: u64,
    pub role: BufferRole,
}

impl BufferDesc {
    pub fn storage(size: u64) -> Self {
        Self {
            size,
            role: BufferRole::Storage,
        }
    }

    pub fn upload(size: u64) -> Self {
        Self {
            size,
            role: BufferRole::Upload,
        }
    }

    pub fn readback(size: u64) -> Self {
        Self {
            size,
            role: BufferRole::Readback,
        }
    }

    /// Vulkan usage flags and memory location for the role. Zero-sized buffers are
    /// invalid in Vulkan, so the size is at least 4 bytes.
    pub fn vk_usage(&self) -> (vk::BufferUsageFlags, MemoryLocation, u64) {
        let size = self.size.max(4);
        match self.role {
            BufferRole::Storage => (
                vk::BufferUsageFlags::STORAGE_BUFFER
                    | vk::BufferUsageFlags::INDIRECT_BUFFER
                    | vk::BufferUsageFlags::TRANSFER_SRC
                    | vk::BufferUsageFlags::TRANSFER_DST,
                MemoryLocation::GpuOnly,
                size,
            ),
            BufferRole::Upload => (
                vk::BufferUsageFlags::TRANSFER_SRC,
                MemoryLocation::CpuToGpu,
                size,
            ),
            BufferRole::Readback => (
                vk::BufferUsageFlags::TRANSFER_DST,
                MemoryLocation::GpuToCpu,
                size,
            ),
        }
    }
}

pub struct Buffer {
    pub raw: vk::Buffer,
    /// What was asked for; the buffer may be larger ([`Buffer::capacity`]).
    pub desc: BufferDesc,
    capacity: u64,
    allocation: Option<Allocation>,
    device: Arc<Device>,
}

/// A released buffer with its memory, kept by the device for the next request of its
/// role and capacity ([`super::buffer_pool`]).
pub struct KeptBuffer {
    pub raw: vk::Buffer,
    pub allocation: Allocation,
}

impl Buffer {
    /// A buffer for `desc`: one the device kept of its role and capacity, or a new one.
    /// A kept buffer's contents are whatever its last user left.
    pub fn new(device: &Arc<Device>, desc: BufferDesc, name: &str) -> GpuResult<Buffer> {
        timed(HostWork::Allocation, || {
            let capacity = pooled_capacity(desc.vk_usage().2);
            match device.take_kept_buffer(desc.role, capacity) {
                Some(kept) => Ok(Buffer {
                    raw: kept.raw,
                    desc,
                    capacity,
                    allocation: Some(kept.allocation),
                    device: device.clone(),
                }),
                None => Self::create(device, desc, capacity, name),
            }
        })
    }

    fn create(
        device: &Arc<Device>,
        desc: BufferDesc,
        capacity: u64,
        name: &str,
    ) -> GpuResult<Buffer> {
        let (usage, location, _) = desc.vk_usage();
        let info = vk::BufferCreateInfo::default()
            .size(capacity)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: the device is valid and `info` outlives the call.
        let raw = unsafe { device.raw.create_buffer(&info, None) }.call("vkCreateBuffer")?;
        // From here on, Drop destroys the buffer (and frees memory once it is bound).
        let mut buffer = Buffer {
            raw,
            desc,
            capacity,
            allocation: None,
            device: device.clone(),
        };
        // SAFETY: `raw` was just created from this device.
        let requirements = unsafe { device.raw.get_buffer_memory_requirements(raw) };
        let allocation = device.with_allocator(|allocator| {
            allocator
                .allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location,
                    linear: true,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                })
                .map_err(|source| GpuError::Allocation {
                    what: format!("{name} ({capacity} bytes)"),
                    source,
                })
        })?;
        // SAFETY: the allocation satisfies the buffer's requirements.
        let bound = unsafe {
            device
                .raw
                .bind_buffer_memory(raw, allocation.memory(), allocation.offset())
        };
        if let Err(err) = bound.call("vkBindBufferMemory") {
            // Not kept: a buffer whose binding failed is released with its memory.
            device.release_buffer(KeptBuffer { raw, allocation });
            buffer.raw = vk::Buffer::null();
            return Err(err);
        }
        buffer.allocation = Some(allocation);
        Ok(buffer)
    }

    /// Writes `bytes` at the start of a host-visible buffer.
    pub fn write(&mut self, bytes: &[u8]) -> GpuResult<()> {
        let size = self.desc.size;
        let mapped = self
            .allocation
            .as_mut()
            .and_then(|a| a.mapped_slice_mut())
            .ok_or_else(|| {
                GpuError::Unsupported("writing to a buffer the CPU cannot map".into())
            })?;
        if bytes.len() as u64 > size {
            return Err(GpuError::Unsupported(format!(
                "writing {} bytes into a {size}-byte buffer",
                bytes.len()
            )));
        }
        timed(HostWork::Writes, || {
            mapped[..bytes.len()].copy_from_slice(bytes)
        });
        host_time::count_written(bytes.len());
        Ok(())
    }

    /// The contents of a host-visible buffer, as far as its desc's size.
    pub fn read(&self) -> GpuResult<&[u8]> {
        let size = self.desc.size as usize;
        self.allocation
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .map(|bytes| &bytes[..size])
            .ok_or_else(|| GpuError::Unsupported("reading a buffer the CPU cannot map".into()))
    }

    pub fn size(&self) -> u64 {
        self.desc.size
    }

    /// The bytes the buffer really has: its size rounded up to what the device keeps.
    pub fn capacity(&self) -> u64 {
        self.capacity
    }

    /// The range a descriptor binds: the size asked for (at least 4 bytes, as created).
    pub fn bound_size(&self) -> u64 {
        self.desc.vk_usage().2
    }
}

impl Drop for Buffer {
    /// Hands the buffer to the device to keep. Command buffers that use it have completed:
    /// every submission waits for its fence before its buffers can be dropped.
    fn drop(&mut self) {
        timed(HostWork::Allocation, || match self.allocation.take() {
            Some(allocation) => self.device.keep_buffer(
                self.desc.role,
                self.capacity,
                KeptBuffer {
                    raw: self.raw,
                    allocation,
                },
            ),
            None if self.raw != vk::Buffer::null() => {
                // SAFETY: created from this device, never bound, never used.
                unsafe { self.device.raw.destroy_buffer(self.raw, None) };
            }
            None => {}
        });
    }
}

/// Plain values that may be copied to and from GPU memory byte for byte.
pub trait Pod: Copy + 'static {}
impl Pod for u8 {}
impl Pod for f32 {}
impl Pod for u32 {}
impl Pod for i32 {}
impl Pod for [f32; 2] {}
impl Pod for [f32; 3] {}
impl Pod for [f32; 4] {}
impl Pod for [u32; 3] {}
impl Pod for [u32; 4] {}

pub fn as_bytes<T: Pod>(values: &[T]) -> &[u8] {
    // SAFETY: `Pod` types have no padding and no invalid bit patterns.
    unsafe { std::slice::from_raw_parts(values.as_ptr().cast(), std::mem::size_of_val(values)) }
}

/// Copies bytes into values (the source need not be aligned).
pub fn from_bytes<T: Pod + Default>(bytes: &[u8]) -> Vec<T> {
    let mut values = vec![T::default(); bytes.len() / std::mem::size_of::<T>()];
    copy_from_bytes(bytes, &mut values);
    values
}

/// Copies the first `size_of_val(values)` bytes into `values` (the source need not be
/// aligned). Panics where there are fewer bytes.
pub fn copy_from_bytes<T: Pod>(bytes: &[u8], values: &mut [T]) {
    let size = std::mem::size_of_val(values);
    assert!(bytes.len() >= size, "{} bytes for {size}", bytes.len());
    // SAFETY: the destination holds exactly `size` bytes of `Pod` values, and the source
    // at least as many.
    unsafe {
        std::ptr::copy_nonoverlapping(bytes.as_ptr(), values.as_mut_ptr().cast::<u8>(), size)
    };
}
