//! Shadow-map and camera-depth rasterization on the GPU: a graphics pipeline with a depth
//! attachment, drawn headless, with the semantics of [`crate::raster::rasterize`].
//!
//! - Vertices are pulled from storage buffers (positions, triangle corners, object ids) by
//!   `raster.vert`, which maps them with one `clip_from_world` matrix (f32): the CPU's
//!   `pixel_from_world` followed by the viewport's inverse, so that Vulkan's pixel centres
//!   are the CPU's samples. Vulkan snaps to the device's sub-pixel grid (8 bits on lavapipe
//!   and NVIDIA, as on the CPU).
//! - The viewport extends 128 pixels beyond the target on each side (as far as the
//!   device's viewport limits allow) and the scissor trims it back, so that Vulkan's
//!   clipping happens away from the samples, as the CPU's does (at its own, wider guard
//!   band).
//! - The image is drawn upside down (y flipped in clip space) and its rows reversed on
//!   read-back: Vulkan's top-left rule (lavapipe's, and D3D-style GPUs') then becomes the
//!   CPU's rule, which owns left and bottom edges of rows counted downwards, so that even
//!   samples exactly on an edge go to the same triangle.
//! - Depth goes into a D32_SFLOAT attachment through a [`DepthEncoding`]: affine in depth
//!   for orthographic targets, `near / w` for pinhole cameras ("reversed" depth, whose f32
//!   keeps w's relative precision at every distance). Read-back inverts it exactly.
//! - The shadow map's object ids come from the same pass: `raster.frag` writes the
//!   triangle's id into an R32_UINT colour attachment, which the depth test guards. The
//!   camera depth is a depth-only pass (no fragment shader).
//! - Frames with alpha-cut triangles ([`crate::cutout`]) draw with `raster_cut.vert` and a
//!   fragment shader that samples each triangle's mask at its perspective-correct texture
//!   coordinates, as the CPU does, and discards where it is empty (`raster_cut.frag` with
//!   ids, `raster_cut_depth.frag` without).
//! - Ties keep the first triangle, as on the CPU: the depth test is strict and Vulkan
//!   applies it in primitive order.
//!
//! Projected depth (a projective epipolar map, z/w without depth clipping) stays on the
//! CPU: it needs depth clamping, which the device is not asked for.

use std::sync::{Arc, Mutex};

use ash::vk;
use glam::{DMat4, DVec4};
use rayon::prelude::*;

use super::barrier::Access;
use super::command::Recorder;
use super::device::Device;
use super::dispatch::Std430;
use super::error::{GpuError, GpuResult};
use super::graphics_pipeline::{fitting_guard, Framebuffer, GraphicsPipelineDesc};
use super::image::{Image, ImageDesc};
use super::shader::Shader;
use crate::error::Result;
use crate::raster::{DepthTarget, RasterDesc, Rasterizer, NO_OBJECT};
use crate::render::Geometry;

pub const SHADOW_MAP_STAGE: &str = "shadow map";
pub const CAMERA_DEPTH_STAGE: &str = "camera depth";
/// The vertex shader's `clip_from_world`.
const PUSH_BYTES: u32 = 64;
/// Positions, triangle corners, object ids.
const BUFFERS: u32 = 3;
/// Those, and for alpha-cut triangles: texture coordinates, each triangle's mask, the masks'
/// table (offset, width, height, threshold) and their texels.
const CUT_BUFFERS: u32 = 7;
/// Pixels the viewport extends beyond each side of the target. Without it, Vulkan clips
/// triangles at the image border and the vertices it makes there snap off the original
/// edges, moving them across samples near the border; a wider band makes lavapipe
/// interpolate depth across larger clipped triangles, in f32, and its error grows with
/// the band (measured on the built-in scenes at 640×360: 3e-5 of the depth range at 128
/// pixels, 7e-5 at 256, 1.6e-4 at 512).
const GUARD_BAND: u32 = 128;

/// How depth is stored in the D32_SFLOAT attachment, whose values must lie in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DepthEncoding {
    /// stored = (depth − offset) · scale, nearer is smaller: orthographic targets.
    Linear { offset: f64, scale: f64 },
    /// stored = near / w, nearer is larger: pinhole cameras, whose depth is w ≥ near.
    Reciprocal { near: f64 },
}

impl DepthEncoding {
    /// The encoding for `desc`. `geometry_bounds` gives the (min, max) depth of the
    /// geometry, needed where the target keeps every depth (the shadow map).
    pub fn for_target(
        desc: &RasterDesc,
        geometry_bounds: impl FnOnce() -> (f64, f64),
    ) -> GpuResult<Self> {
        if desc.projected_depth {
            return Err(GpuError::Unsupported(
                "rasterizing projected depth (projective maps) on the GPU".to_owned(),
            ));
        }
        if desc.perspective {
            if !(desc.near_w > 0.0 && desc.near_w.is_finite()) {
                return Err(GpuError::Unsupported(format!(
                    "a perspective target with the near plane at w = {}",
                    desc.near_w
                )));
            }
            return Ok(DepthEncoding::Reciprocal { near: desc.near_w });
        }
        let (near, far) = desc.depth_range;
        let (low, high) = if near.is_finite() && far.is_finite() {
            // The clip range itself: Vulkan's clipping at 0 and 1 is the CPU's range test.
            (near, far)
        } else {
            let (min, max) = geometry_bounds();
            // A margin keeps f32 rounding in the vertex shader from clipping the extremes.
            let pad = 0.01 * (max - min) + 1e-5 * min.abs().max(max.abs()).max(1.0);
            (
                if near.is_finite() { near } else { min - pad },
                if far.is_finite() { far } else { max + pad },
            )
        };
        if !(high > low && low.is_finite() && high.is_finite()) {
            return Err(GpuError::Unsupported(format!(
                "a depth range of [{low}, {high}]"
            )));
        }
        Ok(DepthEncoding::Linear {
            offset: low,
            scale: 1.0 / (high - low),
        })
    }

    /// The attachment's value where nothing was drawn.
    pub fn cleared(&self) -> f32 {
        match self {
            DepthEncoding::Linear { .. } => 1.0,
            DepthEncoding::Reciprocal { .. } => 0.0,
        }
    }

    /// The depth test that keeps the nearer sample, the first of equals.
    pub fn compare_op(&self) -> vk::CompareOp {
        match self {
            DepthEncoding::Linear { .. } => vk::CompareOp::LESS,
            DepthEncoding::Reciprocal { .. } => vk::CompareOp::GREATER,
        }
    }

    pub fn encode(&self, depth: f64) -> f64 {
        match *self {
            DepthEncoding::Linear { offset, scale } => (depth - offset) * scale,
            DepthEncoding::Reciprocal { near } => near / depth,
        }
    }

    /// The depth a stored value encodes, +∞ for [`DepthEncoding::cleared`].
    pub fn decode(&self, stored: f32) -> f64 {
        if stored == self.cleared() {
            return f64::INFINITY;
        }
        match *self {
            DepthEncoding::Linear { offset, scale } => offset + stored as f64 / scale,
            DepthEncoding::Reciprocal { near } => near / stored as f64,
        }
    }

    /// The clip-space z row: z_clip / w_clip is the stored value, given the rows of
    /// `pixel_from_world` (depth in row 2, w in row 3).
    fn clip_depth_row(&self, pixel_from_world: &DMat4) -> DVec4 {
        match *self {
            DepthEncoding::Linear { offset, scale } => {
                (pixel_from_world.row(2) - offset * pixel_from_world.row(3)) * scale
            }
            // z_clip = near (a constant), so z_clip ≤ w_clip is the near plane w ≥ near.
            DepthEncoding::Reciprocal { near } => DVec4::new(0.0, 0.0, 0.0, near),
        }
    }
}

/// World to Vulkan clip space for a `width × height` target drawn with
/// [`guarded_viewport`](super::graphics_pipeline::guarded_viewport)`(width, height, guard)`: pixel centre (x + ½, y + ½) of
/// `pixel_from_world` is Vulkan's sample of pixel (x, height − 1 − y), upside down, and
/// z / w is the encoded depth.
pub fn clip_from_world(
    pixel_from_world: &DMat4,
    width: u32,
    height: u32,
    guard: u32,
    encoding: &DepthEncoding,
) -> DMat4 {
    // Framebuffer x' = x and y' = height − y; the viewport maps −guard..size + guard to
    // NDC −1..1. Multiplied through by w, since x and y here are x·w and y·w.
    let w = pixel_from_world.row(3);
    let guard = guard as f64;
    let x = (pixel_from_world.row(0) + guard * w) * (2.0 / (width as f64 + 2.0 * guard)) - w;
    let y = ((height as f64 + guard) * w - pixel_from_world.row(1))
        * (2.0 / (height as f64 + 2.0 * guard))
        - w;
    DMat4::from_cols(x, y, encoding.clip_depth_row(pixel_from_world), w).transpose()
}

/// The smallest and largest depth of the geometry's vertices.
pub fn depth_bounds(geometry: &Geometry, pixel_from_world: &DMat4) -> (f64, f64) {
    let row = geometry.pixel_from_local(pixel_from_world).row(2);
    geometry
        .positions
        .par_iter()
        .map(|p| row.dot(DVec4::new(p[0] as f64, p[1] as f64, p[2] as f64, 1.0)))
        .fold(
            || (f64::INFINITY, f64::NEG_INFINITY),
            |(lo, hi), z| (lo.min(z), hi.max(z)),
        )
        .reduce(
            || (f64::INFINITY, f64::NEG_INFINITY),
            |a, b| (a.0.min(b.0), a.1.max(b.1)),
        )
}

/// Depth as the CPU stores it from the upside-down read-back: rows reversed, decoded,
/// +∞ outside `desc.depth_range`; ids likewise reversed, and cleared where depth is +∞.
fn decode_target(
    stored: &[f32],
    ids: &[u32],
    encoding: &DepthEncoding,
    desc: &RasterDesc,
) -> DepthTarget {
    let (near, far) = desc.depth_range;
    let width = desc.width as usize;
    let mut depth = vec![f32::INFINITY; stored.len()];
    depth
        .par_chunks_mut(width)
        .zip(stored.par_chunks(width).rev())
        .for_each(|(row, stored_row)| {
            for (out, &value) in row.iter_mut().zip(stored_row) {
                let decoded = encoding.decode(value);
                if decoded >= near && decoded <= far {
                    *out = decoded as f32;
                }
            }
        });
    let mut ids: Vec<u32> = ids.chunks(width.max(1)).rev().flatten().copied().collect();
    ids.par_iter_mut()
        .zip(&depth)
        .filter(|(_, d)| d.is_infinite())
        .for_each(|(id, _)| *id = NO_OBJECT);
    DepthTarget {
        width: desc.width,
        height: desc.height,
        depth,
        ids,
    }
}

/// [`Rasterizer`] on a Vulkan device's graphics queue; remembers the GPU time of its last
/// draw.
pub struct GpuRasterizer {
    device: Arc<Device>,
    stage: &'static str,
    /// Whether the pass also writes object ids.
    ids: bool,
    milliseconds: Mutex<Option<f64>>,
}

impl GpuRasterizer {
    /// Depth and object ids, for the shadow map.
    pub fn shadow_map(device: &Arc<Device>) -> Self {
        Self::new(device, SHADOW_MAP_STAGE, true)
    }

    /// Depth alone (its [`DepthTarget::ids`] are empty), for the camera depth.
    pub fn camera_depth(device: &Arc<Device>) -> Self {
        Self::new(device, CAMERA_DEPTH_STAGE, false)
    }

    fn new(device: &Arc<Device>, stage: &'static str, ids: bool) -> Self {
        Self {
            device: device.clone(),
            stage,
            ids,
            milliseconds: Mutex::new(None),
        }
    }

    /// Whether the device can draw a `width × height` target: a graphics queue and
    /// framebuffers that large.
    pub fn fits(&self, width: u32, height: u32) -> bool {
        let [max_width, max_height] = self.device.physical.max_render_size;
        self.device.physical.graphics && width <= max_width && height <= max_height
    }

    pub fn milliseconds(&self) -> Option<f64> {
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn run(
        &self,
        geometry: &Geometry,
        pixel_from_world: &DMat4,
        desc: &RasterDesc,
    ) -> GpuResult<DepthTarget> {
        let device = &self.device;
        let (width, height) = (desc.width, desc.height);
        if !self.fits(width, height) {
            return Err(GpuError::Unsupported(format!(
                "a {width}×{height} depth target (the device draws up to {:?}{})",
                device.physical.max_render_size,
                if device.physical.graphics {
                    ""
                } else {
                    ", and its queue has no graphics"
                }
            )));
        }
        let vertex_count = u32::try_from(geometry.triangles.len() * 3).map_err(|_| {
            GpuError::Unsupported(format!(
                "drawing {} triangles in one call",
                geometry.triangles.len()
            ))
        })?;
        let cutouts = geometry.cutouts.as_ref().filter(|c| c.cuts_any());
        // The masks' table and their texels, one after another.
        // Six words a mask, as `raster_cut.glsl`'s `Mask`.
        let (mask_table, texels): (Vec<u32>, Vec<f32>) = match cutouts {
            None => (Vec::new(), Vec::new()),
            Some(cutouts) => {
                let mut table = Vec::with_capacity(6 * cutouts.masks.len());
                let mut texels = Vec::new();
                for mask in cutouts.masks {
                    let offset = u32::try_from(texels.len()).map_err(|_| {
                        GpuError::Unsupported("alpha masks of more than 2³² texels".to_owned())
                    })?;
                    table.extend([
                        offset,
                        mask.width,
                        mask.height,
                        mask.threshold.to_bits(),
                        mask.shader_sampling(),
                        mask.border.to_bits(),
                    ]);
                    texels.extend_from_slice(&mask.alpha);
                }
                (table, texels)
            }
        };
        let largest = std::mem::size_of_val(geometry.positions)
            .max(std::mem::size_of_val(geometry.triangles))
            .max(std::mem::size_of_val(texels.as_slice())) as u64;
        if largest > device.physical.max_storage_buffer_range as u64 {
            return Err(GpuError::Unsupported(format!(
                "a {largest}-byte geometry buffer (the device binds up to {})",
                device.physical.max_storage_buffer_range
            )));
        }
        let encoding =
            DepthEncoding::for_target(desc, || depth_bounds(geometry, pixel_from_world))?;
        let (vertex, buffers) = match cutouts {
            None => (Shader::RasterVertex, BUFFERS),
            Some(_) => (Shader::RasterCutVertex, CUT_BUFFERS),
        };
        let mut pipeline_desc = GraphicsPipelineDesc::depth_only(vertex, buffers)
            .push_constants(PUSH_BYTES)
            .depth_compare(encoding.compare_op());
        pipeline_desc = match (self.ids, cutouts.is_some()) {
            (true, false) => pipeline_desc.with_ids(Shader::RasterFragment),
            (true, true) => pipeline_desc.with_ids(Shader::RasterCutFragment),
            (false, true) => pipeline_desc.with_fragment(Shader::RasterCutDepthFragment),
            (false, false) => pipeline_desc,
        };
        let pipeline = device.graphics_pipeline(&pipeline_desc)?;
        // Attachments exist before the recorder, so that its Drop (which waits for work
        // in flight) runs before theirs.
        let depth_image = Image::new(device, ImageDesc::depth(width, height), "depth target")?;
        let id_image = if self.ids {
            Some(Image::new(
                device,
                ImageDesc::ids(width, height),
                "id target",
            )?)
        } else {
            None
        };
        let physical = &device.physical;
        let guard = fitting_guard(
            width,
            height,
            GUARD_BAND,
            physical.max_viewport_dimensions,
            physical.viewport_bounds_range,
        );
        let framebuffer =
            Framebuffer::new(device, &pipeline, &depth_image, id_image.as_ref(), guard)?;

        let mut rec = Recorder::new(device, self.stage, 1, buffers)?;
        let positions = rec.upload(geometry.positions, "positions")?;
        let corners = rec.upload(geometry.triangles, "triangle corners")?;
        let object_ids = rec.upload(geometry.object_ids, "object ids")?;
        let cut_buffers = match cutouts {
            None => None,
            Some(cutouts) => Some([
                rec.upload(cutouts.uvs, "texture coordinates")?,
                rec.upload(cutouts.triangle_masks, "triangle masks")?,
                rec.upload(&mask_table, "alpha masks' table")?,
                rec.upload(&texels, "alpha masks' texels")?,
            ]),
        };
        rec.barrier(Access::TransferWrite, Access::VertexRead);
        if cut_buffers.is_some() {
            rec.barrier(Access::TransferWrite, Access::FragmentRead);
        }
        // The vertex shader's matrix takes the positions as stored, relative to the origin.
        let pixel_from_local = geometry.pixel_from_local(pixel_from_world);
        let clip = clip_from_world(&pixel_from_local, width, height, guard, &encoding).as_mat4();
        let push = Std430::new().mat4(clip.to_cols_array()).finish();
        let clear = [
            vk::ClearValue {
                depth_stencil: vk::ClearDepthStencilValue {
                    depth: encoding.cleared(),
                    stencil: 0,
                },
            },
            vk::ClearValue {
                color: vk::ClearColorValue {
                    uint32: [NO_OBJECT, 0, 0, 0],
                },
            },
        ];
        let attachments = pipeline_desc.attachment_formats().len();
        let mut bound = vec![&positions, &corners, &object_ids];
        if let Some(cut) = &cut_buffers {
            bound.extend(cut.iter());
        }
        rec.timed(self.stage, |rec| {
            rec.draw(
                &pipeline_desc,
                &framebuffer,
                &clear[..attachments],
                &bound,
                &push,
                vertex_count,
            )
        })?;
        let depth_back = rec.download_image(&depth_image, "depth read-back")?;
        let id_back = match &id_image {
            Some(image) => Some(rec.download_image(image, "id read-back")?),
            None => None,
        };
        let done = rec.submit_and_wait()?;
        *self.milliseconds.lock().unwrap_or_else(|p| p.into_inner()) =
            done.milliseconds(self.stage);
        let stored: Vec<f32> = done.read(depth_back)?;
        let ids: Vec<u32> = match id_back {
            Some(back) => done.read(back)?,
            None => Vec::new(),
        };
        Ok(decode_target(&stored, &ids, &encoding, desc))
    }
}

impl Rasterizer for GpuRasterizer {
    fn rasterize(
        &self,
        geometry: &Geometry,
        pixel_from_world: &DMat4,
        desc: &RasterDesc,
    ) -> Result<DepthTarget> {
        Ok(self
            .run(geometry, pixel_from_world, desc)
            .map_err(|err| err.in_stage(self.stage))?)
    }
}

#[cfg(test)]
mod tests {
    use super::super::graphics_pipeline::guarded_viewport;
    use super::*;
    use glam::DVec3;

    /// Vulkan's viewport transform: clip space to framebuffer coordinates and depth.
    fn to_framebuffer(clip: DVec4, viewport: &vk::Viewport) -> DVec3 {
        let ndc = clip / clip.w;
        DVec3::new(
            viewport.x as f64 + (ndc.x + 1.0) * viewport.width as f64 / 2.0,
            viewport.y as f64 + (ndc.y + 1.0) * viewport.height as f64 / 2.0,
            ndc.z,
        )
    }

    fn a_pinhole() -> DMat4 {
        // 90° field of view on 64×48, looking down −Z: (px·w, py·w, w, w) with w = −z.
        DMat4::from_cols(
            DVec4::new(32.0, 0.0, 0.0, 0.0),
            DVec4::new(0.0, -32.0, 0.0, 0.0),
            DVec4::new(-32.0, -24.0, -1.0, -1.0),
            DVec4::ZERO,
        )
    }

    #[test]
    fn linear_depth_round_trips_and_the_clear_value_is_empty() {
        let encoding = DepthEncoding::Linear {
            offset: -3.0,
            scale: 0.125,
        };
        for depth in [-3.0, -1.5, 0.0, 4.9] {
            let stored = encoding.encode(depth) as f32;
            assert!((0.0..1.0).contains(&stored));
            assert!((encoding.decode(stored) - depth).abs() < 1e-6);
        }
        assert_eq!(encoding.decode(encoding.cleared()), f64::INFINITY);
        assert_eq!(encoding.compare_op(), vk::CompareOp::LESS);
    }

    #[test]
    fn reciprocal_depth_keeps_relative_precision_at_every_distance() {
        let encoding = DepthEncoding::Reciprocal { near: 0.1 };
        for depth in [0.1, 1.0, 37.5, 1000.0, 1e5] {
            let stored = encoding.encode(depth) as f32;
            assert!(stored > 0.0 && stored <= 1.0);
            let relative = (encoding.decode(stored) - depth).abs() / depth;
            assert!(relative < 1e-7, "{depth}: {relative}");
        }
        assert_eq!(encoding.decode(0.0), f64::INFINITY);
        assert_eq!(encoding.compare_op(), vk::CompareOp::GREATER);
    }

    #[test]
    fn each_target_gets_its_encoding() {
        let no_bounds = || -> (f64, f64) { panic!("bounds are not needed") };
        let pinhole = RasterDesc::perspective(64, 48, 0.5, 80.0);
        assert_eq!(
            DepthEncoding::for_target(&pinhole, no_bounds).unwrap(),
            DepthEncoding::Reciprocal { near: 0.5 }
        );
        let orthographic_camera = RasterDesc {
            depth_range: (2.0, 10.0),
            ..RasterDesc::orthographic(64, 48)
        };
        assert_eq!(
            DepthEncoding::for_target(&orthographic_camera, no_bounds).unwrap(),
            DepthEncoding::Linear {
                offset: 2.0,
                scale: 0.125
            }
        );
        // The shadow map keeps every depth: the geometry's, with a margin inside (0, 1).
        let shadow = RasterDesc::orthographic(256, 256);
        let encoding = DepthEncoding::for_target(&shadow, || (-4.0, 6.0)).unwrap();
        for depth in [-4.0, 6.0] {
            let stored = encoding.encode(depth);
            assert!(stored > 0.005 && stored < 0.995, "{stored}");
        }
        // A flat map (every vertex at one depth) still gets a non-empty range.
        let flat = DepthEncoding::for_target(&shadow, || (100.0, 100.0)).unwrap();
        assert!((flat.encode(100.0) - 0.5).abs() < 1e-9);
        assert!(DepthEncoding::for_target(&RasterDesc::projective(8, 8, 0.1), no_bounds).is_err());
    }

    #[test]
    fn pixel_centres_land_on_vulkan_sample_positions_upside_down() {
        let (width, height) = (64, 48);
        let encoding = DepthEncoding::Reciprocal { near: 0.25 };
        let pinhole = a_pinhole();
        for guard in [0, 17, 192] {
            let clip = clip_from_world(&pinhole, width, height, guard, &encoding);
            let viewport = guarded_viewport(width, height, guard);
            for world in [
                DVec3::new(0.0, 0.0, -1.0),
                DVec3::new(0.3, -0.2, -2.0),
                DVec3::new(-1.0, 0.7, -9.0),
            ] {
                let p = world.extend(1.0);
                let pixel = pinhole * p;
                let (x, y) = (pixel.x / pixel.w, pixel.y / pixel.w);
                let expected = DVec3::new(x, height as f64 - y, 0.25 / pixel.w);
                let got = to_framebuffer(clip * p, &viewport);
                assert!(
                    (got - expected).abs().max_element() < 1e-12,
                    "{got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn clipping_happens_at_the_guard_band() {
        // Vulkan keeps −w ≤ x ≤ w: the target's pixels −guard..width + guard.
        let encoding = DepthEncoding::Linear {
            offset: 0.0,
            scale: 1.0,
        };
        let clip = clip_from_world(&DMat4::IDENTITY, 64, 32, 40, &encoding);
        let inside = |x: f64, y: f64| {
            let c = clip * DVec4::new(x, y, 0.5, 1.0);
            c.x.abs() <= c.w && c.y.abs() <= c.w
        };
        assert!(inside(-39.9, -39.9) && inside(103.9, 71.9));
        assert!(!inside(-40.1, 0.0) && !inside(0.0, 72.1));
    }

    #[test]
    fn the_reciprocal_encoding_clips_at_the_near_plane_only() {
        let encoding = DepthEncoding::Reciprocal { near: 0.25 };
        let clip = clip_from_world(&a_pinhole(), 64, 48, 0, &encoding);
        // Vulkan keeps 0 ≤ z ≤ w.
        let kept = |depth: f64| {
            let c = clip * DVec4::new(0.0, 0.0, -depth, 1.0);
            0.0 <= c.z && c.z <= c.w
        };
        assert!(!kept(0.2));
        assert!(kept(0.25) && kept(1.0) && kept(1e6));
    }

    #[test]
    fn orthographic_depth_is_affine_in_clip_space() {
        // Texel x = world x, texel y = world y, depth = world z.
        let encoding = DepthEncoding::Linear {
            offset: -1.0,
            scale: 0.5,
        };
        let clip = clip_from_world(&DMat4::IDENTITY, 16, 8, 4, &encoding);
        let viewport = guarded_viewport(16, 8, 4);
        let got = to_framebuffer(clip * DVec4::new(3.5, 2.5, 0.0, 1.0), &viewport);
        assert!((got - DVec3::new(3.5, 8.0 - 2.5, 0.5)).abs().max_element() < 1e-12);
    }

    #[test]
    fn read_back_values_become_the_cpu_depths_and_ids_rows_reversed() {
        let desc = RasterDesc::perspective(2, 2, 1.0, 50.0);
        let encoding = DepthEncoding::Reciprocal { near: 1.0 };
        // Bottom row first: empty, at 4; then beyond the far plane (100), at the near plane.
        let stored = [0.0, 0.25, 0.01, 1.0];
        let target = decode_target(&stored, &[NO_OBJECT, 7, 8, 9], &encoding, &desc);
        assert_eq!(target.depth, [f32::INFINITY, 1.0, f32::INFINITY, 4.0]);
        assert_eq!(target.ids, [NO_OBJECT, 9, NO_OBJECT, 7]);
        let depth_only = decode_target(&stored, &[], &encoding, &desc);
        assert!(depth_only.ids.is_empty());
    }

    #[test]
    fn flipping_rows_turns_the_top_left_rule_into_the_cpus() {
        // The CPU owns a horizontal edge when its interior lies above it (rows downwards):
        // a bottom edge. Drawn upside down, that edge is on top, which Vulkan owns.
        let (height, edge_y) = (8, 5.5);
        let encoding = DepthEncoding::Linear {
            offset: 0.0,
            scale: 1.0,
        };
        let clip = clip_from_world(&DMat4::IDENTITY, 8, height, 0, &encoding);
        let viewport = guarded_viewport(8, height, 0);
        let flipped = |y: f64| to_framebuffer(clip * DVec4::new(0.0, y, 0.0, 1.0), &viewport).y;
        assert!(
            flipped(edge_y - 1.0) > flipped(edge_y),
            "the interior lies below on the GPU"
        );
    }

    #[test]
    fn depth_bounds_cover_every_vertex() {
        let positions = [[0.0, 0.0, 1.0], [1.0, 2.0, -3.0], [5.0, 0.0, 2.5]];
        let triangles = [[0, 1, 2]];
        let ids = [1];
        let geometry = Geometry {
            positions: &positions,
            triangles: &triangles,
            object_ids: &ids,
            origin: glam::DVec3::ZERO,
            cutouts: None,
        };
        let doubled = DMat4::from_scale(DVec3::new(1.0, 1.0, 2.0));
        assert_eq!(depth_bounds(&geometry, &doubled), (-6.0, 5.0));
    }
}
