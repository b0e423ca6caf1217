//! Which memory barrier separates two accesses to the same buffer. Pure logic, so that
//! the decisions are tested without a GPU.

use ash::vk;

/// How a command touches a buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Access {
    /// A vertex shader reading a storage buffer (the depth passes' vertex pulling).
    VertexRead,
    /// A fragment shader reading a storage buffer (the cut depth passes' masks).
    FragmentRead,
    ComputeRead,
    ComputeWrite,
    TransferRead,
    TransferWrite,
    HostRead,
    /// An indirect dispatch reading its workgroup counts from a buffer.
    IndirectRead,
}

impl Access {
    pub fn is_write(self) -> bool {
        matches!(self, Access::ComputeWrite | Access::TransferWrite)
    }

    fn stage(self) -> vk::PipelineStageFlags {
        match self {
            Access::VertexRead => vk::PipelineStageFlags::VERTEX_SHADER,
            Access::FragmentRead => vk::PipelineStageFlags::FRAGMENT_SHADER,
            Access::ComputeRead | Access::ComputeWrite => vk::PipelineStageFlags::COMPUTE_SHADER,
            Access::TransferRead | Access::TransferWrite => vk::PipelineStageFlags::TRANSFER,
            Access::HostRead => vk::PipelineStageFlags::HOST,
            Access::IndirectRead => vk::PipelineStageFlags::DRAW_INDIRECT,
        }
    }

    fn mask(self) -> vk::AccessFlags {
        match self {
            Access::VertexRead | Access::FragmentRead | Access::ComputeRead => {
                vk::AccessFlags::SHADER_READ
            }
            Access::ComputeWrite => vk::AccessFlags::SHADER_WRITE,
            Access::TransferRead => vk::AccessFlags::TRANSFER_READ,
            Access::TransferWrite => vk::AccessFlags::TRANSFER_WRITE,
            Access::HostRead => vk::AccessFlags::HOST_READ,
            Access::IndirectRead => vk::AccessFlags::INDIRECT_COMMAND_READ,
        }
    }
}

/// A global memory barrier: stages and accesses on each side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Barrier {
    pub src_stage: vk::PipelineStageFlags,
    pub src_access: vk::AccessFlags,
    pub dst_stage: vk::PipelineStageFlags,
    pub dst_access: vk::AccessFlags,
}

/// The barrier needed between `before` and `after` on the same memory, or `None` when
/// both only read. A write after a read needs only an execution dependency (no access
/// to make available), so its source access mask is empty.
pub fn barrier_between(before: Access, after: Access) -> Option<Barrier> {
    if !before.is_write() && !after.is_write() {
        return None;
    }
    Some(Barrier {
        src_stage: before.stage(),
        src_access: if before.is_write() {
            before.mask()
        } else {
            vk::AccessFlags::empty()
        },
        dst_stage: after.stage(),
        dst_access: after.mask(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_after_reads_need_no_barrier() {
        assert_eq!(
            barrier_between(Access::ComputeRead, Access::ComputeRead),
            None
        );
        assert_eq!(
            barrier_between(Access::TransferRead, Access::ComputeRead),
            None
        );
    }

    #[test]
    fn upload_then_shader_read_makes_the_copy_visible() {
        let b = barrier_between(Access::TransferWrite, Access::ComputeRead).unwrap();
        assert_eq!(b.src_stage, vk::PipelineStageFlags::TRANSFER);
        assert_eq!(b.src_access, vk::AccessFlags::TRANSFER_WRITE);
        assert_eq!(b.dst_stage, vk::PipelineStageFlags::COMPUTE_SHADER);
        assert_eq!(b.dst_access, vk::AccessFlags::SHADER_READ);
    }

    #[test]
    fn pass_to_pass_and_readback_barriers() {
        let b = barrier_between(Access::ComputeWrite, Access::ComputeRead).unwrap();
        assert_eq!(b.src_access, vk::AccessFlags::SHADER_WRITE);
        assert_eq!(b.dst_stage, vk::PipelineStageFlags::COMPUTE_SHADER);
        let b = barrier_between(Access::TransferWrite, Access::HostRead).unwrap();
        assert_eq!(b.dst_stage, vk::PipelineStageFlags::HOST);
        assert_eq!(b.dst_access, vk::AccessFlags::HOST_READ);
    }

    #[test]
    fn an_indirect_dispatch_waits_for_the_shader_that_wrote_its_counts() {
        let b = barrier_between(Access::ComputeWrite, Access::IndirectRead).unwrap();
        assert_eq!(b.src_access, vk::AccessFlags::SHADER_WRITE);
        assert_eq!(b.dst_stage, vk::PipelineStageFlags::DRAW_INDIRECT);
        assert_eq!(b.dst_access, vk::AccessFlags::INDIRECT_COMMAND_READ);
    }

    #[test]
    fn upload_then_vertex_pulling_waits_for_the_copy() {
        let b = barrier_between(Access::TransferWrite, Access::VertexRead).unwrap();
        assert_eq!(b.src_access, vk::AccessFlags::TRANSFER_WRITE);
        assert_eq!(b.dst_stage, vk::PipelineStageFlags::VERTEX_SHADER);
        assert_eq!(b.dst_access, vk::AccessFlags::SHADER_READ);
    }

    #[test]
    fn write_after_read_is_an_execution_dependency_only() {
        let b = barrier_between(Access::ComputeRead, Access::ComputeWrite).unwrap();
        assert!(b.src_access.is_empty());
        assert_eq!(b.src_stage, vk::PipelineStageFlags::COMPUTE_SHADER);
    }
}
