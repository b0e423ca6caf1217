//! Silhouette enhancement (1D epipolar dilation or closure, Eq. 3) on the GPU: one thread
//! per texel walks the rays of its cone that cross it, as [`crate::silhouette::apply_naive`]
//! does. The lines come from the CPU's own set-up ([`family_tables`]), packed here; the
//! shader evaluates the same expressions in the same precision and order, so the result
//! equals the CPU's bit for bit. Ray placement needs double precision in shaders.

use std::sync::Arc;

use super::barrier::Access;
use super::command::Recorder;
use super::compute_pipeline::ComputePipelineDesc;
use super::device::Device;
use super::dispatch::{groups_2d, Std430};
use super::error::GpuError;
use super::shader::Shader;
use crate::error::Result;
use crate::morphology::check_depth;
use crate::silhouette::{family_tables, Epipole, FamilyTables, SilhouetteDesc, SilhouetteOp};

pub const STAGE: &str = "silhouettes";
const LOCAL: [u32; 2] = [16, 16];
const PUSH_BYTES: u32 = 16;
/// Bytes of one `Family` in the shader (std430: a dvec2, nine scalars, padding to 16).
pub const FAMILY_BYTES: usize = 64;
/// Bytes of one column's `Placement` (a dvec4) and `Column` (four scalars).
pub const PLACEMENT_BYTES: usize = 32;
pub const COLUMN_BYTES: usize = 16;

/// The shader's tables for one filter, as the bytes of its storage buffers.
#[derive(Clone, Debug, PartialEq)]
pub struct PackedLines {
    pub family_count: u32,
    pub close: bool,
    pub families: Vec<u8>,
    /// Per family, `size` columns each.
    pub placements: Vec<u8>,
    pub columns: Vec<u8>,
    /// Every family's kernel lengths per ray, one after the other.
    pub steps: Vec<u32>,
}

/// Packs `tables` (of a `size`² map) in the shader's layout.
pub fn pack(tables: &[FamilyTables], size: u32, op: SilhouetteOp) -> PackedLines {
    let n = size as usize;
    let mut families = Vec::with_capacity(tables.len() * FAMILY_BYTES);
    let mut placements = Vec::with_capacity(tables.len() * n * PLACEMENT_BYTES);
    let mut columns = Vec::with_capacity(tables.len() * n * COLUMN_BYTES);
    let mut steps = Vec::new();
    for family in tables {
        let header = Std430::new()
            .dvec2([family.major, family.minor])
            .i32(family.x_major as i32)
            .i32(family.sign)
            .i32(family.fan as i32)
            .i32(family.rays.0)
            .i32(family.rays.1)
            .i32(family.steps_first)
            .i32(family.steps.len() as i32)
            .i32(steps.len() as i32)
            .f32(family.base)
            .finish();
        families.extend_from_slice(&header);
        for q in 0..n {
            for value in [
                family.along[q],
                family.shift[q],
                family.inv_along[q],
                family.inv_shift[q],
            ] {
                placements.extend_from_slice(&value.to_le_bytes());
            }
            let info = if family.fan {
                family.visits[q] as i32
            } else {
                family.rows[q]
            };
            columns.extend_from_slice(&family.scale[q].to_le_bytes());
            columns.extend_from_slice(&family.offset[q].to_le_bytes());
            columns.extend_from_slice(&family.unscale[q].to_le_bytes());
            columns.extend_from_slice(&info.to_le_bytes());
        }
        steps.extend_from_slice(&family.steps);
    }
    PackedLines {
        family_count: tables.len() as u32,
        close: op == SilhouetteOp::Close,
        families,
        placements,
        columns,
        steps,
    }
}

fn push_constants(size: u32, lines: &PackedLines) -> Vec<u8> {
    Std430::new()
        .u32(size)
        .u32(lines.family_count)
        .u32(lines.close as u32)
        .u32(0)
        .finish()
}

/// Whether `device` can run this stage (it needs double precision in shaders).
pub fn supported(device: &Device) -> bool {
    device.physical.float64
}

/// [`crate::silhouette::apply`] on the GPU; also returns the GPU time in milliseconds
/// (`None` where nothing ran or the device has no timestamps).
pub fn apply(
    device: &Arc<Device>,
    depth: &[f32],
    size: u32,
    epipole: Epipole,
    desc: &SilhouetteDesc,
) -> Result<(Vec<f32>, Option<f64>)> {
    let tables = family_tables(size, epipole, desc)?;
    check_depth(depth, size)?;
    let Some(tables) = tables else {
        return Ok((depth.to_vec(), None));
    };
    if !supported(device) {
        return Err(GpuError::Unsupported(format!(
            "the {STAGE} stage needs double precision in shaders (shaderFloat64)"
        ))
        .into());
    }
    let lines = pack(&tables, size, desc.op);
    let groups = groups_2d(size, size, LOCAL, device.physical.max_workgroup_count)?;
    let run = || {
        let mut rec = Recorder::new(device, STAGE, 1, 6)?;
        let source = rec.upload(depth, "shadow-map depth")?;
        let target = rec.storage(depth.len() as u64 * 4, "extruded depth")?;
        let families = rec.upload(&lines.families, "line families")?;
        let placements = rec.upload(&lines.placements, "ray placement per column")?;
        let columns = rec.upload(&lines.columns, "depth transform per column")?;
        let steps = rec.upload(&lines.steps, "kernel length per ray")?;
        rec.barrier(Access::TransferWrite, Access::ComputeRead);
        let desc = ComputePipelineDesc::new(Shader::Silhouette, 6).push_constants(PUSH_BYTES);
        rec.timed(STAGE, |rec| {
            rec.dispatch(
                &desc,
                &[&source, &target, &families, &placements, &columns, &steps],
                &push_constants(size, &lines),
                groups,
            )
        })?;
        let back = rec.download(&target, "extruded depth read-back")?;
        let done = rec.submit_and_wait()?;
        Ok::<_, GpuError>((done.read(back)?, done.milliseconds(STAGE)))
    };
    Ok(run().map_err(|err| err.in_stage(STAGE))?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn a_pinhole_epipole_inside_the_map_packs_four_cones() {
        let size = 48;
        let epipole = Epipole::Point(DVec3::new(20.3, 30.7, 12.0));
        let tables = family_tables(size, epipole, &SilhouetteDesc::close(6.0))
            .unwrap()
            .unwrap();
        assert_eq!(tables.len(), 4);
        let lines = pack(&tables, size, SilhouetteOp::Close);
        assert_eq!(lines.family_count, 4);
        assert!(lines.close);
        assert_eq!(lines.families.len(), 4 * FAMILY_BYTES);
        assert_eq!(lines.placements.len(), 4 * size as usize * PLACEMENT_BYTES);
        assert_eq!(lines.columns.len(), 4 * size as usize * COLUMN_BYTES);
        let word =
            |bytes: &[u8], at: usize| i32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        // The second family's steps follow the first's.
        assert_eq!(
            word(&lines.families, FAMILY_BYTES + 44),
            tables[0].steps.len() as i32
        );
        assert_eq!(word(&lines.families, 20), tables[0].sign);
        let base = f32::from_le_bytes(lines.families[48..52].try_into().unwrap());
        assert_eq!(base, 12.0);
        assert_eq!(
            lines.steps.len(),
            tables.iter().map(|t| t.steps.len()).sum::<usize>()
        );
    }

    #[test]
    fn an_orthographic_view_packs_one_family_with_row_offsets() {
        let size = 32;
        let epipole = Epipole::Direction(DVec3::new(0.3, -0.9, 0.2));
        let tables = family_tables(size, epipole, &SilhouetteDesc::dilate(5.0))
            .unwrap()
            .unwrap();
        assert_eq!(tables.len(), 1);
        assert!(!tables[0].fan && !tables[0].x_major && tables[0].sign == -1);
        let lines = pack(&tables, size, SilhouetteOp::Dilate);
        assert!(!lines.close);
        let info = |q: usize| {
            let at = q * COLUMN_BYTES + 12;
            i32::from_le_bytes(lines.columns[at..at + 4].try_into().unwrap())
        };
        assert!((0..size as usize).all(|q| info(q) == tables[0].rows[q]));
        // A slope of 1/3 moves line 0 by a third of a row per column.
        assert_eq!(info(30), 10);
    }

    #[test]
    fn short_kernels_and_a_view_along_the_light_need_no_dispatch() {
        let point = Epipole::Point(DVec3::new(3.0, 4.0, 5.0));
        assert_eq!(
            family_tables(16, point, &SilhouetteDesc::dilate(0.5)).unwrap(),
            None
        );
        let along = Epipole::Direction(DVec3::new(0.0, 0.0, -1.0));
        assert_eq!(
            family_tables(16, along, &SilhouetteDesc::close(4.0)).unwrap(),
            None
        );
        assert!(family_tables(16, point, &SilhouetteDesc::dilate(f32::NAN)).is_err());
    }

    #[test]
    fn push_constants_are_four_words() {
        let tables = family_tables(
            8,
            Epipole::Point(DVec3::new(-3.0, 4.0, 1.0)),
            &SilhouetteDesc::close(2.0),
        )
        .unwrap()
        .unwrap();
        let lines = pack(&tables, 8, SilhouetteOp::Close);
        let bytes = push_constants(8, &lines);
        assert_eq!(bytes.len(), PUSH_BYTES as usize);
        assert_eq!(&bytes[4..8], &lines.family_count.to_le_bytes());
        assert_eq!(&bytes[8..12], &1u32.to_le_bytes());
    }
}
