//! SPIR-V compiled from `shaders/` at build time, embedded in the binary, and turned into
//! shader modules.

use ash::vk;

use super::error::{GpuError, GpuResult, VkContext};

/// The shaders, compute and graphics, by their file in `shaders/`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Shader {
    March,
    Morphology,
    Transfer,
    Prefix,
    Prefiltered,
    /// Adaptive shading's dark floor from the coarse grid, for `prefiltered.comp`.
    AdaptiveFloor,
    /// The rectified map's uniformity table, which prefiltered evaluation reads.
    Uniformity,
    Upsample,
    Rectify,
    Silhouette,
    Holes,
    /// The depth passes' vertex shader.
    RasterVertex,
    /// The shadow map's fragment shader, which writes object ids.
    RasterFragment,
    /// The depth passes' vertex shader where triangles are cut by alpha masks.
    RasterCutVertex,
    /// The shadow map's fragment shader where triangles are cut by alpha masks.
    RasterCutFragment,
    /// The camera depth's fragment shader where triangles are cut by alpha masks.
    RasterCutDepthFragment,
    /// The clock probe (needs VK_KHR_shader_clock).
    Clock,
}

impl Shader {
    pub const ALL: [Shader; 17] = [
        Shader::March,
        Shader::Morphology,
        Shader::Transfer,
        Shader::Prefix,
        Shader::Prefiltered,
        Shader::AdaptiveFloor,
        Shader::Uniformity,
        Shader::Upsample,
        Shader::Rectify,
        Shader::Silhouette,
        Shader::Holes,
        Shader::RasterVertex,
        Shader::RasterFragment,
        Shader::RasterCutVertex,
        Shader::RasterCutFragment,
        Shader::RasterCutDepthFragment,
        Shader::Clock,
    ];

    /// The source's file name in `shaders/`.
    pub fn name(self) -> &'static str {
        match self {
            Shader::March => "march.comp",
            Shader::Morphology => "morphology.comp",
            Shader::Transfer => "transfer.comp",
            Shader::Prefix => "prefix.comp",
            Shader::Prefiltered => "prefiltered.comp",
            Shader::AdaptiveFloor => "adaptive_floor.comp",
            Shader::Uniformity => "uniformity.comp",
            Shader::Upsample => "upsample.comp",
            Shader::Rectify => "rectify.comp",
            Shader::Silhouette => "silhouette.comp",
            Shader::Holes => "holes.comp",
            Shader::RasterVertex => "raster.vert",
            Shader::RasterFragment => "raster.frag",
            Shader::RasterCutVertex => "raster_cut.vert",
            Shader::RasterCutFragment => "raster_cut.frag",
            Shader::RasterCutDepthFragment => "raster_cut_depth.frag",
            Shader::Clock => "clock.comp",
        }
    }

    /// The pipeline stage the shader runs in.
    pub fn stage(self) -> vk::ShaderStageFlags {
        match self {
            Shader::RasterVertex | Shader::RasterCutVertex => vk::ShaderStageFlags::VERTEX,
            Shader::RasterFragment | Shader::RasterCutFragment | Shader::RasterCutDepthFragment => {
                vk::ShaderStageFlags::FRAGMENT
            }
            _ => vk::ShaderStageFlags::COMPUTE,
        }
    }

    pub fn spirv(self) -> &'static [u8] {
        match self {
            Shader::March => include_bytes!(concat!(env!("OUT_DIR"), "/march.comp.spv")),
            Shader::Morphology => {
                include_bytes!(concat!(env!("OUT_DIR"), "/morphology.comp.spv"))
            }
            Shader::Transfer => include_bytes!(concat!(env!("OUT_DIR"), "/transfer.comp.spv")),
            Shader::Prefix => include_bytes!(concat!(env!("OUT_DIR"), "/prefix.comp.spv")),
            Shader::Prefiltered => {
                include_bytes!(concat!(env!("OUT_DIR"), "/prefiltered.comp.spv"))
            }
            Shader::AdaptiveFloor => {
                include_bytes!(concat!(env!("OUT_DIR"), "/adaptive_floor.comp.spv"))
            }
            Shader::Uniformity => {
                include_bytes!(concat!(env!("OUT_DIR"), "/uniformity.comp.spv"))
            }
            Shader::Upsample => include_bytes!(concat!(env!("OUT_DIR"), "/upsample.comp.spv")),
            Shader::Rectify => include_bytes!(concat!(env!("OUT_DIR"), "/rectify.comp.spv")),
            Shader::Silhouette => {
                include_bytes!(concat!(env!("OUT_DIR"), "/silhouette.comp.spv"))
            }
            Shader::Holes => include_bytes!(concat!(env!("OUT_DIR"), "/holes.comp.spv")),
            Shader::RasterVertex => include_bytes!(concat!(env!("OUT_DIR"), "/raster.vert.spv")),
            Shader::RasterFragment => {
                include_bytes!(concat!(env!("OUT_DIR"), "/raster.frag.spv"))
            }
            Shader::RasterCutVertex => {
                include_bytes!(concat!(env!("OUT_DIR"), "/raster_cut.vert.spv"))
            }
            Shader::RasterCutFragment => {
                include_bytes!(concat!(env!("OUT_DIR"), "/raster_cut.frag.spv"))
            }
            Shader::RasterCutDepthFragment => {
                include_bytes!(concat!(env!("OUT_DIR"), "/raster_cut_depth.frag.spv"))
            }
            Shader::Clock => include_bytes!(concat!(env!("OUT_DIR"), "/clock.comp.spv")),
        }
    }

    /// The SPIR-V as 32-bit words (the embedded bytes need not be aligned).
    pub fn words(self) -> GpuResult<Vec<u32>> {
        ash::util::read_spv(&mut std::io::Cursor::new(self.spirv())).map_err(|err| {
            GpuError::Shader {
                name: self.name(),
                reason: format!("invalid SPIR-V: {err}"),
            }
        })
    }
}

/// A shader module, destroyed by its owner once the pipeline exists.
pub struct ShaderModule {
    pub raw: vk::ShaderModule,
}

impl ShaderModule {
    pub fn new(device: &ash::Device, shader: Shader) -> GpuResult<Self> {
        let words = shader.words()?;
        let info = vk::ShaderModuleCreateInfo::default().code(&words);
        // SAFETY: `words` is valid SPIR-V produced by glslc and outlives the call.
        let raw =
            unsafe { device.create_shader_module(&info, None) }.call("vkCreateShaderModule")?;
        Ok(Self { raw })
    }

    pub fn destroy(self, device: &ash::Device) {
        // SAFETY: the module is only referenced during pipeline creation, which is over.
        unsafe { device.destroy_shader_module(self.raw, None) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_shader_is_embedded_as_spirv() {
        for shader in Shader::ALL {
            let words = shader.words().unwrap();
            assert_eq!(
                words[0],
                0x0723_0203,
                "{} lacks the SPIR-V magic",
                shader.name()
            );
        }
    }

    #[test]
    fn every_source_in_the_shader_directory_has_a_variant() {
        let shaders = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shaders");
        for entry in std::fs::read_dir(shaders).unwrap() {
            let path = entry.unwrap().path();
            let name = path.file_name().unwrap().to_str().unwrap().to_owned();
            if ["comp", "vert", "frag"]
                .iter()
                .any(|ext| path.extension().is_some_and(|e| e == *ext))
            {
                assert!(
                    Shader::ALL.iter().any(|s| s.name() == name),
                    "{name} is compiled but not embedded"
                );
            }
        }
    }

    #[test]
    fn graphics_shaders_name_their_stage() {
        assert_eq!(Shader::RasterVertex.stage(), vk::ShaderStageFlags::VERTEX);
        assert_eq!(
            Shader::RasterFragment.stage(),
            vk::ShaderStageFlags::FRAGMENT
        );
        assert_eq!(Shader::March.stage(), vk::ShaderStageFlags::COMPUTE);
    }
}
