//! Coloured extinction. Cycles scales a Volume Scatter's σt by its colour, so each channel of
//! the in-scattered light decays at its own rate, along the view ray and, in a box, along the
//! sunlight's way in. Every method integrates one σt, so a frame whose channels differ is
//! scattered once per distinct coefficient, and each channel of the radiance is taken from
//! its own pass: exact for every method, at up to three times the cost. The scalar layers
//! (opacity and visibility) blend the channels' by their Rec. 709 luminance weights, and the
//! transfer function runs once, on the assembled layers.

use rayon::prelude::*;

use crate::control::RenderControl;
use crate::error::Result;
use crate::layers::Layers;
use crate::render::{apply_transfer_function_timed, Frame, StageTimes};
use crate::scene::Medium;
use crate::style::Style;
use crate::transfer_function::luminance;

/// `render` of `frame`, once per distinct extinction of its medium's channels where it has
/// `channel_extinction`, with the layers assembled channel by channel; else `render` of the
/// frame itself. `render` gets grey media only, and no transfer function where there are
/// several passes (it is applied here, once).
pub fn by_channel(
    frame: &Frame,
    control: &RenderControl,
    render: impl Fn(&Frame, &RenderControl) -> Result<(Layers, StageTimes)>,
) -> Result<(Layers, StageTimes)> {
    let Some(channels) = frame.medium.channel_extinction else {
        return render(frame, control);
    };
    frame.medium.validate()?;
    let values = channels.to_array();
    let distinct = distinct_values(values);
    let grey = |extinction: f32| Medium {
        extinction,
        channel_extinction: None,
        ..frame.medium.clone()
    };
    if let [only] = distinct[..] {
        let medium = grey(only);
        return render(
            &Frame {
                medium: &medium,
                ..*frame
            },
            control,
        );
    }
    let style = Style {
        tf: None,
        ..frame.style.clone()
    };
    let render_pass = |extinction: f32| {
        let medium = grey(extinction);
        let pass = Frame {
            medium: &medium,
            style: &style,
            ..*frame
        };
        render(&pass, control)
    };
    let channels_of = |extinction: f32| values.map(|value| value == extinction);
    // `distinct` starts with the red channel's value.
    let (first, mut times) = render_pass(values[0])?;
    let mut layers = first_pass(first, channels_of(values[0]));
    for &extinction in &distinct[1..] {
        let (pass, pass_times) = render_pass(extinction)?;
        times.accumulate(&pass_times);
        add_pass(&mut layers, &pass, channels_of(extinction));
    }
    apply_transfer_function_timed(frame, &mut layers, &mut times)?;
    Ok((layers, times))
}

/// The values, each once, in the order they first appear (compared as numbers: -0 and 0
/// are one).
fn distinct_values(values: [f32; 3]) -> Vec<f32> {
    let mut distinct: Vec<f32> = Vec::with_capacity(3);
    for value in values {
        if !distinct.contains(&value) {
            distinct.push(value);
        }
    }
    distinct
}

/// The luminance weight of the `channels` a pass gives.
fn share(channels: [bool; 3]) -> f32 {
    luminance(channels.map(f32::from))
}

/// The assembly's start from the first pass, which gives `channels`: its layers, opacity
/// and visibility weighted by the share of its channels. The other channels' radiance is
/// overwritten by the passes that give them; the depth is every pass's.
fn first_pass(mut layers: Layers, channels: [bool; 3]) -> Layers {
    let weight = share(channels);
    layers
        .volume
        .par_chunks_mut(4)
        .zip(layers.visibility.par_iter_mut())
        .for_each(|(rgba, visibility)| {
            rgba[3] *= weight;
            *visibility *= weight;
        });
    layers
}

/// A later pass into the assembly: the radiance of its `channels`, and its share of the
/// opacity and visibility. One pass at a time, so that a frame holds two sets of layers
/// however many passes it takes.
fn add_pass(out: &mut Layers, pass: &Layers, channels: [bool; 3]) {
    let weight = share(channels);
    out.volume
        .par_chunks_mut(4)
        .zip(out.visibility.par_iter_mut())
        .zip(pass.volume.par_chunks(4).zip(pass.visibility.par_iter()))
        .for_each(|((rgba, visibility), (from, from_visibility))| {
            for (channel, &given) in channels.iter().enumerate() {
                if given {
                    rgba[channel] = from[channel];
                }
            }
            rgba[3] += weight * from[3];
            *visibility += weight * from_visibility;
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distinct_values_keep_their_first_order() {
        assert_eq!(distinct_values([0.3, 0.1, 0.3]), vec![0.3, 0.1]);
        assert_eq!(distinct_values([0.2, 0.2, 0.2]), vec![0.2]);
        assert_eq!(distinct_values([0.0, -0.0, 1.0]), vec![0.0, 1.0]);
    }

    #[test]
    fn assembly_takes_each_channel_from_its_pass_and_blends_the_scalars() {
        let layers = |value: f32, alpha: f32, visibility: f32| Layers {
            width: 2,
            height: 1,
            volume: vec![value, value, value, alpha, value, value, value, alpha],
            visibility: vec![visibility; 2],
            depth: vec![7.0, 8.0],
            pixel_aspect: 1.0,
        };
        let (red, green, blue) = (
            layers(1.0, 0.2, 0.5),
            layers(2.0, 0.4, 0.25),
            layers(3.0, 0.6, 1.0),
        );
        let mut out = first_pass(red, [true, false, false]);
        add_pass(&mut out, &green, [false, true, false]);
        add_pass(&mut out, &blue, [false, false, true]);
        assert_eq!(out.depth, vec![7.0, 8.0]);
        for pixel in 0..2 {
            assert_eq!(&out.volume[4 * pixel..4 * pixel + 3], &[1.0, 2.0, 3.0]);
            // Three passes add up as the luminance does, in the same order.
            assert_eq!(out.volume[4 * pixel + 3], luminance([0.2, 0.4, 0.6]));
            assert_eq!(out.visibility[pixel], luminance([0.5, 0.25, 1.0]));
        }
        // Two passes: one gives red and blue.
        let mut out = first_pass(layers(1.0, 0.2, 0.5), [true, false, true]);
        add_pass(&mut out, &layers(2.0, 0.4, 0.25), [false, true, false]);
        assert_eq!(&out.volume[0..3], &[1.0, 2.0, 1.0]);
        let expected = luminance([0.2, 0.4, 0.2]);
        assert!(
            (out.volume[3] - expected).abs() <= 1e-7,
            "{}",
            out.volume[3]
        );
    }
}
