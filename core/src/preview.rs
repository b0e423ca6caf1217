//! Quick-look PNG previews of linear renders: exposure, a highlight shoulder, sRGB encoding.

use std::path::Path;

use crate::error::{Error, Result};

/// How linear scene values become display values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewTransform {
    /// Exposure in stops: values are multiplied by 2^exposure.
    pub exposure: f32,
    /// Roll highlights off smoothly instead of clipping them (see [`tone_map`]).
    pub tone_map: bool,
}

impl Default for ViewTransform {
    fn default() -> Self {
        Self {
            exposure: 0.0,
            tone_map: true,
        }
    }
}

/// Below this, the tone map is the identity; above, a Reinhard shoulder approaches 1.
const KNEE: f32 = 0.8;

/// Linear display value (after exposure) that [`auto_exposure`] puts the 99th-percentile
/// luminance at.
const AUTO_TARGET: f32 = 0.9;

/// [`auto_exposure`] stays within ±this many stops, so near-black noise is not blown up
/// to full brightness.
const AUTO_LIMIT: f32 = 24.0;

/// Writes an 8-bit sRGB RGB PNG of a premultiplied linear RGBA image (rows top to bottom).
/// The image is shown composited over black, i.e. alpha is ignored.
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    rgba_premultiplied: &[f32],
    view: &ViewTransform,
) -> Result<()> {
    let pixels = width as usize * height as usize;
    if width == 0 || height == 0 {
        return Err(Error::invalid(
            "size",
            format!("a PNG needs at least one pixel, got {width}x{height}"),
        ));
    }
    if rgba_premultiplied.len() != pixels * 4 {
        return Err(Error::invalid(
            "rgba",
            format!(
                "has {} values, expected {} (RGBA for {width}x{height})",
                rgba_premultiplied.len(),
                pixels * 4
            ),
        ));
    }
    let scale = view.exposure.exp2();
    let mut rgb8 = Vec::with_capacity(pixels * 3);
    for rgba in rgba_premultiplied.chunks_exact(4) {
        let mut rgb = [rgba[0], rgba[1], rgba[2]].map(|c| sanitize(sanitize(c) * scale));
        if view.tone_map {
            rgb = tone_map(rgb);
        }
        rgb8.extend(rgb.map(|c| (srgb_oetf(c.clamp(0.0, 1.0)) * 255.0).round() as u8));
    }

    let png_error = |error: png::EncodingError| match error {
        png::EncodingError::IoError(source) => Error::io(path, source),
        other => Error::Png {
            path: path.to_path_buf(),
            reason: other.to_string(),
        },
    };
    // Encode in memory so that every write error surfaces (a BufWriter drops them on drop).
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    let mut writer = encoder.write_header().map_err(png_error)?;
    writer.write_image_data(&rgb8).map_err(png_error)?;
    writer.finish().map_err(png_error)?;
    std::fs::write(path, &bytes).map_err(|source| Error::io(path, source))
}

/// NaN and negative values show as black, infinities as the largest finite value.
fn sanitize(c: f32) -> f32 {
    if c.is_nan() {
        0.0
    } else {
        c.clamp(0.0, f32::MAX)
    }
}

/// Highlight shoulder: identity up to `KNEE`, then `k + (1 − k)·t/(1 + t)` with
/// `t = (x − k)/(1 − k)`, which meets the identity with matching slope and approaches 1.
/// It is applied to the largest channel and the others scaled alike, so hue is kept and
/// no channel clips.
pub fn tone_map(rgb: [f32; 3]) -> [f32; 3] {
    let peak = rgb[0].max(rgb[1]).max(rgb[2]);
    if peak <= KNEE {
        return rgb;
    }
    let t = (peak - KNEE) / (1.0 - KNEE);
    // t/(1 + t) written so that t = ∞ gives 1, not NaN.
    let mapped = KNEE + (1.0 - KNEE) * (1.0 - 1.0 / (1.0 + t));
    rgb.map(|c| c * (mapped / peak))
}

/// The sRGB opto-electronic transfer function (IEC 61966-2-1), linear [0, 1] to encoded.
pub fn srgb_oetf(linear: f32) -> f32 {
    if linear <= 0.003_130_8 {
        12.92 * linear
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// Rec. 709 luminance of linear RGB.
fn luminance(rgba: &[f32]) -> f32 {
    0.2126 * rgba[0] + 0.7152 * rgba[1] + 0.0722 * rgba[2]
}

/// Exposure in stops that puts the 99th-percentile luminance of `rgba` (interleaved,
/// linear) at 0.9 — a quick look at very dim or very bright shafts. If fewer than 1 % of
/// the pixels are lit, the brightest pixel is used instead. Black images give 0.
pub fn auto_exposure(rgba: &[f32]) -> f32 {
    let mut lum: Vec<f32> = rgba
        .chunks_exact(4)
        .map(luminance)
        .filter(|l| l.is_finite())
        .map(|l| l.max(0.0))
        .collect();
    if lum.is_empty() {
        return 0.0;
    }
    let index = ((lum.len() - 1) as f64 * 0.99).round() as usize;
    let (_, &mut p99, brighter) = lum.select_nth_unstable_by(index, f32::total_cmp);
    let reference = if p99 > 0.0 {
        p99
    } else {
        brighter.iter().copied().fold(0.0, f32::max)
    };
    if reference <= 0.0 {
        return 0.0;
    }
    (AUTO_TARGET / reference)
        .log2()
        .clamp(-AUTO_LIMIT, AUTO_LIMIT)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_curve_matches_reference_values() {
        // Reference values from the IEC 61966-2-1 formula evaluated in f64.
        for (linear, encoded) in [
            (0.0, 0.0),
            (0.001, 0.012_92),
            (0.003_130_8, 0.040_45),
            (0.18, 0.461_356),
            (0.5, 0.735_357),
            (1.0, 1.0),
        ] {
            let got = srgb_oetf(linear);
            assert!((got - encoded).abs() < 2e-5, "oetf({linear}) = {got}");
        }
        // The two pieces meet at the breakpoint.
        let below = srgb_oetf(0.003_130_8);
        let above = srgb_oetf(0.003_130_9);
        assert!((above - below).abs() < 1e-5);
    }

    #[test]
    fn tone_map_is_identity_below_knee_and_bounded_above() {
        assert_eq!(tone_map([0.1, 0.5, 0.8]), [0.1, 0.5, 0.8]);
        let bright = tone_map([4.0, 2.0, 1.0]);
        assert!(bright[0] < 1.0 && bright[0] > KNEE);
        // Hue (channel ratios) is kept.
        assert!((bright[0] / bright[1] - 2.0).abs() < 1e-5);
        assert!((bright[1] / bright[2] - 2.0).abs() < 1e-5);
        let huge = tone_map([f32::MAX, 0.0, 0.0]);
        assert!(huge[0] <= 1.0 && huge[0] > 0.99);
        // Continuous at the knee.
        let just_above = tone_map([KNEE + 1e-4, 0.0, 0.0])[0];
        assert!((just_above - KNEE).abs() < 2e-4);
    }

    #[test]
    fn auto_exposure_targets_the_99th_percentile() {
        let mut rgba = Vec::new();
        for i in 0..100 {
            let l = if i == 99 {
                1000.0
            } else {
                0.1 + i as f32 * 0.001
            };
            rgba.extend_from_slice(&[l, l, l, 1.0]);
        }
        // Rank round(0.99·99) = 98 is 0.198: the single outlier at 1000 is ignored.
        let stops = auto_exposure(&rgba);
        assert!((0.198 * stops.exp2() - AUTO_TARGET).abs() < 1e-4, "{stops}");
        assert_eq!(auto_exposure(&[0.0; 40]), 0.0);
        assert_eq!(auto_exposure(&[]), 0.0);
        assert_eq!(auto_exposure(&[f32::NAN, 1.0, 1.0, 1.0]), 0.0);
        // Sparse lit pixels: the brightest is used.
        let mut sparse = vec![0.0; 4 * 1000];
        sparse[0..3].copy_from_slice(&[0.45, 0.45, 0.45]);
        assert!((auto_exposure(&sparse) - 1.0).abs() < 1e-5);
        assert_eq!(auto_exposure(&[1e-30, 1e-30, 1e-30, 1.0]), AUTO_LIMIT);
    }

    #[test]
    fn png_decodes_with_expected_pixels() {
        let path = std::env::temp_dir().join(format!(
            "crepuscular-preview-{}-decode.png",
            std::process::id()
        ));
        // 2x1: mid grey with alpha ignored, and a NaN/negative pixel that shows as black.
        let rgba = [0.18, 0.5, 1.0, 0.3, f32::NAN, -1.0, 0.0, 1.0];
        let view = ViewTransform {
            exposure: 0.0,
            tone_map: false,
        };
        write_png(&path, 2, 1, &rgba, &view).unwrap();
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_eq!((info.width, info.height), (2, 1));
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        // round(255·0.461356) = 118, round(255·0.735357) = 188.
        assert_eq!(&buf[..info.buffer_size()], &[118, 188, 255, 0, 0, 0]);
    }

    #[test]
    fn exposure_scales_before_encoding() {
        let path = std::env::temp_dir().join(format!(
            "crepuscular-preview-{}-exposure.png",
            std::process::id()
        ));
        let view = ViewTransform {
            exposure: 1.0,
            tone_map: false,
        };
        write_png(&path, 1, 1, &[0.25, 0.25, 0.25, 1.0], &view).unwrap();
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(&buf[..3], &[188, 188, 188]);
    }

    #[test]
    fn bad_sizes_are_rejected() {
        let path = Path::new("/nonexistent/never-written.png");
        let view = ViewTransform::default();
        assert!(matches!(
            write_png(path, 2, 2, &[0.0; 12], &view),
            Err(Error::InvalidInput { field, .. }) if field == "rgba"
        ));
        assert!(matches!(
            write_png(path, 0, 2, &[], &view),
            Err(Error::InvalidInput { field, .. }) if field == "size"
        ));
        assert!(matches!(
            write_png(path, 1, 1, &[0.0; 4], &view),
            Err(Error::Io { .. })
        ));
    }
}
