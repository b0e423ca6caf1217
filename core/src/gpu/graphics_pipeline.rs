//! Graphics pipelines for headless depth passes: a Vulkan 1.1 render pass with a D32_SFLOAT
//! depth attachment and, optionally, an R32_UINT colour attachment that a fragment shader
//! fills with object ids; the vertex shader pulls its vertices from storage buffers. Both
//! attachments end in `TRANSFER_SRC_OPTIMAL`, ready to be copied to a buffer. Also the
//! framebuffers that bind images to such a render pass.

use std::sync::Arc;

use ash::vk;

use super::device::Device;
use super::error::{GpuError, GpuResult, VkContext};
use super::image::{Image, ImageDesc};
use super::shader::{Shader, ShaderModule};

/// Attachment index of the depth image; the id image, when there is one, follows it.
pub const DEPTH_ATTACHMENT: u32 = 0;
pub const ID_ATTACHMENT: u32 = 1;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct GraphicsPipelineDesc {
    pub vertex: Shader,
    /// The fragment shader: `None` for a depth-only pass without discards.
    pub fragment: Option<Shader>,
    /// Whether the fragment shader writes the R32_UINT id attachment.
    pub ids: bool,
    /// Storage buffers at bindings 0..buffers of set 0, read by the vertex shader (and the
    /// fragment shader of cut passes).
    pub buffers: u32,
    /// Push constants of the vertex shader.
    pub push_constant_bytes: u32,
    /// The depth test; writes happen where it passes.
    pub depth_compare: vk::CompareOp,
}

impl GraphicsPipelineDesc {
    /// A pass that writes depth alone, nearer being smaller.
    pub fn depth_only(vertex: Shader, buffers: u32) -> Self {
        Self {
            vertex,
            fragment: None,
            ids: false,
            buffers,
            push_constant_bytes: 0,
            depth_compare: vk::CompareOp::LESS,
        }
    }

    /// Adds the id attachment, written by `fragment` in the same pass as depth.
    pub fn with_ids(self, fragment: Shader) -> Self {
        Self {
            fragment: Some(fragment),
            ids: true,
            ..self
        }
    }

    /// Adds a fragment shader that writes no attachment (it discards samples).
    pub fn with_fragment(self, fragment: Shader) -> Self {
        Self {
            fragment: Some(fragment),
            ..self
        }
    }

    pub fn push_constants(self, bytes: u32) -> Self {
        Self {
            push_constant_bytes: bytes,
            ..self
        }
    }

    pub fn depth_compare(self, op: vk::CompareOp) -> Self {
        Self {
            depth_compare: op,
            ..self
        }
    }

    pub fn writes_ids(&self) -> bool {
        self.ids
    }

    /// The attachments in render-pass order: depth, then ids.
    pub fn attachment_formats(&self) -> Vec<vk::Format> {
        let mut formats = vec![vk::Format::D32_SFLOAT];
        if self.writes_ids() {
            formats.push(vk::Format::R32_UINT);
        }
        formats
    }
}

/// The viewport of a `width × height` target with `guard` pixels beyond each side:
/// normalised device coordinates −1..1 map to −guard..width + guard in x and likewise in
/// y (framebuffer rows downwards), depth 0..1 unchanged. Vulkan clips primitives to the
/// viewport, so the guard band keeps clipping (and the snapping of the vertices it makes)
/// away from the target's samples; the scissor then keeps drawing inside the target.
pub fn guarded_viewport(width: u32, height: u32, guard: u32) -> vk::Viewport {
    vk::Viewport {
        x: -(guard as f32),
        y: -(guard as f32),
        width: (width + 2 * guard) as f32,
        height: (height + 2 * guard) as f32,
        min_depth: 0.0,
        max_depth: 1.0,
    }
}

/// The largest guard band, up to `wanted` pixels, for which [`guarded_viewport`] of a
/// `width × height` target fits the device's `max_dimensions` and `bounds_range`.
pub fn fitting_guard(
    width: u32,
    height: u32,
    wanted: u32,
    max_dimensions: [u32; 2],
    bounds_range: [f32; 2],
) -> u32 {
    let by_dimensions = (max_dimensions[0].saturating_sub(width) / 2)
        .min(max_dimensions[1].saturating_sub(height) / 2);
    let below = (-bounds_range[0]).max(0.0).floor() as u32;
    let above = (bounds_range[1] - width.max(height) as f32)
        .max(0.0)
        .floor() as u32;
    wanted.min(by_dimensions).min(below).min(above)
}

/// The scissor rectangle covering a `width × height` target.
pub fn full_scissor(width: u32, height: u32) -> vk::Rect2D {
    vk::Rect2D {
        offset: vk::Offset2D { x: 0, y: 0 },
        extent: vk::Extent2D { width, height },
    }
}

pub struct GraphicsPipeline {
    pub raw: vk::Pipeline,
    pub layout: vk::PipelineLayout,
    pub set_layout: vk::DescriptorSetLayout,
    pub render_pass: vk::RenderPass,
    pub desc: GraphicsPipelineDesc,
}

/// Handles created so far, destroyed together if a later step fails.
#[derive(Default)]
struct Partial {
    set_layout: vk::DescriptorSetLayout,
    layout: vk::PipelineLayout,
    render_pass: vk::RenderPass,
    modules: Vec<ShaderModule>,
}

impl Partial {
    fn destroy(self, device: &ash::Device) {
        for module in self.modules {
            module.destroy(device);
        }
        // SAFETY: every handle is null or was created above and is used by no pipeline.
        unsafe {
            device.destroy_render_pass(self.render_pass, None);
            device.destroy_pipeline_layout(self.layout, None);
            device.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

impl GraphicsPipeline {
    pub fn new(device: &ash::Device, desc: &GraphicsPipelineDesc) -> GpuResult<Self> {
        if desc.push_constant_bytes > 128 || !desc.push_constant_bytes.is_multiple_of(4) {
            return Err(GpuError::Shader {
                name: desc.vertex.name(),
                reason: format!(
                    "{} bytes of push constants (at most 128, a multiple of 4)",
                    desc.push_constant_bytes
                ),
            });
        }
        let mut partial = Partial::default();
        match Self::create(device, desc, &mut partial) {
            Ok(raw) => {
                for module in partial.modules.drain(..) {
                    module.destroy(device);
                }
                Ok(Self {
                    raw,
                    layout: partial.layout,
                    set_layout: partial.set_layout,
                    render_pass: partial.render_pass,
                    desc: *desc,
                })
            }
            Err(err) => {
                partial.destroy(device);
                Err(err)
            }
        }
    }

    fn create(
        device: &ash::Device,
        desc: &GraphicsPipelineDesc,
        partial: &mut Partial,
    ) -> GpuResult<vk::Pipeline> {
        let bindings: Vec<vk::DescriptorSetLayoutBinding> = (0..desc.buffers)
            .map(|binding| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT)
            })
            .collect();
        let set_info = vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings);
        // SAFETY (this and the create calls below): the create infos and what they point
        // to outlive the calls; each handle is stored in `partial` as soon as it exists.
        partial.set_layout = unsafe { device.create_descriptor_set_layout(&set_info, None) }
            .call("vkCreateDescriptorSetLayout")?;
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(vk::ShaderStageFlags::VERTEX)
            .offset(0)
            .size(desc.push_constant_bytes)];
        let set_layouts = [partial.set_layout];
        let mut layout_info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if desc.push_constant_bytes > 0 {
            layout_info = layout_info.push_constant_ranges(&ranges);
        }
        partial.layout = unsafe { device.create_pipeline_layout(&layout_info, None) }
            .call("vkCreatePipelineLayout")?;
        partial.render_pass = create_render_pass(device, desc)?;

        partial
            .modules
            .push(ShaderModule::new(device, desc.vertex)?);
        if let Some(fragment) = desc.fragment {
            partial.modules.push(ShaderModule::new(device, fragment)?);
        }
        let mut shaders = vec![desc.vertex];
        shaders.extend(desc.fragment);
        let stages: Vec<vk::PipelineShaderStageCreateInfo> = shaders
            .iter()
            .zip(&partial.modules)
            .map(|(shader, module)| {
                vk::PipelineShaderStageCreateInfo::default()
                    .stage(shader.stage())
                    .module(module.raw)
                    .name(c"main")
            })
            .collect();
        let vertex_input = vk::PipelineVertexInputStateCreateInfo::default();
        let input_assembly = vk::PipelineInputAssemblyStateCreateInfo::default()
            .topology(vk::PrimitiveTopology::TRIANGLE_LIST);
        let viewport = vk::PipelineViewportStateCreateInfo::default()
            .viewport_count(1)
            .scissor_count(1);
        // Both windings are drawn: a shadow caster is seen from either side.
        let rasterization = vk::PipelineRasterizationStateCreateInfo::default()
            .polygon_mode(vk::PolygonMode::FILL)
            .cull_mode(vk::CullModeFlags::NONE)
            .front_face(vk::FrontFace::COUNTER_CLOCKWISE)
            .line_width(1.0);
        let multisample = vk::PipelineMultisampleStateCreateInfo::default()
            .rasterization_samples(vk::SampleCountFlags::TYPE_1);
        let depth_stencil = vk::PipelineDepthStencilStateCreateInfo::default()
            .depth_test_enable(true)
            .depth_write_enable(true)
            .depth_compare_op(desc.depth_compare);
        let blend_attachments = [vk::PipelineColorBlendAttachmentState::default()
            .blend_enable(false)
            .color_write_mask(vk::ColorComponentFlags::R)];
        let color_count = usize::from(desc.writes_ids());
        let color_blend = vk::PipelineColorBlendStateCreateInfo::default()
            .attachments(&blend_attachments[..color_count]);
        let dynamic_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
        let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic_states);
        let info = vk::GraphicsPipelineCreateInfo::default()
            .stages(&stages)
            .vertex_input_state(&vertex_input)
            .input_assembly_state(&input_assembly)
            .viewport_state(&viewport)
            .rasterization_state(&rasterization)
            .multisample_state(&multisample)
            .depth_stencil_state(&depth_stencil)
            .color_blend_state(&color_blend)
            .dynamic_state(&dynamic)
            .layout(partial.layout)
            .render_pass(partial.render_pass)
            .subpass(0);
        let created =
            unsafe { device.create_graphics_pipelines(vk::PipelineCache::null(), &[info], None) };
        match created {
            Ok(pipelines) => Ok(pipelines[0]),
            Err((_, result)) => Err(GpuError::Vulkan {
                call: "vkCreateGraphicsPipelines",
                result,
            }),
        }
    }

    pub fn destroy(&self, device: &ash::Device) {
        // SAFETY: called by the device's Drop once the queue is idle.
        unsafe {
            device.destroy_pipeline(self.raw, None);
            device.destroy_render_pass(self.render_pass, None);
            device.destroy_pipeline_layout(self.layout, None);
            device.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

/// One subpass that clears and stores its attachments, which end ready for a copy: the
/// dependency to the outside makes the attachment writes visible to transfer reads.
fn create_render_pass(
    device: &ash::Device,
    desc: &GraphicsPipelineDesc,
) -> GpuResult<vk::RenderPass> {
    let attachments: Vec<vk::AttachmentDescription> = desc
        .attachment_formats()
        .into_iter()
        .map(|format| {
            vk::AttachmentDescription::default()
                .format(format)
                .samples(vk::SampleCountFlags::TYPE_1)
                .load_op(vk::AttachmentLoadOp::CLEAR)
                .store_op(vk::AttachmentStoreOp::STORE)
                .stencil_load_op(vk::AttachmentLoadOp::DONT_CARE)
                .stencil_store_op(vk::AttachmentStoreOp::DONT_CARE)
                .initial_layout(vk::ImageLayout::UNDEFINED)
                .final_layout(vk::ImageLayout::TRANSFER_SRC_OPTIMAL)
        })
        .collect();
    let depth_ref = vk::AttachmentReference::default()
        .attachment(DEPTH_ATTACHMENT)
        .layout(vk::ImageLayout::DEPTH_STENCIL_ATTACHMENT_OPTIMAL);
    let color_refs = [vk::AttachmentReference::default()
        .attachment(ID_ATTACHMENT)
        .layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)];
    let color_count = usize::from(desc.writes_ids());
    let subpass = vk::SubpassDescription::default()
        .pipeline_bind_point(vk::PipelineBindPoint::GRAPHICS)
        .color_attachments(&color_refs[..color_count])
        .depth_stencil_attachment(&depth_ref);
    let to_transfer = vk::SubpassDependency::default()
        .src_subpass(0)
        .dst_subpass(vk::SUBPASS_EXTERNAL)
        .src_stage_mask(
            vk::PipelineStageFlags::EARLY_FRAGMENT_TESTS
                | vk::PipelineStageFlags::LATE_FRAGMENT_TESTS
                | vk::PipelineStageFlags::COLOR_ATTACHMENT_OUTPUT,
        )
        .src_access_mask(
            vk::AccessFlags::DEPTH_STENCIL_ATTACHMENT_WRITE
                | vk::AccessFlags::COLOR_ATTACHMENT_WRITE,
        )
        .dst_stage_mask(vk::PipelineStageFlags::TRANSFER)
        .dst_access_mask(vk::AccessFlags::TRANSFER_READ);
    let info = vk::RenderPassCreateInfo::default()
        .attachments(&attachments)
        .subpasses(std::slice::from_ref(&subpass))
        .dependencies(std::slice::from_ref(&to_transfer));
    // SAFETY: `info` and what it points to outlive the call.
    unsafe { device.create_render_pass(&info, None) }.call("vkCreateRenderPass")
}

/// Images bound to a pipeline's render pass, in its attachment order, with the guard band
/// of their viewport.
pub struct Framebuffer {
    pub raw: vk::Framebuffer,
    pub render_pass: vk::RenderPass,
    pub width: u32,
    pub height: u32,
    /// Pixels the viewport extends beyond each side (see [`guarded_viewport`]).
    pub guard: u32,
    device: Arc<Device>,
}

impl Framebuffer {
    /// Binds `depth` and, for a pipeline that writes ids, `ids` (of the same size).
    pub fn new(
        device: &Arc<Device>,
        pipeline: &GraphicsPipeline,
        depth: &Image,
        ids: Option<&Image>,
        guard: u32,
    ) -> GpuResult<Framebuffer> {
        let images: Vec<&Image> = std::iter::once(depth).chain(ids).collect();
        let formats: Vec<vk::Format> = images.iter().map(|i| i.desc.format()).collect();
        let size = |d: &ImageDesc| (d.width, d.height);
        if formats != pipeline.desc.attachment_formats()
            || images.iter().any(|i| size(&i.desc) != size(&depth.desc))
        {
            return Err(GpuError::Unsupported(format!(
                "attachments {formats:?} for a render pass of {:?}, all of one size",
                pipeline.desc.attachment_formats()
            )));
        }
        let views: Vec<vk::ImageView> = images.iter().map(|i| i.view).collect();
        let info = vk::FramebufferCreateInfo::default()
            .render_pass(pipeline.render_pass)
            .attachments(&views)
            .width(depth.desc.width)
            .height(depth.desc.height)
            .layers(1);
        // SAFETY: the views and the render pass are valid; `info` outlives the call.
        let raw =
            unsafe { device.raw.create_framebuffer(&info, None) }.call("vkCreateFramebuffer")?;
        Ok(Framebuffer {
            raw,
            render_pass: pipeline.render_pass,
            width: depth.desc.width,
            height: depth.desc.height,
            guard,
            device: device.clone(),
        })
    }

    pub fn viewport(&self) -> vk::Viewport {
        guarded_viewport(self.width, self.height, self.guard)
    }

    pub fn scissor(&self) -> vk::Rect2D {
        full_scissor(self.width, self.height)
    }
}

impl Drop for Framebuffer {
    fn drop(&mut self) {
        // SAFETY: the command buffers that used the framebuffer have completed (it is
        // created before the recorder that uses it, so the recorder's Drop waits first).
        unsafe { self.device.raw.destroy_framebuffer(self.raw, None) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_viewport_maps_ndc_onto_the_target_and_its_guard_band() {
        let viewport = guarded_viewport(1920, 1080, 100);
        // Vulkan: x_f = x + (x_ndc + 1) · width / 2, and the same for y (rows downwards).
        let to_pixel = |ndc: f32, origin: f32, extent: f32| origin + (ndc + 1.0) * extent / 2.0;
        assert_eq!(to_pixel(-1.0, viewport.x, viewport.width), -100.0);
        assert_eq!(to_pixel(1.0, viewport.x, viewport.width), 2020.0);
        assert_eq!(to_pixel(1.0, viewport.y, viewport.height), 1180.0);
        assert_eq!((viewport.min_depth, viewport.max_depth), (0.0, 1.0));
        let unguarded = guarded_viewport(64, 32, 0);
        assert_eq!(
            (unguarded.x, unguarded.width, unguarded.height),
            (0.0, 64.0, 32.0)
        );
        let scissor = full_scissor(1920, 1080);
        assert_eq!((scissor.offset.x, scissor.offset.y), (0, 0));
        assert_eq!((scissor.extent.width, scissor.extent.height), (1920, 1080));
    }

    #[test]
    fn the_guard_band_shrinks_to_the_viewport_limits() {
        // Lavapipe's limits: viewports up to 16384 wide, corners within ±32768.
        let (dimensions, bounds) = ([16384, 16384], [-32768.0, 32768.0]);
        assert_eq!(fitting_guard(1920, 1080, 3904, dimensions, bounds), 3904);
        assert_eq!(fitting_guard(3840, 2160, 7744, dimensions, bounds), 6272);
        // The minimum the specification allows: 4096 and [−8192, 8191].
        assert_eq!(
            fitting_guard(1024, 1024, 2112, [4096, 4096], [-8192.0, 8191.0]),
            1536
        );
        assert_eq!(
            fitting_guard(512, 512, 1088, [4096, 4096], [-100.0, 8191.0]),
            100
        );
        assert_eq!(
            fitting_guard(5000, 10, 64, [4096, 4096], [-8192.0, 8191.0]),
            0
        );
    }

    #[test]
    fn a_depth_only_pass_has_one_attachment_and_ids_add_the_second() {
        let depth_only = GraphicsPipelineDesc::depth_only(Shader::RasterVertex, 3);
        assert_eq!(depth_only.attachment_formats(), [vk::Format::D32_SFLOAT]);
        assert_eq!(depth_only.depth_compare, vk::CompareOp::LESS);
        let with_ids = depth_only
            .with_ids(Shader::RasterFragment)
            .depth_compare(vk::CompareOp::GREATER)
            .push_constants(64);
        assert_eq!(
            with_ids.attachment_formats(),
            [vk::Format::D32_SFLOAT, vk::Format::R32_UINT]
        );
        assert_eq!(
            with_ids.attachment_formats()[ID_ATTACHMENT as usize],
            vk::Format::R32_UINT
        );
        assert_eq!(with_ids.push_constant_bytes, 64);
    }
}
