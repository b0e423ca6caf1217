//! Hole filling (2D morphology of the shadow map's depth) on the GPU, with the kernels of
//! [`crate::morphology`]: a disk as one pass of per-row chords, a box as a row pass and a
//! column pass. Minimum and maximum are exact, so the result equals the CPU's bit for bit.

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::shader::Shader;
use crate::error::Result;
use crate::morphology::{check_depth, in_disk, KernelShape, MorphologyDesc, MorphologyOp};

pub const STAGE: &str = "hole filling";
const LOCAL: [u32; 2] = [16, 16];
const PUSH_BYTES: u32 = 16;

/// One dispatch: the extremum over chords `half_widths[dy + rows]` for dy in [−rows, rows].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pass {
    /// Maximum (occluders shrink) or minimum (occluders grow).
    pub take_max: bool,
    pub vertical: bool,
    pub rows: i32,
    /// −1 where a row holds no kernel texel.
    pub half_widths: Vec<i32>,
}

/// Half-width of the disk's chord at each row offset −⌊r⌋..=⌊r⌋, by the CPU's own
/// membership test.
pub fn disk_chords(radius: f32) -> Vec<i32> {
    let rows = radius.max(0.0).floor() as i64;
    (-rows..=rows)
        .map(|dy| {
            if !in_disk(0, dy, radius) {
                return -1;
            }
            let mut w = 0;
            while in_disk(w + 1, dy, radius) {
                w += 1;
            }
            w as i32
        })
        .collect()
}

/// The dispatches that apply `desc`.
pub fn plan(desc: &MorphologyDesc) -> Vec<Pass> {
    let passes_for = |take_max: bool| -> Vec<Pass> {
        match desc.shape {
            KernelShape::Disk => {
                let half_widths = disk_chords(desc.radius_texels);
                vec![Pass {
                    take_max,
                    vertical: false,
                    rows: (half_widths.len() / 2) as i32,
                    half_widths,
                }]
            }
            KernelShape::Box => {
                let w = desc.radius_texels.max(0.0).floor() as i32;
                [false, true]
                    .into_iter()
                    .map(|vertical| Pass {
                        take_max,
                        vertical,
                        rows: 0,
                        half_widths: vec![w],
                    })
                    .collect()
            }
        }
    };
    let order: &[bool] = match desc.op {
        MorphologyOp::Dilate => &[false],
        MorphologyOp::Erode => &[true],
        MorphologyOp::Close => &[false, true],
        MorphologyOp::Open => &[true, false],
    };
    order
        .iter()
        .flat_map(|&take_max| passes_for(take_max))
        .collect()
}

fn push_constants(size: u32, pass: &Pass) -> Vec<u8> {
    Std430::new()
        .u32(size)
        .i32(pass.rows)
        .u32(pass.vertical as u32)
        .u32(pass.take_max as u32)
        .finish()
}

/// [`crate::morphology::apply`] on the GPU; also returns the GPU time in milliseconds.
pub fn apply(
    device: &Arc<Device>,
    depth: &[f32],
    size: u32,
    desc: &MorphologyDesc,
) -> Result<(Vec<f32>, Option<f64>)> {
    desc.validate()?;
    check_depth(depth, size)?;
    let passes = plan(desc);
    let groups = groups_2d(size, size, LOCAL, device.physical.max_workgroup_count)?;
    let run = || {
        let mut rec = Recorder::new(device, STAGE, passes.len() as u32, 3)?;
        let bytes = depth.len() as u64 * 4;
        let source = rec.upload(depth, "shadow-map depth")?;
        let scratch = [
            rec.storage(bytes, "morphology ping")?,
            rec.storage(bytes, "morphology pong")?,
        ];
        let chords = passes
            .iter()
            .map(|pass| rec.upload(&pass.half_widths, "kernel chords"))
            .collect::<Result<Vec<_>, _>>()?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Morphology, 3).push_constants(PUSH_BYTES);
        rec.timed(STAGE, |rec| {
            for (i, pass) in passes.iter().enumerate() {
                let input = if i == 0 {
                    &source
                } else {
                    &scratch[(i + 1) % 2]
                };
                rec.dispatch(
                    &desc,
                    &[input, &scratch[i % 2], &chords[i]],
                    &push_constants(size, pass),
                    groups,
                )?;
                rec.barrier(Access::ComputeWrite, Access::ComputeRead);
            }
            Ok(())
        })?;
        let result = if passes.is_empty() {
            &source
        } else {
            &scratch[(passes.len() - 1) % 2]
        };
        let back = rec.download(result, "filtered depth")?;
        let done = rec.submit_and_wait()?;
        Ok::<_, super::GpuError>((done.read(back)?, done.milliseconds(STAGE)))
    };
    Ok(run().map_err(|err| err.in_stage(STAGE))?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disk_chords_follow_the_membership_test() {
        assert_eq!(disk_chords(0.0), vec![0]);
        assert_eq!(disk_chords(1.0), vec![0, 1, 0]);
        assert_eq!(disk_chords(1.5), vec![1, 1, 1]);
        assert_eq!(disk_chords(2.0), vec![0, 1, 2, 1, 0]);
        let chords = disk_chords(7.3);
        for (row, &w) in chords.iter().enumerate() {
            let dy = row as i64 - 7;
            assert!(in_disk(w as i64, dy, 7.3) && !in_disk(w as i64 + 1, dy, 7.3));
        }
    }

    #[test]
    fn a_closing_grows_then_shrinks_and_a_box_splits_into_rows_and_columns() {
        let close = plan(&MorphologyDesc::close(KernelShape::Disk, 3.0));
        assert_eq!(close.len(), 2);
        assert!(!close[0].take_max && close[1].take_max);
        assert_eq!(close[0].rows, 3);
        let open = plan(&MorphologyDesc::open(KernelShape::Box, 2.7));
        let kinds: Vec<(bool, bool)> = open.iter().map(|p| (p.take_max, p.vertical)).collect();
        assert_eq!(
            kinds,
            [(true, false), (true, true), (false, false), (false, true)]
        );
        assert!(open.iter().all(|p| p.rows == 0 && p.half_widths == [2]));
    }

    #[test]
    fn push_constants_are_four_words() {
        let pass = &plan(&MorphologyDesc::erode(KernelShape::Disk, 2.0))[0];
        let bytes = push_constants(512, pass);
        assert_eq!(bytes.len(), PUSH_BYTES as usize);
        assert_eq!(&bytes[4..8], &2i32.to_le_bytes());
        assert_eq!(&bytes[12..16], &1u32.to_le_bytes());
    }
}
