//! Compiles the GLSL shaders in the top-level `shaders/` directory (compute `.comp`, vertex
//! `.vert` and fragment `.frag`) to SPIR-V with `glslc`, into OUT_DIR as `<file name>.spv`
//! (`march.comp.spv`), where the Vulkan backend embeds them.

use std::path::{Path, PathBuf};
use std::process::Command;

/// File extensions of shader sources; glslc takes the stage from them.
const SHADER_STAGES: [&str; 3] = ["comp", "vert", "frag"];

fn main() {
    let manifest = PathBuf::from(
        std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"),
    );
    let shaders = manifest.join("..").join("shaders");
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    println!("cargo:rerun-if-changed={}", shaders.display());
    println!("cargo:rerun-if-env-changed=GLSLC");
    let compiler = std::env::var_os("GLSLC").unwrap_or_else(|| "glslc".into());
    let mut sources: Vec<PathBuf> = std::fs::read_dir(&shaders)
        .unwrap_or_else(|err| {
            panic!(
                "cannot read the shader directory {}: {err}",
                shaders.display()
            )
        })
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| {
            path.extension()
                .is_some_and(|ext| SHADER_STAGES.iter().any(|stage| ext == *stage))
        })
        .collect();
    sources.sort();
    for source in &sources {
        println!("cargo:rerun-if-changed={}", source.display());
        compile(&compiler, source, &out);
    }
    for include in std::fs::read_dir(&shaders).into_iter().flatten().flatten() {
        let path = include.path();
        if path.extension().is_some_and(|ext| ext == "glsl") {
            println!("cargo:rerun-if-changed={}", path.display());
        }
    }
}

fn compile(compiler: &std::ffi::OsStr, source: &Path, out: &Path) {
    let file_name = source
        .file_name()
        .and_then(|s| s.to_str())
        .unwrap_or("shader");
    let target = out.join(format!("{file_name}.spv"));
    let result = Command::new(compiler)
        .args(["--target-env=vulkan1.1", "-O", "-Werror", "-o"])
        .arg(&target)
        .arg(source)
        .output();
    match result {
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => panic!(
            "\n\nThe GLSL compiler `glslc` was not found; it compiles the Vulkan backend's \
             shaders. Install it with the Debian package `glslc` (apt-get install glslc), or \
             set GLSLC to its path.\n"
        ),
        Err(err) => panic!("cannot run glslc on {}: {err}", source.display()),
        Ok(output) if !output.status.success() => panic!(
            "glslc failed on {}:\n{}",
            source.display(),
            String::from_utf8_lossy(&output.stderr)
        ),
        Ok(_) => {}
    }
}
