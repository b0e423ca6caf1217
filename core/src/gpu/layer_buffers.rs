//! The three per-pixel layers a scattering stage writes on the device, and their trip back
//! into [`Layers`]: one place for the sizes and the read-back order every stage shares.

use super::buffer::Buffer;
use super::command::{Completed, Readback, Recorder};
use super::error::{GpuError, GpuResult};
use crate::layers::Layers;

/// Device buffers for `volume` (RGBA f32), `visibility` and `depth` (f32) of one image.
pub struct LayerBuffers {
    pub volume: Buffer,
    pub visibility: Buffer,
    pub depth: Buffer,
    width: u32,
    height: u32,
}

/// The layers' copies, readable once the submission has completed.
pub struct LayerReadback {
    volume: Readback,
    visibility: Readback,
    depth: Readback,
    width: u32,
    height: u32,
}

impl LayerBuffers {
    pub fn new(rec: &Recorder, width: u32, height: u32) -> GpuResult<Self> {
        let pixels = width as u64 * height as u64;
        Ok(Self {
            volume: rec.storage(pixels * 16, "volume layer")?,
            visibility: rec.storage(pixels * 4, "visibility layer")?,
            depth: rec.storage(pixels * 4, "depth layer")?,
            width,
            height,
        })
    }

    /// Records the copies back to the host after the work recorded so far.
    pub fn download(&self, rec: &mut Recorder) -> GpuResult<LayerReadback> {
        Ok(LayerReadback {
            volume: rec.download(&self.volume, "volume read-back")?,
            visibility: rec.download(&self.visibility, "visibility read-back")?,
            depth: rec.download(&self.depth, "depth read-back")?,
            width: self.width,
            height: self.height,
        })
    }
}

impl LayerReadback {
    /// The layers, in memory kept from an earlier frame's.
    pub fn read(self, done: &Completed) -> GpuResult<Layers> {
        let mut layers = Layers::for_overwrite(self.width, self.height).map_err(GpuError::host)?;
        done.read_into(self.volume, &mut layers.volume)?;
        done.read_into(self.visibility, &mut layers.visibility)?;
        done.read_into(self.depth, &mut layers.depth)?;
        Ok(layers)
    }
}
