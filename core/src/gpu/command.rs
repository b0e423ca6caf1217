//! Recording and submitting one stage's work: a command buffer with its descriptor sets,
//! staging buffers and timestamps, submitted once and waited for. One submission per
//! stage, so that a lost device is reported with the stage that was running.

use std::sync::Arc;

use ash::vk;

use super::barrier::{barrier_between, Access};
use super::buffer::{as_bytes, copy_from_bytes, from_bytes, Buffer, BufferDesc, Pod};
use super::compute_pipeline::{ComputePipeline, ComputePipelineDesc};
use super::device::Device;
use super::error::{GpuError, GpuResult, VkContext};
use super::graphics_pipeline::{Framebuffer, GraphicsPipeline, GraphicsPipelineDesc};
use super::host_time::{self, timed, HostWork};
use super::image::Image;
use super::query::TimestampPool;

/// Timestamp pairs one recording can hold.
const TIMESTAMPS: u32 = 16;

/// Handle of a read-back recorded with [`Recorder::download`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Readback(usize);

pub struct Recorder {
    device: Arc<Device>,
    stage: &'static str,
    pool: vk::CommandPool,
    cb: vk::CommandBuffer,
    descriptors: vk::DescriptorPool,
    fence: vk::Fence,
    timestamps: Option<TimestampPool>,
    pipelines: Vec<Arc<ComputePipeline>>,
    graphics_pipelines: Vec<Arc<GraphicsPipeline>>,
    staging: Vec<Buffer>,
    readbacks: Vec<Buffer>,
    /// Submitted but not yet known to be complete: Drop must wait before destroying.
    in_flight: bool,
}

impl Recorder {
    /// Begins recording `stage`, with room for `max_dispatches` descriptor sets (one per
    /// dispatch or draw) of up to `max_buffers` storage buffers each.
    pub fn new(
        device: &Arc<Device>,
        stage: &'static str,
        max_dispatches: u32,
        max_buffers: u32,
    ) -> GpuResult<Recorder> {
        let raw = &device.raw;
        let pool_info = vk::CommandPoolCreateInfo::default()
            .flags(vk::CommandPoolCreateFlags::TRANSIENT)
            .queue_family_index(device.physical.queue_family);
        // SAFETY: the create infos outlive their calls. Handles created here are stored in
        // `recorder` as soon as they exist, so that Drop destroys them on any failure.
        let pool = unsafe { raw.create_command_pool(&pool_info, None) }
            .call("vkCreateCommandPool")
            .map_err(|e| e.in_stage(stage))?;
        let mut recorder = Recorder {
            device: device.clone(),
            stage,
            pool,
            cb: vk::CommandBuffer::null(),
            descriptors: vk::DescriptorPool::null(),
            fence: vk::Fence::null(),
            timestamps: None,
            pipelines: Vec::new(),
            graphics_pipelines: Vec::new(),
            staging: Vec::new(),
            readbacks: Vec::new(),
            in_flight: false,
        };
        let sizes = [vk::DescriptorPoolSize::default()
            .ty(vk::DescriptorType::STORAGE_BUFFER)
            .descriptor_count((max_dispatches * max_buffers).max(1))];
        let descriptor_info = vk::DescriptorPoolCreateInfo::default()
            .max_sets(max_dispatches.max(1))
            .pool_sizes(&sizes);
        // SAFETY: as above.
        recorder.descriptors = unsafe { raw.create_descriptor_pool(&descriptor_info, None) }
            .call("vkCreateDescriptorPool")
            .map_err(|e| e.in_stage(stage))?;
        // SAFETY: as above.
        recorder.fence = unsafe { raw.create_fence(&vk::FenceCreateInfo::default(), None) }
            .call("vkCreateFence")
            .map_err(|e| e.in_stage(stage))?;
        let allocate = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: as above.
        recorder.cb = unsafe { raw.allocate_command_buffers(&allocate) }
            .call("vkAllocateCommandBuffers")
            .map_err(|e| e.in_stage(stage))?[0];
        if device.physical.timestamp_valid_bits > 0 {
            recorder.timestamps = Some(TimestampPool::new(raw, TIMESTAMPS * 2)?);
        }
        let begin = vk::CommandBufferBeginInfo::default()
            .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: the command buffer is in the initial state.
        unsafe { raw.begin_command_buffer(recorder.cb, &begin) }
            .call("vkBeginCommandBuffer")
            .map_err(|e| e.in_stage(stage))?;
        if let Some(timestamps) = &recorder.timestamps {
            // SAFETY: recording; the range lies inside the pool.
            unsafe {
                raw.cmd_reset_query_pool(recorder.cb, timestamps.raw, 0, timestamps.capacity())
            };
        }
        Ok(recorder)
    }

    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }

    /// A device-local buffer filled with `values` by a copy recorded here. Follow it with
    /// [`Recorder::barrier`]`(TransferWrite, ComputeRead)` before a shader reads it.
    pub fn upload<T: Pod>(&mut self, values: &[T], name: &str) -> GpuResult<Buffer> {
        let bytes = as_bytes(values);
        let size = bytes.len() as u64;
        let mut staging = Buffer::new(&self.device, BufferDesc::upload(size), name)?;
        staging.write(bytes)?;
        let target = Buffer::new(&self.device, BufferDesc::storage(size), name)?;
        self.copy(&staging, &target, size);
        self.staging.push(staging);
        Ok(target)
    }

    /// A device-local buffer of `size` bytes, for a shader to write.
    pub fn storage(&self, size: u64, name: &str) -> GpuResult<Buffer> {
        Buffer::new(&self.device, BufferDesc::storage(size), name)
    }

    pub fn copy(&mut self, src: &Buffer, dst: &Buffer, size: u64) {
        let region = vk::BufferCopy::default().size(size.max(4).min(src.size().max(4)));
        // SAFETY: recording; both buffers outlive the submission (owned by the caller
        // or by this recorder).
        unsafe {
            self.device
                .raw
                .cmd_copy_buffer(self.cb, src.raw, dst.raw, &[region])
        };
    }

    /// Copies `src` to a host-visible buffer after the work recorded so far; read it from
    /// the [`Completed`] submission.
    pub fn download(&mut self, src: &Buffer, name: &str) -> GpuResult<Readback> {
        self.barrier(Access::ComputeWrite, Access::TransferRead);
        let target = Buffer::new(&self.device, BufferDesc::readback(src.size()), name)?;
        self.copy(src, &target, src.size());
        self.readbacks.push(target);
        Ok(Readback(self.readbacks.len() - 1))
    }

    /// A global memory barrier between two kinds of access, if one is needed.
    pub fn barrier(&mut self, before: Access, after: Access) {
        let Some(b) = barrier_between(before, after) else {
            return;
        };
        let memory = vk::MemoryBarrier::default()
            .src_access_mask(b.src_access)
            .dst_access_mask(b.dst_access);
        // SAFETY: recording.
        unsafe {
            self.device.raw.cmd_pipeline_barrier(
                self.cb,
                b.src_stage,
                b.dst_stage,
                vk::DependencyFlags::empty(),
                &[memory],
                &[],
                &[],
            )
        };
    }

    /// Records one dispatch of `desc`'s pipeline with `buffers` at bindings 0.. and
    /// `push` as push constants.
    pub fn dispatch(
        &mut self,
        desc: &ComputePipelineDesc,
        buffers: &[&Buffer],
        push: &[u8],
        groups: [u32; 3],
    ) -> GpuResult<()> {
        self.bind_compute(desc, buffers, push)?;
        // SAFETY: recording, with the pipeline and its set bound above.
        unsafe {
            self.device
                .raw
                .cmd_dispatch(self.cb, groups[0], groups[1], groups[2])
        };
        Ok(())
    }

    /// [`Recorder::dispatch`] with the workgroup counts read on the device from `args` at
    /// `offset` (three u32), as an earlier dispatch wrote them: follow that one with
    /// [`Recorder::barrier`]`(ComputeWrite, IndirectRead)`.
    pub fn dispatch_indirect(
        &mut self,
        desc: &ComputePipelineDesc,
        buffers: &[&Buffer],
        push: &[u8],
        args: &Buffer,
        offset: u64,
    ) -> GpuResult<()> {
        if !offset.is_multiple_of(4) || offset + 12 > args.size() {
            return Err(GpuError::Unsupported(format!(
                "indirect arguments at byte {offset} of a {}-byte buffer",
                args.size()
            )));
        }
        self.bind_compute(desc, buffers, push)?;
        // SAFETY: recording, with the pipeline and its set bound above; the arguments lie
        // inside `args`, which outlives the submission.
        unsafe {
            self.device
                .raw
                .cmd_dispatch_indirect(self.cb, args.raw, offset)
        };
        Ok(())
    }

    /// Binds `desc`'s pipeline with `buffers` at bindings 0.. and pushes `push`.
    fn bind_compute(
        &mut self,
        desc: &ComputePipelineDesc,
        buffers: &[&Buffer],
        push: &[u8],
    ) -> GpuResult<()> {
        if buffers.len() != desc.buffers as usize || push.len() != desc.push_constant_bytes as usize
        {
            return Err(GpuError::Shader {
                name: desc.shader.name(),
                reason: format!(
                    "bound {} buffers and {} push-constant bytes, the pipeline takes {} and {}",
                    buffers.len(),
                    push.len(),
                    desc.buffers,
                    desc.push_constant_bytes
                ),
            });
        }
        let pipeline = self.device.pipeline(desc)?;
        let set = self.descriptor_set(pipeline.set_layout, buffers)?;
        // SAFETY: recording; the buffers outlive the submission.
        unsafe {
            self.device.raw.cmd_bind_pipeline(
                self.cb,
                vk::PipelineBindPoint::COMPUTE,
                pipeline.raw,
            );
            self.bind_set_and_push(
                vk::PipelineBindPoint::COMPUTE,
                pipeline.layout,
                set,
                vk::ShaderStageFlags::COMPUTE,
                push,
            );
        }
        self.pipelines.push(pipeline);
        Ok(())
    }

    /// Binds `set` and pushes `push` (if any) for the pipeline bound at `point`.
    ///
    /// # Safety
    /// Recording, with a pipeline of `layout` bound at `point`; the set's buffers outlive
    /// the submission.
    unsafe fn bind_set_and_push(
        &self,
        point: vk::PipelineBindPoint,
        layout: vk::PipelineLayout,
        set: vk::DescriptorSet,
        stages: vk::ShaderStageFlags,
        push: &[u8],
    ) {
        let raw = &self.device.raw;
        raw.cmd_bind_descriptor_sets(self.cb, point, layout, 0, &[set], &[]);
        if !push.is_empty() {
            raw.cmd_push_constants(self.cb, layout, stages, 0, push);
        }
    }

    /// A descriptor set of `layout` with `buffers` as storage buffers at bindings 0...
    fn descriptor_set(
        &mut self,
        layout: vk::DescriptorSetLayout,
        buffers: &[&Buffer],
    ) -> GpuResult<vk::DescriptorSet> {
        let raw = &self.device.raw;
        let layouts = [layout];
        let allocate = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(self.descriptors)
            .set_layouts(&layouts);
        // SAFETY: the pool was sized for this recording's dispatches and draws.
        let set =
            unsafe { raw.allocate_descriptor_sets(&allocate) }.call("vkAllocateDescriptorSets")?[0];
        let infos: Vec<vk::DescriptorBufferInfo> = buffers
            .iter()
            .map(|b| {
                vk::DescriptorBufferInfo::default()
                    .buffer(b.raw)
                    .offset(0)
                    // Not the whole buffer: a kept one may be larger than asked for.
                    .range(b.bound_size())
            })
            .collect();
        let writes: Vec<vk::WriteDescriptorSet> = infos
            .iter()
            .enumerate()
            .map(|(binding, info)| {
                vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(binding as u32)
                    .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                    .buffer_info(std::slice::from_ref(info))
            })
            .collect();
        // SAFETY: `infos` outlives the update; the set is not in use yet.
        unsafe { raw.update_descriptor_sets(&writes, &[]) };
        Ok(set)
    }

    /// Records one render pass on `target` that clears its attachments to `clear` (in
    /// attachment order) and draws `vertex_count` vertices with `desc`'s pipeline, with
    /// `buffers` at bindings 0.. and `push` as the vertex shader's push constants. The
    /// attachments end ready for [`Recorder::download_image`].
    pub fn draw(
        &mut self,
        desc: &GraphicsPipelineDesc,
        target: &Framebuffer,
        clear: &[vk::ClearValue],
        buffers: &[&Buffer],
        push: &[u8],
        vertex_count: u32,
    ) -> GpuResult<()> {
        let attachments = desc.attachment_formats().len();
        if buffers.len() != desc.buffers as usize
            || push.len() != desc.push_constant_bytes as usize
            || clear.len() != attachments
        {
            return Err(GpuError::Shader {
                name: desc.vertex.name(),
                reason: format!(
                    "bound {} buffers, {} push-constant bytes and {} clear values, the \
                     pipeline takes {}, {} and {}",
                    buffers.len(),
                    push.len(),
                    clear.len(),
                    desc.buffers,
                    desc.push_constant_bytes,
                    attachments
                ),
            });
        }
        let pipeline = self.device.graphics_pipeline(desc)?;
        if pipeline.render_pass != target.render_pass {
            return Err(GpuError::Unsupported(
                "a framebuffer made for another render pass".to_owned(),
            ));
        }
        let set = self.descriptor_set(pipeline.set_layout, buffers)?;
        let raw = &self.device.raw;
        let begin = vk::RenderPassBeginInfo::default()
            .render_pass(pipeline.render_pass)
            .framebuffer(target.raw)
            .render_area(target.scissor())
            .clear_values(clear);
        // SAFETY: recording outside a render pass; the framebuffer, its images and the
        // buffers outlive the submission.
        unsafe {
            raw.cmd_begin_render_pass(self.cb, &begin, vk::SubpassContents::INLINE);
            raw.cmd_bind_pipeline(self.cb, vk::PipelineBindPoint::GRAPHICS, pipeline.raw);
            raw.cmd_set_viewport(self.cb, 0, &[target.viewport()]);
            raw.cmd_set_scissor(self.cb, 0, &[target.scissor()]);
            self.bind_set_and_push(
                vk::PipelineBindPoint::GRAPHICS,
                pipeline.layout,
                set,
                vk::ShaderStageFlags::VERTEX,
                push,
            );
            raw.cmd_draw(self.cb, vertex_count, 1, 0, 0);
            raw.cmd_end_render_pass(self.cb);
        }
        self.graphics_pipelines.push(pipeline);
        Ok(())
    }

    /// Copies an image that a render pass left in `TRANSFER_SRC_OPTIMAL` (see
    /// [`Recorder::draw`]) to a host-visible buffer, rows tightly packed; read it from the
    /// [`Completed`] submission.
    pub fn download_image(&mut self, image: &Image, name: &str) -> GpuResult<Readback> {
        let target = Buffer::new(
            &self.device,
            BufferDesc::readback(image.desc.buffer_bytes()),
            name,
        )?;
        // SAFETY: recording; the image outlives the submission and is in the layout named.
        unsafe {
            self.device.raw.cmd_copy_image_to_buffer(
                self.cb,
                image.raw,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                target.raw,
                &[image.desc.copy_to_buffer_region()],
            )
        };
        self.readbacks.push(target);
        Ok(Readback(self.readbacks.len() - 1))
    }

    /// Records `f`'s commands between two timestamps labelled `label` (untimed where the
    /// queue has no timestamps).
    pub fn timed<T>(
        &mut self,
        label: &'static str,
        f: impl FnOnce(&mut Recorder) -> GpuResult<T>,
    ) -> GpuResult<T> {
        let pair = self.timestamps.as_mut().and_then(|t| t.reserve(label));
        let pool = self.timestamps.as_ref().map(|t| t.raw);
        if let (Some((start, _)), Some(pool)) = (pair, pool) {
            // SAFETY: recording; the query was reset at the start of the recording.
            unsafe {
                self.device.raw.cmd_write_timestamp(
                    self.cb,
                    vk::PipelineStageFlags::TOP_OF_PIPE,
                    pool,
                    start,
                )
            };
        }
        let result = f(self)?;
        if let (Some((_, end)), Some(pool)) = (pair, pool) {
            // SAFETY: as above.
            unsafe {
                self.device.raw.cmd_write_timestamp(
                    self.cb,
                    vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                    pool,
                    end,
                )
            };
        }
        Ok(result)
    }

    /// Submits the recording and waits for it.
    pub fn submit_and_wait(mut self) -> GpuResult<Completed> {
        let stage = self.stage;
        let raw = &self.device.raw;
        // SAFETY: recording ends here.
        unsafe { raw.end_command_buffer(self.cb) }
            .call("vkEndCommandBuffer")
            .map_err(|e| e.in_stage(stage))?;
        let buffers = [self.cb];
        let submit = vk::SubmitInfo::default().command_buffers(&buffers);
        {
            let _queue = self.device.queue_guard();
            // SAFETY: the queue is externally synchronised by the guard; the fence is
            // unsignalled.
            unsafe { raw.queue_submit(self.device.queue, &[submit], self.fence) }
                .call("vkQueueSubmit")
                .map_err(|e| e.in_stage(stage))?;
        }
        self.in_flight = true;
        // SAFETY: the fence belongs to this device.
        timed(HostWork::Waits, || unsafe {
            raw.wait_for_fences(&[self.fence], true, u64::MAX)
        })
        .call("vkWaitForFences")
        .map_err(|e| e.in_stage(stage))?;
        self.in_flight = false;
        let timings = match &self.timestamps {
            Some(pool) => pool
                .read(
                    raw,
                    self.device.physical.timestamp_valid_bits,
                    self.device.physical.timestamp_period,
                )
                .map_err(|e| e.in_stage(stage))?,
            None => Vec::new(),
        };
        Ok(Completed {
            readbacks: std::mem::take(&mut self.readbacks),
            timings,
        })
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        let raw = &self.device.raw;
        // SAFETY: work that may still use these objects is waited for first; each handle
        // is either null (never created) or owned by this recorder.
        unsafe {
            if self.in_flight {
                let _ = raw.device_wait_idle();
            }
            if let Some(timestamps) = &self.timestamps {
                timestamps.destroy(raw);
            }
            if self.fence != vk::Fence::null() {
                raw.destroy_fence(self.fence, None);
            }
            if self.descriptors != vk::DescriptorPool::null() {
                raw.destroy_descriptor_pool(self.descriptors, None);
            }
            raw.destroy_command_pool(self.pool, None);
        }
    }
}

/// A finished submission: its read-backs and its timestamps.
pub struct Completed {
    readbacks: Vec<Buffer>,
    /// (label, milliseconds) per timed section.
    pub timings: Vec<(&'static str, f64)>,
}

impl Completed {
    pub fn read<T: Pod + Default>(&self, readback: Readback) -> GpuResult<Vec<T>> {
        let bytes = self.bytes(readback)?;
        host_time::count_read(bytes.len());
        Ok(timed(HostWork::Reads, || from_bytes(bytes)))
    }

    /// Reads into `values`, which must hold exactly what was copied back: memory the
    /// caller kept from an earlier frame, whose pages need not fault in again.
    pub fn read_into<T: Pod>(&self, readback: Readback, values: &mut [T]) -> GpuResult<()> {
        let bytes = self.bytes(readback)?;
        if bytes.len() != std::mem::size_of_val(values) {
            return Err(GpuError::Unsupported(format!(
                "reading {} bytes back into {} bytes",
                bytes.len(),
                std::mem::size_of_val(values)
            )));
        }
        host_time::count_read(bytes.len());
        timed(HostWork::Reads, || copy_from_bytes(bytes, values));
        Ok(())
    }

    fn bytes(&self, readback: Readback) -> GpuResult<&[u8]> {
        self.readbacks
            .get(readback.0)
            .ok_or_else(|| GpuError::Unsupported("an unknown read-back".to_owned()))?
            .read()
    }

    pub fn milliseconds(&self, label: &str) -> Option<f64> {
        self.timings
            .iter()
            .find(|(l, _)| *l == label)
            .map(|(_, ms)| *ms)
    }
}
