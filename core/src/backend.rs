//! Which backend renders a frame: the CPU (always there, the oracle) or Vulkan, chosen
//! automatically or by request, with a fallback to the CPU on any Vulkan failure.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::gpu::{self, Device, DevicePolicy, GpuError};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Backend {
    /// A discrete or integrated GPU when there is one, otherwise the CPU. Software Vulkan
    /// implementations (lavapipe) are never chosen.
    #[default]
    Auto,
    Cpu,
    /// Vulkan on any device, software implementations included (the parity tests use
    /// lavapipe); the CPU when Vulkan cannot run, with a message.
    Vulkan,
}

impl Backend {
    pub const ALL: [Backend; 3] = [Backend::Auto, Backend::Cpu, Backend::Vulkan];

    pub fn name(self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Cpu => "cpu",
            Backend::Vulkan => "vulkan",
        }
    }

    pub fn is_auto(&self) -> bool {
        *self == Backend::Auto
    }
}

impl std::str::FromStr for Backend {
    type Err = Error;

    fn from_str(text: &str) -> Result<Self> {
        Backend::ALL
            .into_iter()
            .find(|b| b.name() == text)
            .ok_or_else(|| {
                let known: Vec<_> = Backend::ALL.iter().map(|b| b.name()).collect();
                Error::invalid(
                    "render.backend",
                    format!("unknown backend '{text}' (known: {})", known.join(", ")),
                )
            })
    }
}

/// The device policy a backend request uses, or `None` for the CPU.
pub fn device_policy(backend: Backend) -> Option<DevicePolicy> {
    match backend {
        Backend::Cpu => None,
        Backend::Auto => Some(DevicePolicy::HardwareOnly),
        Backend::Vulkan => Some(DevicePolicy::Any),
    }
}

/// The Vulkan device to render on, or `None` for the CPU. An explicit `vulkan` request
/// that cannot be met prints why on standard error; `auto` falls back silently, since
/// having no GPU is not a failure.
pub fn vulkan_device(backend: Backend) -> Option<Arc<Device>> {
    let policy = device_policy(backend)?;
    match gpu::shared_device(policy) {
        Ok(device) => Some(device),
        Err(err) => {
            if backend == Backend::Vulkan {
                report_fallback(&err);
            }
            None
        }
    }
}

/// The one message a Vulkan failure prints before the CPU takes over.
pub fn report_fallback(err: &GpuError) {
    eprintln!("crepuscular: Vulkan backend unavailable ({err}); rendering on the CPU instead");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for backend in Backend::ALL {
            assert_eq!(backend.name().parse::<Backend>().unwrap(), backend);
        }
        let err = "cuda".parse::<Backend>().unwrap_err().to_string();
        assert!(
            err.contains("render.backend") && err.contains("cuda"),
            "{err}"
        );
    }

    #[test]
    fn only_an_explicit_request_accepts_software_devices() {
        assert_eq!(device_policy(Backend::Cpu), None);
        assert_eq!(
            device_policy(Backend::Auto),
            Some(DevicePolicy::HardwareOnly)
        );
        assert_eq!(device_policy(Backend::Vulkan), Some(DevicePolicy::Any));
    }
}
