//! `sensor.demosaic`: Bayer mosaic → RGB by bilinear interpolation, the gradient-corrected
//! linear filters of Malvar, He & Cutler (2004), or the edge-directed interpolation of
//! Hamilton & Adams (1997).
//!
//! The algorithm is [`demosaic`]; [`Demosaic`] is the thin operator. Borders are handled by
//! mirroring without repeating the edge sample, which keeps the Bayer phase, so border pixels
//! are interpolated with the same filters as interior ones. Rows are computed independently in
//! parallel: the output does not depend on the thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, PixelData, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::{BLUE, BayerPattern, GREEN, RED, mirror};

/// Mirrored border around the mosaic: the widest filter (5×5) reaches 2 px.
const PAD: usize = 2;

param_enum! {
    /// Demosaicing method.
    pub enum DemosaicMethod {
        /// Bilinear interpolation of each colour plane from its nearest samples.
        Bilinear = "bilinear",
        /// Malvar–He–Cutler gradient-corrected bilinear (5×5 linear filters).
        Malvar = "malvar",
        /// Hamilton–Adams: green interpolated along the smoother direction with a Laplacian
        /// correction, red and blue from colour differences.
        HamiltonAdams = "hamilton_adams",
    }
}

param_enum! {
    /// Sample type of the output.
    pub enum DemosaicDepth {
        /// f32, in the mosaic's units (digital numbers stay digital numbers).
        F32 = "f32",
        /// u16, rounded and clamped to 0..65535.
        U16 = "u16",
    }
}

params! {
    /// Parameters of `sensor.demosaic`.
    pub struct DemosaicParams {
        /// "bilinear", "malvar" or "hamilton_adams".
        method: DemosaicMethod = DemosaicMethod::Malvar,
        /// Bayer layout of the mosaic: "rggb", "bggr", "grbg" or "gbrg".
        pattern: BayerPattern = BayerPattern::Rggb,
        /// Output sample type: "f32" or "u16".
        depth: DemosaicDepth = DemosaicDepth::F32,
    }
}

/// One filter tap: offset (dx, dy) and weight.
type Tap = (isize, isize, f32);

/// The four interpolation cases of a Bayer mosaic.
struct Filters {
    /// Green at a red or blue pixel.
    green_at_chroma: &'static [Tap],
    /// Red or blue at a green pixel whose row holds that colour (horizontal neighbours).
    chroma_in_row: &'static [Tap],
    /// Red or blue at a green pixel whose column holds that colour.
    chroma_in_column: &'static [Tap],
    /// Red at blue or blue at red (diagonal neighbours).
    chroma_at_chroma: &'static [Tap],
}

/// Bilinear interpolation.
const BILINEAR: Filters = Filters {
    green_at_chroma: &[(-1, 0, 0.25), (1, 0, 0.25), (0, -1, 0.25), (0, 1, 0.25)],
    chroma_in_row: &[(-1, 0, 0.5), (1, 0, 0.5)],
    chroma_in_column: &[(0, -1, 0.5), (0, 1, 0.5)],
    chroma_at_chroma: &[(-1, -1, 0.25), (1, -1, 0.25), (-1, 1, 0.25), (1, 1, 0.25)],
};

/// Malvar, He & Cutler (2004), Fig. 2: the filter coefficients over 8.
const MALVAR: Filters = Filters {
    green_at_chroma: &[
        (0, 0, 4.0 / 8.0),
        (-1, 0, 2.0 / 8.0),
        (1, 0, 2.0 / 8.0),
        (0, -1, 2.0 / 8.0),
        (0, 1, 2.0 / 8.0),
        (-2, 0, -1.0 / 8.0),
        (2, 0, -1.0 / 8.0),
        (0, -2, -1.0 / 8.0),
        (0, 2, -1.0 / 8.0),
    ],
    chroma_in_row: &[
        (0, 0, 5.0 / 8.0),
        (-1, 0, 4.0 / 8.0),
        (1, 0, 4.0 / 8.0),
        (-2, 0, -1.0 / 8.0),
        (2, 0, -1.0 / 8.0),
        (-1, -1, -1.0 / 8.0),
        (1, -1, -1.0 / 8.0),
        (-1, 1, -1.0 / 8.0),
        (1, 1, -1.0 / 8.0),
        (0, -2, 0.5 / 8.0),
        (0, 2, 0.5 / 8.0),
    ],
    chroma_in_column: &[
        (0, 0, 5.0 / 8.0),
        (0, -1, 4.0 / 8.0),
        (0, 1, 4.0 / 8.0),
        (0, -2, -1.0 / 8.0),
        (0, 2, -1.0 / 8.0),
        (-1, -1, -1.0 / 8.0),
        (1, -1, -1.0 / 8.0),
        (-1, 1, -1.0 / 8.0),
        (1, 1, -1.0 / 8.0),
        (-2, 0, 0.5 / 8.0),
        (2, 0, 0.5 / 8.0),
    ],
    chroma_at_chroma: &[
        (0, 0, 6.0 / 8.0),
        (-1, -1, 2.0 / 8.0),
        (1, -1, 2.0 / 8.0),
        (-1, 1, 2.0 / 8.0),
        (1, 1, 2.0 / 8.0),
        (-2, 0, -1.5 / 8.0),
        (2, 0, -1.5 / 8.0),
        (0, -2, -1.5 / 8.0),
        (0, 2, -1.5 / 8.0),
    ],
};

/// A plane with a mirrored border of [`PAD`] px, indexed by unpadded coordinates.
struct Padded {
    data: Vec<f32>,
    stride: usize,
}

impl Padded {
    fn new(plane: &[f32], width: usize, height: usize) -> Padded {
        let stride = width + 2 * PAD;
        let mut data = vec![0.0f32; stride * (height + 2 * PAD)];
        data.par_chunks_mut(stride)
            .enumerate()
            .for_each(|(py, row)| {
                let y = mirror(py as isize - PAD as isize, height);
                for (px, o) in row.iter_mut().enumerate() {
                    *o = plane[y * width + mirror(px as isize - PAD as isize, width)];
                }
            });
        Padded { data, stride }
    }

    /// The sample at (x + dx, y + dy), |dx|, |dy| ≤ [`PAD`].
    #[inline]
    fn at(&self, x: usize, y: usize, dx: isize, dy: isize) -> f32 {
        let px = (x + PAD).wrapping_add_signed(dx);
        let py = (y + PAD).wrapping_add_signed(dy);
        self.data[py * self.stride + px]
    }

    #[inline]
    fn apply(&self, x: usize, y: usize, taps: &[Tap]) -> f32 {
        taps.iter()
            .map(|&(dx, dy, w)| w * self.at(x, y, dx, dy))
            .sum()
    }
}

/// Demosaics the `width` × `height` Bayer `mosaic` (row-major, one sample per pixel) laid out
/// as `pattern`: interleaved RGB f32, `width · height · 3` samples. Every pixel keeps its own
/// sample in its own channel. Sizes must be ≥ 1 (a 1-px side is mirrored onto itself).
pub fn demosaic(
    mosaic: &[f32],
    width: usize,
    height: usize,
    pattern: BayerPattern,
    method: DemosaicMethod,
) -> Vec<f32> {
    let padded = Padded::new(mosaic, width, height);
    match method {
        DemosaicMethod::Bilinear => linear(&padded, width, height, pattern, &BILINEAR),
        DemosaicMethod::Malvar => linear(&padded, width, height, pattern, &MALVAR),
        DemosaicMethod::HamiltonAdams => hamilton_adams(&padded, width, height, pattern),
    }
}

/// Which filter interpolates channel `target` at (x, y), or `None` where (x, y) samples it.
fn case(
    filters: &Filters,
    pattern: BayerPattern,
    x: usize,
    y: usize,
    target: usize,
) -> Option<&[Tap]> {
    let own = pattern.color_at(x, y);
    if own == target {
        None
    } else if target == GREEN {
        Some(filters.green_at_chroma)
    } else if own == GREEN {
        if pattern.color_at(x + 1, y) == target {
            Some(filters.chroma_in_row)
        } else {
            Some(filters.chroma_in_column)
        }
    } else {
        Some(filters.chroma_at_chroma)
    }
}

/// Demosaicing with linear filters (bilinear or Malvar–He–Cutler).
fn linear(
    padded: &Padded,
    width: usize,
    height: usize,
    pattern: BayerPattern,
    filters: &Filters,
) -> Vec<f32> {
    let mut out = vec![0.0f32; width * height * 3];
    out.par_chunks_mut(width * 3)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(3).enumerate() {
                for (target, o) in px.iter_mut().enumerate() {
                    *o = match case(filters, pattern, x, y, target) {
                        None => padded.at(x, y, 0, 0),
                        Some(taps) => padded.apply(x, y, taps),
                    };
                }
            }
        });
    out
}

/// Hamilton & Adams (US patent 5,629,734, 1997): green at red/blue pixels along the direction
/// of the smaller gradient |ΔG| + |Δ²C|, with the second difference of the pixel's own colour
/// as a correction; red and blue from the colour differences C − G of their neighbours
/// (horizontal or vertical at green pixels, the smoother diagonal at the opposite colour).
fn hamilton_adams(padded: &Padded, width: usize, height: usize, pattern: BayerPattern) -> Vec<f32> {
    let mut green = vec![0.0f32; width * height];
    green
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, g) in row.iter_mut().enumerate() {
                let c = padded.at(x, y, 0, 0);
                if pattern.color_at(x, y) == GREEN {
                    *g = c;
                    continue;
                }
                let p = |dx, dy| padded.at(x, y, dx, dy);
                let laplace_h = 2.0 * c - p(-2, 0) - p(2, 0);
                let laplace_v = 2.0 * c - p(0, -2) - p(0, 2);
                let grad_h = (p(-1, 0) - p(1, 0)).abs() + laplace_h.abs();
                let grad_v = (p(0, -1) - p(0, 1)).abs() + laplace_v.abs();
                let along_h = 0.5 * (p(-1, 0) + p(1, 0)) + 0.25 * laplace_h;
                let along_v = 0.5 * (p(0, -1) + p(0, 1)) + 0.25 * laplace_v;
                *g = if grad_h < grad_v {
                    along_h
                } else if grad_v < grad_h {
                    along_v
                } else {
                    0.5 * (along_h + along_v)
                };
            }
        });
    let green = Padded::new(&green, width, height);
    let mut out = vec![0.0f32; width * height * 3];
    out.par_chunks_mut(width * 3)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(3).enumerate() {
                let own = pattern.color_at(x, y);
                let g = green.at(x, y, 0, 0);
                // Colour difference C − G at an offset.
                let diff = |dx, dy| padded.at(x, y, dx, dy) - green.at(x, y, dx, dy);
                for target in [RED, BLUE] {
                    px[target] = if own == target {
                        padded.at(x, y, 0, 0)
                    } else if own == GREEN {
                        if pattern.color_at(x + 1, y) == target {
                            g + 0.5 * (diff(-1, 0) + diff(1, 0))
                        } else {
                            g + 0.5 * (diff(0, -1) + diff(0, 1))
                        }
                    } else {
                        // The diagonal with the smaller gradient of the target colour and of green.
                        let grad_main = (padded.at(x, y, -1, -1) - padded.at(x, y, 1, 1)).abs()
                            + (2.0 * g - green.at(x, y, -1, -1) - green.at(x, y, 1, 1)).abs();
                        let grad_anti = (padded.at(x, y, 1, -1) - padded.at(x, y, -1, 1)).abs()
                            + (2.0 * g - green.at(x, y, 1, -1) - green.at(x, y, -1, 1)).abs();
                        let main = 0.5 * (diff(-1, -1) + diff(1, 1));
                        let anti = 0.5 * (diff(1, -1) + diff(-1, 1));
                        g + if grad_main < grad_anti {
                            main
                        } else if grad_anti < grad_main {
                            anti
                        } else {
                            0.5 * (main + anti)
                        }
                    };
                }
                px[GREEN] = g;
            }
        });
    out
}

/// Bayer demosaicing (`sensor.demosaic`). See [`demosaic`].
#[derive(Debug, Clone, PartialEq)]
pub struct Demosaic {
    method: DemosaicMethod,
    pattern: BayerPattern,
    depth: DemosaicDepth,
}

impl Op for Demosaic {
    type Params = DemosaicParams;
    const ID: &'static str = "sensor.demosaic";
    const SUMMARY: &'static str =
        "Reconstructs RGB from a Bayer mosaic: bilinear, Malvar–He–Cutler or Hamilton–Adams.";
    const DOC: &'static str = r#"
Interpolates the two missing colours of every pixel of a Bayer mosaic (one gray channel, u8,
u16 or f32, laid out as `pattern`); each pixel keeps its own sample.
- "bilinear": each missing colour is the mean of its nearest samples (2 or 4 neighbours).
- "malvar": the gradient-corrected bilinear filters of H. S. Malvar, L.-W. He, R. Cutler,
  "High-quality linear interpolation for demosaicing of Bayer-patterned color images", ICASSP
  2004: bilinear plus a scaled Laplacian of the pixel's own colour (gains 1/2, 5/8, 3/4), as
  eight 5×5 filters over 8 (OpenCV's `COLOR_BayerBG2BGR_EA` is a different, edge-aware method).
- "hamilton_adams": J. F. Hamilton, J. E. Adams, "Adaptive color plane interpolation in single
  sensor color electronic camera", US patent 5,629,734 (1997): green along the direction of the
  smaller gradient |ΔG| + |2C − C₋₂ − C₊₂| with half that second difference added, then red and
  blue as green plus the mean colour difference of their neighbours (along the smoother
  diagonal at the opposite colour).
Borders are mirrored without repeating the edge sample (keeps the Bayer phase). The output is
RGB, f32 in the mosaic's units or u16 (rounded, clamped) per `depth`. Speed and accuracy: see
bench/notes/sensor.md (bilinear fastest; the edge-aware methods gain several dB of PSNR on
edges).

Example:
    "rgb": (op: "sensor.demosaic", inputs: { "mosaic": "raw.raw" }, params: (method: "malvar", pattern: "rggb")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mosaic",
            PortType::Image,
            "The Bayer mosaic, gray, u8, u16 or f32.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "RGB, same size, f32 (mosaic units) or u16 per `depth`.",
        )]
    }

    fn new(params: DemosaicParams) -> Result<Self, String> {
        let DemosaicParams {
            method,
            pattern,
            depth,
        } = params;
        Ok(Demosaic {
            method,
            pattern,
            depth,
        })
    }
}

impl Operator for Demosaic {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mosaic = inputs.image("mosaic")?;
        if mosaic.channels() != Channels::Gray {
            return Err(OpError::input(
                "mosaic",
                format!(
                    "must be a one-channel (gray) Bayer mosaic, got {}",
                    mosaic.channels().name()
                ),
            ));
        }
        if mosaic.is_empty() {
            return Err(OpError::input("mosaic", "is empty"));
        }
        let samples: Vec<f32> = match mosaic.data() {
            PixelData::U8(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::U16(v) => v.iter().map(|&s| f32::from(s)).collect(),
            PixelData::F32(v) => {
                if v.iter().any(|s| !s.is_finite()) {
                    return Err(OpError::input("mosaic", "contains NaN or infinite samples"));
                }
                v.clone()
            }
        };
        let (width, height) = (mosaic.width(), mosaic.height());
        let rgb = demosaic(&samples, width, height, self.pattern, self.method);
        let data = match self.depth {
            DemosaicDepth::F32 => PixelData::F32(rgb),
            DemosaicDepth::U16 => PixelData::U16(
                rgb.iter()
                    .map(|&v| v.round().clamp(0.0, 65535.0) as u16)
                    .collect(),
            ),
        };
        let image = Image::new(width, height, Channels::Rgb, data)
            .map_err(|e| OpError::failed(format!("building the RGB image: {e}")))?;
        Ok(Outputs::new().with("image", Value::image(image)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyze::quality::{error_stats, psnr_db};
    use crate::capture::pattern::{Drawing, render};
    use ocellus_engine::value::{Depth, PixelFormat};

    const METHODS: [DemosaicMethod; 3] = [
        DemosaicMethod::Bilinear,
        DemosaicMethod::Malvar,
        DemosaicMethod::HamiltonAdams,
    ];
    const PATTERNS: [BayerPattern; 4] = [
        BayerPattern::Rggb,
        BayerPattern::Bggr,
        BayerPattern::Grbg,
        BayerPattern::Gbrg,
    ];

    /// The mosaic of an RGB f32 image.
    fn mosaic_of(rgb: &[f32], width: usize, pattern: BayerPattern) -> Vec<f32> {
        (0..rgb.len() / 3)
            .map(|i| rgb[i * 3 + pattern.color_at(i % width, i / width)])
            .collect()
    }

    fn rgb_image(w: usize, h: usize, data: Vec<f32>) -> Image {
        Image::from_f32(w, h, Channels::Rgb, data).unwrap()
    }

    /// PSNR (peak 1) of a demosaiced test card against the truth, `margin` px excluded.
    fn psnr(truth: &[f32], got: &[f32], w: usize, h: usize, margin: usize) -> f64 {
        let crop = |v: &[f32]| -> Vec<f32> {
            (margin..h - margin)
                .flat_map(|y| v[(y * w + margin) * 3..(y * w + w - margin) * 3].to_vec())
                .collect()
        };
        let (cw, ch) = (w - 2 * margin, h - 2 * margin);
        let e = error_stats(
            &rgb_image(cw, ch, crop(truth)),
            &rgb_image(cw, ch, crop(got)),
        );
        psnr_db(e.mse, 1.0).unwrap_or(f64::INFINITY)
    }

    #[test]
    fn own_samples_are_kept_and_flat_fields_stay_flat() {
        let (w, h) = (9, 7);
        for pattern in PATTERNS {
            let rgb: Vec<f32> = (0..w * h).flat_map(|_| [0.2, 0.5, 0.9]).collect();
            let mosaic = mosaic_of(&rgb, w, pattern);
            for method in METHODS {
                let out = demosaic(&mosaic, w, h, pattern, method);
                for (a, b) in out.iter().zip(&rgb) {
                    assert!((a - b).abs() < 1e-6, "{pattern:?} {method:?}: {a} vs {b}");
                }
            }
            // A random mosaic: each pixel's own channel is its sample.
            let noise: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 113) as f32).collect();
            for method in METHODS {
                let out = demosaic(&noise, w, h, pattern, method);
                for (i, &s) in noise.iter().enumerate() {
                    assert_eq!(out[i * 3 + pattern.color_at(i % w, i / w)], s);
                }
            }
        }
    }

    #[test]
    fn linear_ramps_are_reconstructed_exactly_inside() {
        // Bilinear and Malvar reproduce a linear function away from the border; Hamilton–Adams
        // too (its corrections vanish on a plane).
        let (w, h) = (20, 16);
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                [0.1 + 0.02 * x, 0.3 + 0.01 * x + 0.02 * y, 0.9 - 0.03 * y]
            })
            .collect();
        for method in METHODS {
            let out = demosaic(
                &mosaic_of(&rgb, w, BayerPattern::Grbg),
                w,
                h,
                BayerPattern::Grbg,
                method,
            );
            for y in 2..h - 2 {
                for x in 2..w - 2 {
                    for c in 0..3 {
                        let i = (y * w + x) * 3 + c;
                        assert!((out[i] - rgb[i]).abs() < 1e-5, "{method:?} ({x},{y},{c})");
                    }
                }
            }
        }
    }

    #[test]
    fn edge_aware_methods_beat_bilinear_on_a_test_card() {
        let (w, h) = (128, 96);
        let card = render(
            Drawing::TestCard { square: 16 },
            w,
            h,
            PixelFormat {
                channels: Channels::Rgb,
                depth: Depth::F32,
            },
        )
        .unwrap();
        let truth = card.as_f32().unwrap();
        let mut scores = Vec::new();
        for method in METHODS {
            let out = demosaic(
                &mosaic_of(truth, w, BayerPattern::Rggb),
                w,
                h,
                BayerPattern::Rggb,
                method,
            );
            scores.push(psnr(truth, &out, w, h, 2));
        }
        let [bilinear, malvar, hamilton_adams] = [scores[0], scores[1], scores[2]];
        eprintln!(
            "PSNR dB: bilinear {bilinear:.2}, malvar {malvar:.2}, hamilton_adams {hamilton_adams:.2}"
        );
        // The card's 2–8 px gratings alias under any Bayer sampling, hence the low absolute
        // values; the edge-aware methods must still do better.
        assert!(bilinear > 14.0, "bilinear {bilinear}");
        assert!(
            malvar > bilinear + 2.0,
            "malvar {malvar} vs bilinear {bilinear}"
        );
        assert!(
            hamilton_adams > bilinear + 3.5,
            "hamilton_adams {hamilton_adams} vs bilinear {bilinear}"
        );
    }

    #[test]
    fn hamilton_adams_follows_a_vertical_edge() {
        // A gray vertical step: green interpolated along the edge is exact, bilinear blurs it.
        let (w, h) = (16, 12);
        let rgb: Vec<f32> = (0..w * h)
            .flat_map(|i| if i % w < 7 { [0.1; 3] } else { [0.9; 3] })
            .collect();
        let mosaic = mosaic_of(&rgb, w, BayerPattern::Rggb);
        let ha = demosaic(
            &mosaic,
            w,
            h,
            BayerPattern::Rggb,
            DemosaicMethod::HamiltonAdams,
        );
        let bl = demosaic(&mosaic, w, h, BayerPattern::Rggb, DemosaicMethod::Bilinear);
        let green_error = |out: &[f32]| -> f32 {
            (0..w * h)
                .map(|i| (out[i * 3 + GREEN] - rgb[i * 3 + GREEN]).abs())
                .sum()
        };
        assert!(green_error(&ha) < 1e-5, "{}", green_error(&ha));
        assert!(green_error(&bl) > 1.0);
    }

    #[test]
    fn output_is_identical_for_any_thread_count() {
        let (w, h) = (67, 45);
        let mosaic: Vec<f32> = (0..w * h)
            .map(|i| ((i * 2654435761) % 1000) as f32)
            .collect();
        for method in METHODS {
            let run = |threads| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| demosaic(&mosaic, w, h, BayerPattern::Bggr, method))
            };
            assert_eq!(run(1), run(3));
        }
    }

    #[test]
    fn operator_checks_inputs_and_converts_depth() {
        let op = Demosaic::new(DemosaicParams {
            depth: DemosaicDepth::U16,
            ..DemosaicParams::default()
        })
        .unwrap();
        let specs = Demosaic::inputs();
        let ctx = RunContext {
            node: "n".into(),
            threads: 1,
            element: None,
        };
        let run = |img: Image| op.run(&ctx, &Inputs::new(&specs, &[Some(Value::image(img))]));
        let mut out = run(Image::from_u16(4, 4, Channels::Gray, vec![1000; 16]).unwrap()).unwrap();
        let Some(Value::Image(rgb)) = out.take("image") else {
            panic!("expected an image");
        };
        assert_eq!(rgb.channels(), Channels::Rgb);
        assert!(rgb.as_u16().unwrap().iter().all(|&v| v == 1000));
        assert!(run(Image::from_u8(2, 2, Channels::Rgb, vec![0; 12]).unwrap()).is_err());
        assert!(run(Image::from_f32(1, 1, Channels::Gray, vec![f32::NAN]).unwrap()).is_err());
        assert!(run(Image::from_u8(0, 0, Channels::Gray, vec![]).unwrap()).is_err());
        // 1×1 and 1-px-wide mosaics are mirrored onto themselves without panicking.
        assert!(run(Image::from_u8(1, 1, Channels::Gray, vec![9]).unwrap()).is_ok());
        assert!(run(Image::from_u8(1, 5, Channels::Gray, vec![9; 5]).unwrap()).is_ok());
    }
}
