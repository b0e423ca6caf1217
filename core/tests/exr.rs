//! EXR I/O against files on disk: exact round trips, corrupt input, and a real Blender 5
//! multi-part render (`data/blender5_multipart.exr`, made by `data/make_blender_multipart.py`).

use std::path::{Path, PathBuf};

use crepuscular::exr_file::{read_exr, write_channels, write_layers, ExrCompression, Precision};
use crepuscular::{Error, Layers};

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("crepuscular-it-{}-{name}", std::process::id()))
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// Awkward values for f32: subnormals, extremes, negative zero, non-round fractions.
fn awkward_layers() -> Layers {
    let (width, height) = (7, 5);
    let mut layers = Layers::new(width, height);
    let specials = [
        0.1,
        -0.0,
        f32::MIN_POSITIVE / 3.0,
        f32::MAX,
        -1.0e-7,
        std::f32::consts::PI,
        1.0e10,
        f32::INFINITY,
    ];
    for (i, v) in layers.volume.iter_mut().enumerate() {
        *v = specials[i % specials.len()] * (1.0 + i as f32 * 1.0e-3);
    }
    for (i, v) in layers.visibility.iter_mut().enumerate() {
        *v = i as f32 / 34.0;
    }
    for (i, v) in layers.depth.iter_mut().enumerate() {
        *v = 0.37 + i as f32 * 11.3;
    }
    layers
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

#[test]
fn f32_round_trip_is_bit_identical() {
    let path = temp_path("f32.exr");
    let layers = awkward_layers();
    write_layers(&path, &layers, Precision::F32, ExrCompression::Zip).unwrap();
    let image = read_exr(&path).unwrap();
    std::fs::remove_file(&path).unwrap();

    assert_eq!((image.width, image.height), (7, 5));
    let names: Vec<_> = image.channels.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        [
            "depth",
            "visibility",
            "volume.A",
            "volume.B",
            "volume.G",
            "volume.R"
        ]
    );
    let back = image.to_layers().unwrap();
    assert_eq!(bits(&back.volume), bits(&layers.volume));
    assert_eq!(bits(&back.visibility), bits(&layers.visibility));
    assert_eq!(bits(&back.depth), bits(&layers.depth));
    // Row 0 is the top of the image: pixel (x, y) sits at y·width + x in both.
    assert_eq!(
        back.volume_rgba(3, 4).map(f32::to_bits),
        layers.volume_rgba(3, 4).map(f32::to_bits)
    );
}

#[test]
fn f16_round_trip_is_exact_where_representable() {
    let path = temp_path("f16.exr");
    let mut layers = Layers::new(4, 3);
    // Exactly representable in f16: small dyadic fractions, integers up to 2048, 65504.
    let exact = [
        0.0,
        0.5,
        0.25,
        1.0,
        2048.0,
        65504.0,
        -3.75,
        0.000_061_035_156,
    ];
    for (i, v) in layers.volume.iter_mut().enumerate() {
        *v = exact[i % exact.len()];
    }
    // Not representable: must come back within half precision (2^-11 relative).
    let inexact: Vec<f32> = (0..12).map(|i| 0.1 + i as f32 * 0.0137).collect();
    layers.visibility = inexact.clone();
    layers.depth = (0..12).map(|i| 1.0e6 + i as f32 * 0.1).collect();
    write_layers(&path, &layers, Precision::F16, ExrCompression::Zip).unwrap();
    let back = read_exr(&path).unwrap().to_layers().unwrap();
    std::fs::remove_file(&path).unwrap();

    assert_eq!(bits(&back.volume), bits(&layers.volume));
    for (b, v) in back.visibility.iter().zip(&inexact) {
        assert!((b - v).abs() <= v.abs() * 2f32.powi(-11), "{b} vs {v}");
    }
    // Depth stays f32 even in half files.
    assert_eq!(bits(&back.depth), bits(&layers.depth));
}

#[test]
fn generic_channels_write_rgba() {
    let path = temp_path("rgba.exr");
    let r = [1.0, 0.0];
    let g = [0.0, 0.5];
    let b = [0.25, 0.0];
    let a = [1.0, 0.5];
    let channels: [(&str, &[f32]); 4] = [("R", &r), ("G", &g), ("B", &b), ("A", &a)];
    write_channels(
        &path,
        1,
        2,
        &channels,
        Precision::F16,
        ExrCompression::Zip,
        1.0,
    )
    .unwrap();
    let image = read_exr(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!((image.width, image.height), (1, 2));
    assert_eq!(
        image.beauty_rgba().unwrap(),
        [1.0, 0.0, 0.25, 1.0, 0.0, 0.5, 0.0, 0.5]
    );
}

fn assert_exr_error_naming(path: &Path) {
    match read_exr(path) {
        Err(error @ Error::Exr { .. }) => {
            let Error::Exr { path: named, .. } = &error else {
                unreachable!()
            };
            assert_eq!(named, path);
            assert!(error.to_string().contains(&*path.to_string_lossy()));
        }
        other => panic!("expected Error::Exr for {}, got {other:?}", path.display()),
    }
}

#[test]
fn truncated_files_are_errors_not_panics() {
    let path = temp_path("whole.exr");
    write_layers(
        &path,
        &awkward_layers(),
        Precision::F32,
        ExrCompression::Zip,
    )
    .unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::remove_file(&path).unwrap();

    for (name, len) in [
        ("half.exr", bytes.len() / 2),
        ("ten.exr", 10),
        ("empty.exr", 0),
    ] {
        let cut = temp_path(name);
        std::fs::write(&cut, &bytes[..len]).unwrap();
        assert_exr_error_naming(&cut);
        std::fs::remove_file(&cut).unwrap();
    }
}

#[test]
fn corrupted_bytes_are_errors_not_panics() {
    let path = temp_path("corrupt-src.exr");
    write_layers(
        &path,
        &awkward_layers(),
        Precision::F16,
        ExrCompression::Zip,
    )
    .unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::remove_file(&path).unwrap();

    let cut = temp_path("corrupt.exr");
    // Deterministic corruption sweep: overwrite one byte at a time in the header, the
    // offset table and the compressed data. Any result but a panic or abort is fine; a
    // decoded image must still be consistently sized.
    let mut state = 0x2545_f491_u32;
    for step in 0..bytes.len().min(400) {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        let mut broken = bytes.clone();
        let at = if step < 200 {
            step
        } else {
            state as usize % bytes.len()
        };
        broken[at] = broken[at].wrapping_add(1 + (state >> 24) as u8 % 255);
        std::fs::write(&cut, &broken).unwrap();
        if let Ok(image) = read_exr(&cut) {
            let pixels = image.width as usize * image.height as usize;
            assert!(image.channels.values().all(|plane| plane.len() == pixels));
        }
    }
    std::fs::remove_file(&cut).unwrap();
}

#[test]
fn non_exr_and_missing_files_are_errors() {
    let path = temp_path("not.exr");
    std::fs::write(
        &path,
        b"P3\n1 1\n255\n0 0 0\nthis is not an EXR file at all",
    )
    .unwrap();
    assert_exr_error_naming(&path);
    std::fs::remove_file(&path).unwrap();

    let missing = temp_path("missing.exr");
    assert!(matches!(read_exr(&missing), Err(Error::Io { path, .. }) if path == missing));
}

#[test]
fn blender5_multipart_render_reads() {
    let image = read_exr(&fixture("blender5_multipart.exr")).unwrap();
    assert_eq!((image.width, image.height), (8, 6));

    // Blender 5.0 writes one part per pass, named `<view layer>.<pass>`, with the full
    // `<view layer>.<pass>.<channel>` names inside each part.
    let names: Vec<_> = image.channels.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        [
            "ViewLayer.Combined.A",
            "ViewLayer.Combined.B",
            "ViewLayer.Combined.G",
            "ViewLayer.Combined.R",
            "ViewLayer.Depth.Z",
        ]
    );

    let beauty = image.beauty_rgba().unwrap();
    assert_eq!(beauty.len(), 8 * 6 * 4);
    let alpha = |x: usize, y: usize| beauty[(y * 8 + x) * 4 + 3];
    let depth = image.depth().unwrap();
    assert_eq!(depth, image.channel("ViewLayer.Depth.Z").unwrap());
    let at = |x: usize, y: usize| depth[y * 8 + x];

    // The cube fills the top left: its front face is 3.5 units from the camera, and
    // Blender's Z is planar depth, so it is 3.5 across the face.
    for (x, y) in [(1, 1), (2, 1), (1, 2)] {
        assert_eq!(at(x, y), 3.5, "depth({x},{y})");
        assert_eq!(alpha(x, y), 1.0, "cube alpha at ({x},{y})");
        assert!(beauty[(y * 8 + x) * 4] > 0.1, "lit cube at ({x},{y})");
    }
    // The bottom right sees the empty world (transparent film): Blender writes 1e10 there.
    for y in 3..6 {
        for x in 4..8 {
            assert!(at(x, y) >= 1.0e9, "depth({x},{y}) = {}", at(x, y));
            assert_eq!(alpha(x, y), 0.0, "background alpha at ({x},{y})");
        }
    }
    // Rows are not flipped: bottom left is background, top right is background.
    assert!(at(0, 5) >= 1.0e9 && at(7, 0) >= 1.0e9);
}
