//! 2D images with one view, for render-pass attachments: a depth image or an R32_UINT
//! colour image, rendered once and copied to a buffer. Memory comes from gpu-allocator,
//! like [`super::buffer`]'s.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use super::device::Device;
use super::error::{GpuError, GpuResult, VkContext};

/// What an attachment holds; every kind can also be copied to a buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ImageRole {
    /// A depth attachment, D32_SFLOAT.
    Depth,
    /// A colour attachment of unsigned integers (object ids), R32_UINT.
    Ids,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ImageDesc {
    pub width: u32,
    pub height: u32,
    pub role: ImageRole,
}

impl ImageDesc {
    pub fn depth(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            role: ImageRole::Depth,
        }
    }

    pub fn ids(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            role: ImageRole::Ids,
        }
    }

    pub fn format(&self) -> vk::Format {
        match self.role {
            ImageRole::Depth => vk::Format::D32_SFLOAT,
            ImageRole::Ids => vk::Format::R32_UINT,
        }
    }

    pub fn aspect(&self) -> vk::ImageAspectFlags {
        match self.role {
            ImageRole::Depth => vk::ImageAspectFlags::DEPTH,
            ImageRole::Ids => vk::ImageAspectFlags::COLOR,
        }
    }

    pub fn usage(&self) -> vk::ImageUsageFlags {
        let attachment = match self.role {
            ImageRole::Depth => vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT,
            ImageRole::Ids => vk::ImageUsageFlags::COLOR_ATTACHMENT,
        };
        attachment | vk::ImageUsageFlags::TRANSFER_SRC
    }

    /// The format features the device must offer for optimal tiling.
    pub fn required_features(&self) -> vk::FormatFeatureFlags {
        let attachment = match self.role {
            ImageRole::Depth => vk::FormatFeatureFlags::DEPTH_STENCIL_ATTACHMENT,
            ImageRole::Ids => vk::FormatFeatureFlags::COLOR_ATTACHMENT,
        };
        attachment | vk::FormatFeatureFlags::TRANSFER_SRC
    }

    /// Bytes per texel, as copied to a buffer (both formats are 32-bit).
    pub fn texel_bytes(&self) -> u64 {
        4
    }

    /// Bytes of the whole image copied tightly to a buffer.
    pub fn buffer_bytes(&self) -> u64 {
        self.width as u64 * self.height as u64 * self.texel_bytes()
    }

    pub fn subresource_range(&self) -> vk::ImageSubresourceRange {
        vk::ImageSubresourceRange::default()
            .aspect_mask(self.aspect())
            .base_mip_level(0)
            .level_count(1)
            .base_array_layer(0)
            .layer_count(1)
    }

    /// A copy of the whole image to the start of a buffer, rows tightly packed.
    pub fn copy_to_buffer_region(&self) -> vk::BufferImageCopy {
        vk::BufferImageCopy::default()
            .buffer_offset(0)
            .buffer_row_length(0)
            .buffer_image_height(0)
            .image_subresource(
                vk::ImageSubresourceLayers::default()
                    .aspect_mask(self.aspect())
                    .mip_level(0)
                    .base_array_layer(0)
                    .layer_count(1),
            )
            .image_extent(vk::Extent3D {
                width: self.width,
                height: self.height,
                depth: 1,
            })
    }
}

pub struct Image {
    pub raw: vk::Image,
    pub view: vk::ImageView,
    pub desc: ImageDesc,
    allocation: Option<Allocation>,
    device: Arc<Device>,
}

impl Image {
    pub fn new(device: &Arc<Device>, desc: ImageDesc, name: &str) -> GpuResult<Image> {
        check_format(device, &desc)?;
        let info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(desc.format())
            .extent(vk::Extent3D {
                width: desc.width,
                height: desc.height,
                depth: 1,
            })
            .mip_levels(1)
            .array_layers(1)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(desc.usage())
            .sharing_mode(vk::SharingMode::EXCLUSIVE)
            .initial_layout(vk::ImageLayout::UNDEFINED);
        // SAFETY: the device is valid and `info` outlives the call.
        let raw = unsafe { device.raw.create_image(&info, None) }.call("vkCreateImage")?;
        // From here on, Drop destroys the image, its view and its memory as they exist.
        let mut image = Image {
            raw,
            view: vk::ImageView::null(),
            desc,
            allocation: None,
            device: device.clone(),
        };
        // SAFETY: `raw` was just created from this device.
        let requirements = unsafe { device.raw.get_image_memory_requirements(raw) };
        let allocation = device.with_allocator(|allocator| {
            allocator
                .allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location: MemoryLocation::GpuOnly,
                    linear: false,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                })
                .map_err(|source| GpuError::Allocation {
                    what: format!("{name} ({}×{} image)", desc.width, desc.height),
                    source,
                })
        })?;
        // SAFETY: the allocation satisfies the image's requirements.
        let bound = unsafe {
            device
                .raw
                .bind_image_memory(raw, allocation.memory(), allocation.offset())
        };
        image.allocation = Some(allocation);
        bound.call("vkBindImageMemory")?;
        let view_info = vk::ImageViewCreateInfo::default()
            .image(raw)
            .view_type(vk::ImageViewType::TYPE_2D)
            .format(desc.format())
            .subresource_range(desc.subresource_range());
        // SAFETY: the image is bound to memory; `view_info` outlives the call.
        image.view =
            unsafe { device.raw.create_image_view(&view_info, None) }.call("vkCreateImageView")?;
        Ok(image)
    }
}

/// Fails with [`GpuError::Unsupported`] when the device cannot render `desc`'s format.
fn check_format(device: &Device, desc: &ImageDesc) -> GpuResult<()> {
    // SAFETY: the physical device belongs to the device's instance.
    let properties = unsafe {
        device
            .instance
            .raw
            .get_physical_device_format_properties(device.physical.raw, desc.format())
    };
    let required = desc.required_features();
    if properties.optimal_tiling_features.contains(required) {
        Ok(())
    } else {
        Err(GpuError::Unsupported(format!(
            "{:?} images with {required:?}",
            desc.format()
        )))
    }
}

impl Drop for Image {
    fn drop(&mut self) {
        // SAFETY: command buffers that use this image have completed (images are created
        // before the recorder that uses them, so its Drop waits first).
        unsafe {
            if self.view != vk::ImageView::null() {
                self.device.raw.destroy_image_view(self.view, None);
            }
            self.device.raw.destroy_image(self.raw, None);
        }
        if let Some(allocation) = self.allocation.take() {
            // A failure to free leaks the block until the allocator goes; nothing to report to.
            let _ = self.device.with_allocator(|allocator| {
                allocator
                    .free(allocation)
                    .map_err(|source| GpuError::Allocation {
                        what: "a freed image".to_owned(),
                        source,
                    })
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_and_id_images_are_attachments_that_can_be_copied() {
        let depth = ImageDesc::depth(64, 32);
        assert_eq!(depth.format(), vk::Format::D32_SFLOAT);
        assert_eq!(depth.aspect(), vk::ImageAspectFlags::DEPTH);
        assert!(depth.usage().contains(
            vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC
        ));
        let ids = ImageDesc::ids(64, 32);
        assert_eq!(ids.format(), vk::Format::R32_UINT);
        assert_eq!(ids.aspect(), vk::ImageAspectFlags::COLOR);
        assert_eq!(ids.buffer_bytes(), 64 * 32 * 4);
    }

    #[test]
    fn the_copy_region_covers_the_image_tightly_packed() {
        let region = ImageDesc::depth(1920, 1080).copy_to_buffer_region();
        assert_eq!(region.buffer_row_length, 0);
        assert_eq!(region.image_extent.width, 1920);
        assert_eq!(region.image_extent.height, 1080);
        assert_eq!(
            region.image_subresource.aspect_mask,
            vk::ImageAspectFlags::DEPTH
        );
    }
}
