//! Pure helpers for recording work: workgroup counts and std430 parameter packing.

use super::error::{GpuError, GpuResult};

/// Workgroups of `local` invocations covering `items` along one axis.
pub fn group_count(items: u32, local: u32) -> u32 {
    items.div_ceil(local)
}

/// Workgroups covering a `width × height` grid with `local`-sized groups, checked against
/// the device's per-axis limit.
pub fn groups_2d(
    width: u32,
    height: u32,
    local: [u32; 2],
    max_groups: [u32; 3],
) -> GpuResult<[u32; 3]> {
    let groups = [
        group_count(width, local[0]),
        group_count(height, local[1]),
        1,
    ];
    if groups[0] > max_groups[0] || groups[1] > max_groups[1] {
        return Err(GpuError::Unsupported(format!(
            "a {width}×{height} grid needs {}×{} workgroups; the device allows {}×{}",
            groups[0], groups[1], max_groups[0], max_groups[1]
        )));
    }
    Ok(groups)
}

/// Workgroups covering `items` along x, checked against the device's limit.
pub fn groups_1d(items: u32, local: u32, max_groups: [u32; 3]) -> GpuResult<[u32; 3]> {
    let groups = group_count(items, local);
    if groups > max_groups[0] {
        return Err(GpuError::Unsupported(format!(
            "{items} items need {groups} workgroups; the device allows {}",
            max_groups[0]
        )));
    }
    Ok([groups, 1, 1])
}

/// Packs values by std430 rules (the layout of push constants and of the shaders'
/// parameter buffers): scalars on 4 bytes, vec4 and mat4 columns on 16.
#[derive(Clone, Debug, Default)]
pub struct Std430 {
    bytes: Vec<u8>,
}

impl Std430 {
    pub fn new() -> Self {
        Self::default()
    }

    fn align(&mut self, alignment: usize) {
        while !self.bytes.len().is_multiple_of(alignment) {
            self.bytes.push(0);
        }
    }

    pub fn f32(&mut self, value: f32) -> &mut Self {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
        self
    }

    pub fn u32(&mut self, value: u32) -> &mut Self {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
        self
    }

    pub fn i32(&mut self, value: i32) -> &mut Self {
        self.align(4);
        self.bytes.extend_from_slice(&value.to_le_bytes());
        self
    }

    /// A double, aligned to 8 bytes.
    pub fn f64(&mut self, value: f64) -> &mut Self {
        self.align(8);
        self.bytes.extend_from_slice(&value.to_le_bytes());
        self
    }

    /// A dvec2, aligned to 16 bytes.
    pub fn dvec2(&mut self, value: [f64; 2]) -> &mut Self {
        self.align(16);
        for v in value {
            self.bytes.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// A dvec4, aligned to 32 bytes.
    pub fn dvec4(&mut self, value: [f64; 4]) -> &mut Self {
        self.align(32);
        for v in value {
            self.bytes.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// Pads to `alignment` bytes: the end of a struct in an array.
    pub fn pad_to(&mut self, alignment: usize) -> &mut Self {
        self.align(alignment);
        self
    }

    pub fn vec4(&mut self, value: [f32; 4]) -> &mut Self {
        self.align(16);
        for v in value {
            self.bytes.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// A vec3 stored as a vec4 with w = 0 (std430 gives vec3 the alignment of vec4).
    pub fn vec3(&mut self, value: [f64; 3]) -> &mut Self {
        self.vec4([value[0] as f32, value[1] as f32, value[2] as f32, 0.0])
    }

    /// A column-major 4×4 matrix.
    pub fn mat4(&mut self, columns: [f32; 16]) -> &mut Self {
        self.align(16);
        for v in columns {
            self.bytes.extend_from_slice(&v.to_le_bytes());
        }
        self
    }

    /// The packed bytes, padded to the struct's 16-byte alignment.
    pub fn finish(&mut self) -> Vec<u8> {
        self.align(16);
        std::mem::take(&mut self.bytes)
    }

    pub fn len(&self) -> usize {
        self.bytes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn group_counts_cover_every_item() {
        assert_eq!(group_count(0, 8), 0);
        assert_eq!(group_count(1, 8), 1);
        assert_eq!(group_count(8, 8), 1);
        assert_eq!(group_count(1080, 8), 135);
        assert_eq!(group_count(1081, 8), 136);
        let big = [65_535; 3];
        assert_eq!(groups_2d(1920, 1080, [8, 8], big).unwrap(), [240, 135, 1]);
        assert_eq!(groups_1d(2_073_600, 256, big).unwrap(), [8100, 1, 1]);
    }

    #[test]
    fn grids_beyond_the_device_limit_are_refused() {
        let err = groups_2d(1 << 20, 8, [8, 8], [65_535; 3]).unwrap_err();
        assert!(err.to_string().contains("workgroups"), "{err}");
        assert!(groups_1d(65_535 * 256 + 1, 256, [65_535; 3]).is_err());
    }

    #[test]
    fn std430_aligns_vectors_and_matrices_to_16_bytes() {
        let mut p = Std430::new();
        p.u32(7);
        assert_eq!(p.len(), 4);
        p.vec4([1.0, 2.0, 3.0, 4.0]);
        assert_eq!(p.len(), 32, "the vec4 starts at offset 16");
        p.f32(0.5).f32(0.25).mat4([0.0; 16]);
        assert_eq!(p.len(), 48 + 64, "the mat4 starts at offset 48");
        p.u32(1);
        let bytes = p.finish();
        assert_eq!(bytes.len(), 128);
        assert_eq!(&bytes[0..4], &7u32.to_le_bytes());
        assert_eq!(&bytes[16..20], &1.0f32.to_le_bytes());
        assert_eq!(&bytes[32..36], &0.5f32.to_le_bytes());
    }

    #[test]
    fn std430_aligns_doubles_to_their_size() {
        let mut p = Std430::new();
        p.u32(1).f64(2.0);
        assert_eq!(p.len(), 16, "the double starts at offset 8");
        p.u32(3).dvec2([4.0, 5.0]);
        assert_eq!(p.len(), 48, "the dvec2 starts at offset 32");
        p.u32(6).dvec4([0.0; 4]);
        assert_eq!(p.len(), 96, "the dvec4 starts at offset 64");
        let bytes = p.finish();
        assert_eq!(&bytes[8..16], &2.0f64.to_le_bytes());
        assert_eq!(&bytes[40..48], &5.0f64.to_le_bytes());
    }
}
