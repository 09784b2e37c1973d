//! The `texture` family: texture synthesis and sparse-coding denoising.
//!
//! - [`efros_leung`]: pixel-wise non-parametric synthesis (Efros & Leung 1999).
//! - [`quilting`]: image quilting with minimum-error boundary cuts (Efros & Freeman 2001).
//! - [`chaos_mosaic`]: tiling scrambled by blocks pasted along a cat map (Xu, Guo & Shum 2000).
//! - [`sparse_denoise`]: patch denoising by sparse coding over a DCT or K-SVD dictionary
//!   (Elad & Aharon 2006).
//!
//! The synthesis operators share [`Texture`] (interleaved f32 samples) and report
//! [`patch_match_rms`], the distance of the output's patches to their nearest source patches.

use ocellus_engine::op::{OpError, Outputs, PortSpec};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, PixelData, Value};
use rayon::prelude::*;

pub mod chaos_mosaic;
pub mod efros_leung;
pub mod quilting;
pub mod sparse_denoise;

/// Registers the `texture` operators.
pub fn register(
    registry: &mut ocellus_engine::op::Registry,
) -> Result<(), ocellus_engine::op::RegistryError> {
    registry.register::<efros_leung::EfrosLeung>()?;
    registry.register::<quilting::Quilting>()?;
    registry.register::<chaos_mosaic::ChaosMosaic>()?;
    registry.register::<sparse_denoise::SparseDenoise>()?;
    Ok(())
}

/// Largest output side of the synthesis operators, px.
pub const MAX_OUTPUT_PX: u32 = 4096;

/// An image as interleaved f32 samples (in the image's own units: 0..255 for u8).
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Samples per pixel.
    pub channels: usize,
    /// `width × height × channels` samples, row-major, interleaved.
    pub samples: Vec<f32>,
}

impl Texture {
    /// A zero texture.
    pub fn zeros(width: usize, height: usize, channels: usize) -> Texture {
        Texture {
            width,
            height,
            channels,
            samples: vec![0.0; width * height * channels],
        }
    }

    /// The samples of pixel (x, y).
    pub fn pixel(&self, x: usize, y: usize) -> &[f32] {
        let i = (y * self.width + x) * self.channels;
        &self.samples[i..i + self.channels]
    }

    /// The samples of pixel (x, y), mutable.
    pub fn pixel_mut(&mut self, x: usize, y: usize) -> &mut [f32] {
        let i = (y * self.width + x) * self.channels;
        &mut self.samples[i..i + self.channels]
    }

    /// Converts an image; an empty image or a NaN/infinite sample is an error naming `port`.
    pub fn from_image(image: &Image, port: &str) -> Result<Texture, OpError> {
        if image.is_empty() {
            return Err(OpError::input(port, "is empty"));
        }
        let samples: Vec<f32> = match image.data() {
            PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::U16(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::F32(v) => v.clone(),
        };
        if samples.iter().any(|s| !s.is_finite()) {
            return Err(OpError::input(port, "contains NaN or infinite samples"));
        }
        Ok(Texture {
            width: image.width(),
            height: image.height(),
            channels: image.channels().count(),
            samples,
        })
    }

    /// An image of `channels` and the depth of `like`, samples rounded and saturated for
    /// integer depths.
    pub fn to_image(&self, like: &Image) -> Result<Image, OpError> {
        let data = match like.data() {
            PixelData::U8(_) => PixelData::U8(
                self.samples
                    .iter()
                    .map(|&s| s.round().clamp(0.0, 255.0) as u8)
                    .collect(),
            ),
            PixelData::U16(_) => PixelData::U16(
                self.samples
                    .iter()
                    .map(|&s| s.round().clamp(0.0, 65535.0) as u16)
                    .collect(),
            ),
            PixelData::F32(_) => PixelData::F32(self.samples.clone()),
        };
        let channels: Channels = like.channels();
        Image::new(self.width, self.height, channels, data)
            .map_err(|e| OpError::failed(e.to_string()))
    }
}

/// Checks an output size param (1..=[`MAX_OUTPUT_PX`]).
pub(crate) fn check_output_side(name: &str, value: u32) -> Result<(), String> {
    if !(1..=MAX_OUTPUT_PX).contains(&value) {
        return Err(format!(
            "`{name}` must be between 1 and {MAX_OUTPUT_PX} px, got {value}"
        ));
    }
    Ok(())
}

/// Root-mean-square distance (image units) between the `patch_px × patch_px` patches of
/// `output` taken every `stride_px` pixels and their nearest patch (any position) of `source`:
/// √(mean over output patches of min over source patches of the per-sample mean squared
/// difference). Small values mean every output neighbourhood looks like some source
/// neighbourhood; 0 when the output is made of whole source patches. `None` when either image
/// is smaller than a patch. Output patches run in parallel, each search is sequential and the
/// sum is taken in patch order, so the value is the same for any thread count.
pub fn patch_match_rms(
    output: &Texture,
    source: &Texture,
    patch_px: usize,
    stride_px: usize,
) -> Option<f64> {
    let p = patch_px;
    if p == 0
        || stride_px == 0
        || output.channels != source.channels
        || output.width < p
        || output.height < p
        || source.width < p
        || source.height < p
    {
        return None;
    }
    let c = output.channels;
    let positions: Vec<(usize, usize)> = (0..=output.height - p)
        .step_by(stride_px)
        .flat_map(|y| {
            (0..=output.width - p)
                .step_by(stride_px)
                .map(move |x| (x, y))
        })
        .collect();
    let best: Vec<f64> = positions
        .par_iter()
        .map(|&(ox, oy)| {
            let mut best = f64::INFINITY;
            for sy in 0..=source.height - p {
                for sx in 0..=source.width - p {
                    let mut ssd = 0.0f64;
                    for dy in 0..p {
                        let a = &output.samples[((oy + dy) * output.width + ox) * c..][..p * c];
                        let b = &source.samples[((sy + dy) * source.width + sx) * c..][..p * c];
                        ssd += a
                            .iter()
                            .zip(b)
                            .map(|(x, y)| f64::from(x - y).powi(2))
                            .sum::<f64>();
                        if ssd >= best {
                            break;
                        }
                    }
                    best = best.min(ssd);
                }
            }
            best / (p * p * c) as f64
        })
        .collect();
    Some((best.iter().sum::<f64>() / best.len() as f64).sqrt())
}

/// Patch side of the `patch_match_rms` metric the synthesis operators report, px.
pub const MATCH_PATCH_PX: usize = 7;

/// Most output patches that metric compares (its stride grows on larger outputs).
pub const MAX_MATCH_PATCHES: usize = 1024;

/// [`patch_match_rms`] with [`MATCH_PATCH_PX`] patches on a grid of at most
/// [`MAX_MATCH_PATCHES`] output patches (stride ≥ the patch side).
pub fn synthesis_match_rms(output: &Texture, source: &Texture) -> Option<f64> {
    let p = MATCH_PATCH_PX;
    let mut stride = p;
    while (output.width.saturating_sub(p) / stride + 1)
        * (output.height.saturating_sub(p) / stride + 1)
        > MAX_MATCH_PATCHES
    {
        stride += 1;
    }
    patch_match_rms(output, source, p, stride)
}

/// The input port of the synthesizers: the source texture, at least `at_least` on each side.
pub(crate) fn source_port(at_least: &str) -> Vec<PortSpec> {
    vec![PortSpec::new(
        "source",
        PortType::Image,
        &format!("Source texture, any pixel format, at least {at_least} on each side."),
    )]
}

/// The output ports of the synthesizers: the texture and its `metrics` (named in `metrics`).
pub(crate) fn synthesis_ports(metrics: &str) -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "image",
            PortType::Image,
            "Synthesized texture, width × height, the source's format.",
        ),
        PortSpec::new(
            "metrics",
            PortType::Metrics,
            &format!("{metrics}, patch_match_rms."),
        ),
    ]
}

/// A synthesizer's outputs: `output` as an image of `source_image`'s format, and `metrics`
/// completed with `patch_match_rms` (the distance of the output's patches to `source`'s).
pub(crate) fn synthesis_outputs(
    output: &Texture,
    source: &Texture,
    source_image: &Image,
    mut metrics: Metrics,
) -> Result<Outputs, OpError> {
    if let Some(rms) = synthesis_match_rms(output, source) {
        metrics.insert("patch_match_rms".into(), rms);
    }
    Ok(Outputs::new()
        .with("image", Value::image(output.to_image(source_image)?))
        .with("metrics", Value::metrics(metrics)))
}

/// Mean and population variance of every channel, f64, summed in order.
pub fn channel_moments(texture: &Texture) -> Vec<(f64, f64)> {
    let c = texture.channels;
    let n = (texture.width * texture.height).max(1) as f64;
    (0..c)
        .map(|ch| {
            let values = texture.samples.iter().skip(ch).step_by(c);
            let mean = values.clone().map(|&v| f64::from(v)).sum::<f64>() / n;
            let var = values.map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
            (mean, var)
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod test_support {
    use super::Texture;
    use crate::video::filters::SplitMix64;

    /// A smooth random gray texture: uniform noise box-blurred twice (radius 2), 0..255,
    /// wrapping around (so it tiles).
    pub fn blobs(width: usize, height: usize, seed: u64) -> Texture {
        let mut rng = SplitMix64::new(seed);
        let mut t = Texture {
            width,
            height,
            channels: 1,
            samples: (0..width * height)
                .map(|_| (rng.uniform() * 255.0) as f32)
                .collect(),
        };
        for _ in 0..2 {
            let prev = t.samples.clone();
            for y in 0..height {
                for x in 0..width {
                    let mut s = 0.0;
                    for dy in 0..5 {
                        for dx in 0..5 {
                            let xx = (x + width + dx - 2) % width;
                            let yy = (y + height + dy - 2) % height;
                            s += prev[yy * width + xx];
                        }
                    }
                    t.samples[y * width + x] = s / 25.0;
                }
            }
        }
        // Stretch back to the full range.
        let (lo, hi) = t
            .samples
            .iter()
            .fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
        for s in &mut t.samples {
            *s = ((*s - lo) / (hi - lo) * 255.0).round();
        }
        t
    }

    /// A periodic texture: a random `period × period` gray tile repeated.
    pub fn periodic(width: usize, height: usize, period: usize, seed: u64) -> Texture {
        let mut rng = SplitMix64::new(seed);
        let tile: Vec<f32> = (0..period * period)
            .map(|_| (rng.uniform() * 255.0).floor() as f32)
            .collect();
        Texture {
            width,
            height,
            channels: 1,
            samples: (0..width * height)
                .map(|i| tile[(i / width % period) * period + i % width % period])
                .collect(),
        }
    }

    /// Independent uniform noise (a texture no smooth synthesis resembles patch-wise).
    pub fn noise(width: usize, height: usize, seed: u64) -> Texture {
        let mut rng = SplitMix64::new(seed);
        Texture {
            width,
            height,
            channels: 1,
            samples: (0..width * height)
                .map(|_| (rng.uniform() * 255.0).floor() as f32)
                .collect(),
        }
    }
}
