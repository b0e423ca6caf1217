//! SPIR-V compiled from `shaders/` at build time, embedded in the binary, and turned into
//! shader modules.

use ash::vk;

use super::error::{GpuError, GpuResult, VkContext};

/// The compute shaders, by name (their file stem in `shaders/`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Shader {
    March,
    Morphology,
    Transfer,
    Prefix,
    Prefiltered,
    Upsample,
    Rectify,
}

impl Shader {
    pub fn name(self) -> &'static str {
        match self {
            Shader::March => "march",
            Shader::Morphology => "morphology",
            Shader::Transfer => "transfer",
            Shader::Prefix => "prefix",
            Shader::Prefiltered => "prefiltered",
            Shader::Upsample => "upsample",
            Shader::Rectify => "rectify",
        }
    }

    pub fn spirv(self) -> &'static [u8] {
        match self {
            Shader::March => include_bytes!(concat!(env!("OUT_DIR"), "/march.spv")),
            Shader::Morphology => include_bytes!(concat!(env!("OUT_DIR"), "/morphology.spv")),
            Shader::Transfer => include_bytes!(concat!(env!("OUT_DIR"), "/transfer.spv")),
            Shader::Prefix => include_bytes!(concat!(env!("OUT_DIR"), "/prefix.spv")),
            Shader::Prefiltered => include_bytes!(concat!(env!("OUT_DIR"), "/prefiltered.spv")),
            Shader::Upsample => include_bytes!(concat!(env!("OUT_DIR"), "/upsample.spv")),
            Shader::Rectify => include_bytes!(concat!(env!("OUT_DIR"), "/rectify.spv")),
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
        for shader in [
            Shader::March,
            Shader::Morphology,
            Shader::Transfer,
            Shader::Prefix,
            Shader::Prefiltered,
            Shader::Upsample,
            Shader::Rectify,
        ] {
            let words = shader.words().unwrap();
            assert_eq!(
                words[0],
                0x0723_0203,
                "{} lacks the SPIR-V magic",
                shader.name()
            );
        }
    }
}
