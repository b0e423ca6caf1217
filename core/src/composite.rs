//! Compositing the volume layer over a beauty render (premultiplied "over").

use crate::error::{Error, Result};

/// `volume` over `beauty`, both premultiplied interleaved RGBA:
/// `out.rgb = v.rgb + (1 − v.a)·b.rgb`, `out.a = v.a + (1 − v.a)·b.a`.
pub fn composite_over(volume_rgba: &[f32], beauty_rgba: &[f32]) -> Result<Vec<f32>> {
    // The beauty is what the caller brings to the volume render, so it is what's named.
    if beauty_rgba.len() != volume_rgba.len() || !volume_rgba.len().is_multiple_of(4) {
        return Err(Error::invalid(
            "beauty",
            format!(
                "has {} values and the volume {}; both must be the same whole number of RGBA pixels",
                beauty_rgba.len(),
                volume_rgba.len()
            ),
        ));
    }
    let mut out = Vec::with_capacity(volume_rgba.len());
    for (v, b) in volume_rgba.chunks_exact(4).zip(beauty_rgba.chunks_exact(4)) {
        let through = 1.0 - v[3];
        out.extend((0..4).map(|c| v[c] + through * b[c]));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn over_matches_hand_computed_values() {
        let volume = [0.2, 0.1, 0.0, 0.25, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 1.0];
        let beauty = [0.4, 0.8, 1.0, 1.0, 0.3, 0.6, 0.9, 0.5, 7.0, 7.0, 7.0, 1.0];
        let out = composite_over(&volume, &beauty).unwrap();
        // Pixel 0: 0.2 + 0.75·0.4 = 0.5, 0.1 + 0.75·0.8 = 0.7, 0 + 0.75·1 = 0.75, a = 1.
        // Pixel 1: empty volume leaves the beauty unchanged.
        // Pixel 2: opaque volume hides the beauty.
        let expected = [0.5, 0.7, 0.75, 1.0, 0.3, 0.6, 0.9, 0.5, 0.5, 0.5, 0.5, 1.0];
        for (o, e) in out.iter().zip(expected) {
            assert!((o - e).abs() < 1e-6, "{out:?} != {expected:?}");
        }
    }

    #[test]
    fn mismatched_lengths_name_beauty() {
        for (volume, beauty) in [(vec![0.0; 8], vec![0.0; 4]), (vec![0.0; 6], vec![0.0; 6])] {
            match composite_over(&volume, &beauty) {
                Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "beauty"),
                other => panic!("expected InvalidInput, got {other:?}"),
            }
        }
        assert_eq!(composite_over(&[], &[]).unwrap(), Vec::<f32>::new());
    }
}
