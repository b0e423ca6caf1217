//! The per-pixel output every scattering method writes (DESIGN §3, "Per-pixel layers").

use rayon::prelude::*;

use crate::error::{Result, Sizing};
use crate::spare::Spare;

/// One pixel of every layer.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pixel {
    /// Premultiplied RGBA ([`Layers::volume`]).
    pub volume: [f32; 4],
    pub visibility: f32,
    pub depth: f32,
}

// SAFETY: a pixel is six f32s, for which all-zero bytes are 0.0.
unsafe impl bytemuck::Zeroable for Pixel {}

/// Linear float layers at the camera's resolution, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Layers {
    pub width: u32,
    pub height: u32,
    /// Premultiplied RGBA, interleaved: RGB = in-scattered radiance, A = 1 − transmittance.
    pub volume: Vec<f32>,
    /// Average light visibility V̄ along each view ray.
    pub visibility: Vec<f32>,
    /// Distance along the view ray to the first surface, or the max distance for background.
    pub depth: Vec<f32>,
    /// A pixel's width over its height, the camera's: EXR files carry it for viewers.
    pub pixel_aspect: f32,
}

// Dropped layers' buffers, kept for the next frame's (see `crate::spare`): at 1920×1080 the
// layers take 50 MB, and faulting in fresh pages for them took a third of adaptive
// shading's last pass.
static SPARE_VOLUME: Spare<f32> = Spare::with_slots(2, Sizing::Image);
static SPARE_VISIBILITY: Spare<f32> = Spare::with_slots(2, Sizing::Image);
static SPARE_DEPTH: Spare<f32> = Spare::with_slots(2, Sizing::Image);

/// Lets go of the layers' kept buffers ([`crate::release_kept_buffers`]).
pub(crate) fn release_kept_buffers() {
    for spare in [&SPARE_VOLUME, &SPARE_VISIBILITY, &SPARE_DEPTH] {
        spare.clear();
    }
}

impl Drop for Layers {
    fn drop(&mut self) {
        Self::keep_buffer(LayerBuffer::Volume, std::mem::take(&mut self.volume));
        Self::keep_buffer(
            LayerBuffer::Visibility,
            std::mem::take(&mut self.visibility),
        );
        Self::keep_buffer(LayerBuffer::Depth, std::mem::take(&mut self.depth));
    }
}

/// Which of the layers' buffers one is, for [`Layers::keep_buffer`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LayerBuffer {
    Volume,
    Visibility,
    Depth,
}

impl Layers {
    /// Keeps a buffer taken out of layers (lent to numpy, say) for a later frame's, as
    /// dropping the layers would have.
    pub fn keep_buffer(buffer: LayerBuffer, values: Vec<f32>) {
        match buffer {
            LayerBuffer::Volume => SPARE_VOLUME.keep(values),
            LayerBuffer::Visibility => SPARE_VISIBILITY.keep(values),
            LayerBuffer::Depth => SPARE_DEPTH.keep(values),
        }
    }

    /// Layers whose values are whatever an earlier frame's were, for callers that set
    /// every pixel.
    pub(crate) fn for_overwrite(width: u32, height: u32) -> Result<Self> {
        let pixels = width as usize * height as usize;
        let what = |layer: &'static str| move || format!("the {layer} layer ({width}×{height})");
        Ok(Self {
            width,
            height,
            volume: SPARE_VOLUME.try_take(pixels * 4, what("volume"))?,
            visibility: SPARE_VISIBILITY.try_take(pixels, what("visibility"))?,
            depth: SPARE_DEPTH.try_take(pixels, what("depth"))?,
            pixel_aspect: 1.0,
        })
    }

    pub fn new(width: u32, height: u32) -> Self {
        let pixels = width as usize * height as usize;
        Self {
            width,
            height,
            volume: vec![0.0; pixels * 4],
            visibility: vec![0.0; pixels],
            depth: vec![0.0; pixels],
            pixel_aspect: 1.0,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// The layers in bands of `rows` rows (the last one may be shorter), in parallel.
    pub fn par_bands_mut(
        &mut self,
        rows: usize,
    ) -> impl IndexedParallelIterator<Item = LayersBand<'_>> {
        let width = (self.width as usize).max(1);
        let pixels = (rows * width).max(1);
        self.volume
            .par_chunks_mut(4 * pixels)
            .zip(self.visibility.par_chunks_mut(pixels))
            .zip(self.depth.par_chunks_mut(pixels))
            .enumerate()
            .map(move |(band, ((volume, visibility), depth))| LayersBand {
                first_row: band * rows,
                rows: visibility.len() / width,
                volume,
                visibility,
                depth,
            })
    }

    pub fn volume_rgba(&self, x: u32, y: u32) -> [f32; 4] {
        let i = (y as usize * self.width as usize + x as usize) * 4;
        [
            self.volume[i],
            self.volume[i + 1],
            self.volume[i + 2],
            self.volume[i + 3],
        ]
    }
}

/// Rows `first_row..first_row + rows` of [`Layers`], borrowed for writing.
pub struct LayersBand<'a> {
    pub first_row: usize,
    pub rows: usize,
    pub volume: &'a mut [f32],
    pub visibility: &'a mut [f32],
    pub depth: &'a mut [f32],
}

impl LayersBand<'_> {
    /// Sets pixel `k`, counted from the band's first pixel.
    #[inline]
    pub fn set(&mut self, k: usize, pixel: &Pixel) {
        self.volume[k * 4..k * 4 + 4].copy_from_slice(&pixel.volume);
        self.visibility[k] = pixel.visibility;
        self.depth[k] = pixel.depth;
    }
}
