//! crepuscular: art-directable volumetric light shafts.
//!
//! The core turns a [`Scene`] into per-pixel [`Layers`]: it rasterizes the light's shadow
//! map and the camera depth, then integrates single scattering along every view ray.

pub mod adaptive;
pub mod backend;
pub mod basis_kernels;
pub mod builtin;
pub mod camera;
pub mod channels;
pub mod composite;
pub mod control;
pub mod cutout;
pub mod diffusion;
pub mod epipolar;
pub mod error;
pub mod exr_file;
pub mod gpu;
pub mod holes;
pub mod layers;
pub mod mesh_builder;
pub mod minmax;
pub mod morphology;
pub mod phase;
pub mod prefiltered;
pub mod preview;
pub mod projective;
pub mod raster;
pub mod reference;
pub mod render;
mod running;
pub mod scene;
pub mod shadow_map;
pub mod shadowed_end;
pub mod silhouette;
pub mod slice_reach;
mod spans;
mod spare;
pub mod style;
pub mod sun_disc;
mod total_order;
pub mod transfer_function;
pub mod uniformity;
pub mod upsample;
pub mod visibility;

pub use backend::Backend;
pub use builtin::{builtin_scene, BUILTIN_SCENES};
pub use control::RenderControl;
pub use error::{Error, Result};
pub use layers::Layers;
pub use render::{
    render, render_scene, render_scene_timed, render_timed, CameraDepth, DepthKind, Frame,
    Geometry, StageTimes,
};
pub use scene::Scene;
pub use style::Style;

/// Lets go of the buffers kept from earlier frames for the next (the filtered basis and its
/// plan, the rectified map, min-max's pyramids, adaptive shading's grid, the camera depth,
/// the layers and the silhouette filter's copy of the shadow map): for a host that stops
/// rendering for a while. The next frame allocates them afresh.
pub fn release_kept_buffers() {
    layers::release_kept_buffers();
    adaptive::release_kept_buffers();
    epipolar::release_kept_buffers();
    uniformity::release_kept_buffers();
    minmax::release_kept_buffers();
    prefiltered::release_kept_buffers();
    raster::release_kept_buffers();
    upsample::release_kept_buffers();
    silhouette::release_kept_buffers();
}
