//! Compute pipelines: a shader, its storage-buffer bindings 0..n, and a push-constant range.

use ash::vk;

use super::error::{GpuError, GpuResult, VkContext};
use super::shader::{Shader, ShaderModule};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ComputePipelineDesc {
    pub shader: Shader,
    /// Storage buffers at bindings 0..buffers of set 0.
    pub buffers: u32,
    pub push_constant_bytes: u32,
}

impl ComputePipelineDesc {
    pub fn new(shader: Shader, buffers: u32) -> Self {
        Self {
            shader,
            buffers,
            push_constant_bytes: 0,
        }
    }

    pub fn push_constants(self, bytes: u32) -> Self {
        Self {
            push_constant_bytes: bytes,
            ..self
        }
    }
}

pub struct ComputePipeline {
    pub raw: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    pub set_layout: vk::DescriptorSetLayout,
    pub desc: ComputePipelineDesc,
}

impl ComputePipeline {
    pub fn new(device: &ash::Device, desc: &ComputePipelineDesc) -> GpuResult<Self> {
        if desc.push_constant_bytes > 128 || !desc.push_constant_bytes.is_multiple_of(4) {
            return Err(GpuError::Shader {
                name: desc.shader.name(),
                reason: format!(
                    "{} bytes of push constants (at most 128, a multiple of 4)",
                    desc.push_constant_bytes
                ),
            });
        }
        let bindings: Vec<vk::DescriptorSetLayoutBinding> = (0..desc.buffers)
            .map(|binding| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let set_info = vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings);
        // SAFETY: `set_info` outlives the call. Each object created below is destroyed
        // again if a later step fails.
        let set_layout = unsafe { device.create_descriptor_set_layout(&set_info, None) }
            .call("vkCreateDescriptorSetLayout")?;
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(vk::ShaderStageFlags::COMPUTE)
            .offset(0)
            .size(desc.push_constant_bytes)];
        let set_layouts = [set_layout];
        let mut layout_info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if desc.push_constant_bytes > 0 {
            layout_info = layout_info.push_constant_ranges(&ranges);
        }
        // SAFETY: as above.
        let layout = match unsafe { device.create_pipeline_layout(&layout_info, None) } {
            Ok(layout) => layout,
            Err(result) => {
                // SAFETY: created above and not used by anything.
                unsafe { device.destroy_descriptor_set_layout(set_layout, None) };
                return Err(GpuError::Vulkan {
                    call: "vkCreatePipelineLayout",
                    result,
                });
            }
        };
        let destroy_layouts = || {
            // SAFETY: created above and used by no pipeline.
            unsafe {
                device.destroy_pipeline_layout(layout, None);
                device.destroy_descriptor_set_layout(set_layout, None);
            }
        };
        let module = match ShaderModule::new(device, desc.shader) {
            Ok(module) => module,
            Err(err) => {
                destroy_layouts();
                return Err(err);
            }
        };
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(module.raw)
            .name(c"main");
        let info = vk::ComputePipelineCreateInfo::default()
            .stage(stage)
            .layout(layout);
        // SAFETY: the module and layout are valid; `info` outlives the call.
        let created =
            unsafe { device.create_compute_pipelines(vk::PipelineCache::null(), &[info], None) };
        module.destroy(device);
        match created {
            Ok(pipelines) => Ok(Self {
                raw: pipelines[0],
                layout,
                set_layout,
                desc: *desc,
            }),
            Err((_, result)) => {
                destroy_layouts();
                Err(GpuError::Vulkan {
                    call: "vkCreateComputePipelines",
                    result,
                })
            }
        }
    }

    pub fn destroy(&self, device: &ash::Device) {
        // SAFETY: called by the device's Drop once the queue is idle.
        unsafe {
            device.destroy_pipeline(self.raw, None);
            device.destroy_pipeline_layout(self.layout, None);
            device.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}
