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
    let mut passes = Vec::with_capacity(distinct.len());
    let mut times = StageTimes::default();
    for &extinction in &distinct {
        let medium = grey(extinction);
        let pass = Frame {
            medium: &medium,
            style: &style,
            ..*frame
        };
        let (layers, pass_times) = render(&pass, control)?;
        times.accumulate(&pass_times);
        passes.push(layers);
    }
    let of_channel: [&Layers; 3] = std::array::from_fn(|c| {
        let pass = distinct.iter().position(|&value| value == values[c]);
        &passes[pass.unwrap_or(0)]
    });
    let mut layers = assemble(of_channel);
    apply_transfer_function_timed(frame, &mut layers, &mut times)?;
    Ok((layers, times))
}

/// The values, each once, in the order they first appear (bit for bit: -0 and 0 are one).
fn distinct_values(values: [f32; 3]) -> Vec<f32> {
    let mut distinct: Vec<f32> = Vec::with_capacity(3);
    for value in values {
        if !distinct.contains(&value) {
            distinct.push(value);
        }
    }
    distinct
}

/// Channel c's radiance from `of_channel[c]`, opacity and visibility blended by luminance
/// weights, depth from the red channel's pass (every pass has the same).
fn assemble(of_channel: [&Layers; 3]) -> Layers {
    let [red, green, blue] = of_channel;
    let mut layers = red.clone();
    layers
        .volume
        .par_chunks_mut(4)
        .zip(layers.visibility.par_iter_mut())
        .enumerate()
        .for_each(|(pixel, (rgba, visibility))| {
            let at = |layers: &Layers, channel: usize| layers.volume[4 * pixel + channel];
            rgba[1] = at(green, 1);
            rgba[2] = at(blue, 2);
            rgba[3] = luminance([at(red, 3), at(green, 3), at(blue, 3)]);
            *visibility = luminance([
                red.visibility[pixel],
                green.visibility[pixel],
                blue.visibility[pixel],
            ]);
        });
    layers
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
        };
        let (red, green, blue) = (
            layers(1.0, 0.2, 0.5),
            layers(2.0, 0.4, 0.25),
            layers(3.0, 0.6, 1.0),
        );
        let out = assemble([&red, &green, &blue]);
        assert_eq!(out.depth, vec![7.0, 8.0]);
        for pixel in 0..2 {
            assert_eq!(&out.volume[4 * pixel..4 * pixel + 3], &[1.0, 2.0, 3.0]);
            assert_eq!(out.volume[4 * pixel + 3], luminance([0.2, 0.4, 0.6]));
            assert_eq!(out.visibility[pixel], luminance([0.5, 0.25, 1.0]));
        }
    }
}
