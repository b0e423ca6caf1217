//! The per-pixel output every scattering method writes (DESIGN §3, "Per-pixel layers").

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
}

impl Layers {
    pub fn new(width: u32, height: u32) -> Self {
        let pixels = width as usize * height as usize;
        Self {
            width,
            height,
            volume: vec![0.0; pixels * 4],
            visibility: vec![0.0; pixels],
            depth: vec![0.0; pixels],
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
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
