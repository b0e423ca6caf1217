//! Buffers with their memory from gpu-allocator: device-local storage, and host-visible
//! staging for uploads and read-backs.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use super::device::Device;
use super::error::{GpuError, GpuResult, VkContext};
use super::host_time::{self, timed, HostWork};

/// Where a buffer lives and what it is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BufferRole {
    /// Device-local shader storage, filled and read through copies.
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
    pub desc: BufferDesc,
    allocation: Option<Allocation>,
    device: Arc<Device>,
}

impl Buffer {
    pub fn new(device: &Arc<Device>, desc: BufferDesc, name: &str) -> GpuResult<Buffer> {
        timed(HostWork::Allocation, || Self::create(device, desc, name))
    }

    fn create(device: &Arc<Device>, desc: BufferDesc, name: &str) -> GpuResult<Buffer> {
        let (usage, location, size) = desc.vk_usage();
        let info = vk::BufferCreateInfo::default()
            .size(size)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: the device is valid and `info` outlives the call.
        let raw = unsafe { device.raw.create_buffer(&info, None) }.call("vkCreateBuffer")?;
        // From here on, Drop destroys the buffer (and frees memory once it is bound).
        let mut buffer = Buffer {
            raw,
            desc,
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
                    what: format!("{name} ({size} bytes)"),
                    source,
                })
        })?;
        // SAFETY: the allocation satisfies the buffer's requirements.
        let bound = unsafe {
            device
                .raw
                .bind_buffer_memory(raw, allocation.memory(), allocation.offset())
        };
        buffer.allocation = Some(allocation);
        bound.call("vkBindBufferMemory")?;
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

    /// The contents of a host-visible buffer.
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

    /// Destroys the buffer and frees its memory (its `Drop`).
    fn release(&mut self) {
        // SAFETY: command buffers that use this buffer have completed (every submission
        // waits for its fence before its buffers can be dropped).
        unsafe { self.device.raw.destroy_buffer(self.raw, None) };
        if let Some(allocation) = self.allocation.take() {
            // A failure to free leaks the block until the allocator goes; nothing to report to.
            let _ = self.device.with_allocator(|allocator| {
                allocator
                    .free(allocation)
                    .map_err(|source| GpuError::Allocation {
                        what: "a freed buffer".to_owned(),
                        source,
                    })
            });
        }
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        timed(HostWork::Allocation, || self.release());
    }
}

/// Plain values that may be copied to and from GPU memory byte for byte.
pub trait Pod: Copy + 'static {}
impl Pod for u8 {}
impl Pod for f32 {}
impl Pod for u32 {}
impl Pod for i32 {}
impl Pod for [f32; 3] {}
impl Pod for [f32; 4] {}
impl Pod for [u32; 3] {}

pub fn as_bytes<T: Pod>(values: &[T]) -> &[u8] {
    // SAFETY: `Pod` types have no padding and no invalid bit patterns.
    unsafe { std::slice::from_raw_parts(values.as_ptr().cast(), std::mem::size_of_val(values)) }
}

/// Copies bytes into values (the source need not be aligned).
pub fn from_bytes<T: Pod + Default>(bytes: &[u8]) -> Vec<T> {
    let count = bytes.len() / std::mem::size_of::<T>();
    let mut values = vec![T::default(); count];
    // SAFETY: the destination holds exactly `count` values of `Pod` type.
    unsafe {
        std::ptr::copy_nonoverlapping(
            bytes.as_ptr(),
            values.as_mut_ptr().cast::<u8>(),
            count * std::mem::size_of::<T>(),
        )
    };
    values
}
