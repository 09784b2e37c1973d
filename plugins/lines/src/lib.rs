//! Ocellus plugin `lines`: LSD, the a-contrario line segment detector of von Gioi, Jakubowicz,
//! Morel and Randall ("LSD: a Fast Line Segment Detector with a False Detection Control", PAMI
//! 2010; "LSD: a Line Segment Detector", IPOL 2012). One operator with several outputs: the
//! segments as a matrix, their count, and a debug image.
//!
//! Build: `cargo build --release -p ocellus-plugin-lines`; load with
//! `ocellus run graph.ron --plugin target/release/libocellus_plugin_lines.so`.

pub mod lsd;

use ocellus_plugin::{
    Context, InputViews, OutputValue, OutputValues, OwnedSamples, Param, Params, PluginOp, Port,
    PortType, Samples,
};

use crate::lsd::{LsdParams, detect_segments, draw_segments};

/// Columns of the `segments` matrix.
pub const SEGMENT_COLUMNS: usize = 7;

/// `lines.lsd`: the operator.
pub struct Lsd {
    params: LsdParams,
}

impl PluginOp for Lsd {
    const ID: &'static str = "lines.lsd";
    const SUMMARY: &'static str =
        "LSD line segments with false-detection control: matrix, count, debug image.";
    const DOC: &'static str = "von Gioi et al. (PAMI 2010, IPOL 2012): Gaussian subsampling by `scale`, \
        level-line angles from 2×2 gradients, region growing of pixels whose angle agrees within \
        `angle_tolerance`, rectangle approximation and refinement, and acceptance when the number \
        of false alarms satisfies −log10(NFA) > `log_eps`. Colour input is reduced to the mean of its \
        first three channels; u16 and f32 are scaled to 0..255. Outputs: `segments`, an N×7 matrix \
        of rows [x1, y1, x2, y2, width, p, −log10 NFA] in input pixel coordinates (pixel centres \
        at integers, x right, y down); `count`; `debug`, the gray input as RGB with segments in \
        red. Example: `(op: \"lines.lsd\", inputs: { \"image\": \"gray.image\" })`.";
    const INPUTS: &'static [Port] = &[Port::new(
        "image",
        PortType::Image,
        "gray or colour image, u8/u16/f32",
    )];
    const OUTPUTS: &'static [Port] = &[
        Port::new(
            "segments",
            PortType::Matrix,
            "N×7: x1, y1, x2, y2, width, p, −log10 NFA",
        ),
        Port::new("count", PortType::Integer, "number of segments N"),
        Port::new(
            "debug",
            PortType::Image,
            "RGB u8: the input with the segments drawn in red",
        ),
    ];
    const PARAMS: &'static [Param] = &[
        Param::float("scale", 0.8, "Subsampling factor applied before detection.")
            .min(0.05)
            .max(1.0),
        Param::float("sigma_scale", 0.6, "Gaussian sigma = sigma_scale / scale.")
            .min(0.05)
            .max(10.0),
        Param::float(
            "quant",
            2.0,
            "Bound on gradient quantization error (gray levels).",
        )
        .min(0.0)
        .max(255.0),
        Param::float(
            "angle_tolerance",
            22.5,
            "Angle tolerance of region growing.",
        )
        .min(1.0)
        .max(90.0)
        .unit("deg"),
        Param::float(
            "log_eps",
            0.0,
            "Detection threshold: keep segments with −log10(NFA) > log_eps.",
        )
        .min(-100.0)
        .max(100.0),
        Param::float(
            "density_threshold",
            0.7,
            "Minimum density of aligned points in a rectangle.",
        )
        .min(0.0)
        .max(1.0),
        Param::int(
            "bins",
            1024,
            "Bins of the gradient-magnitude pseudo-ordering.",
        )
        .min(1.0)
        .max(1_000_000.0),
    ];

    fn new(params: &Params) -> Result<Self, String> {
        let params = LsdParams {
            scale: params.float("scale")?,
            sigma_scale: params.float("sigma_scale")?,
            quant: params.float("quant")?,
            angle_tolerance_deg: params.float("angle_tolerance")?,
            log_eps: params.float("log_eps")?,
            density_threshold: params.float("density_threshold")?,
            bins: usize::try_from(params.int("bins")?).map_err(|e| e.to_string())?,
        };
        params.validate()?;
        Ok(Lsd { params })
    }

    fn run(&self, _ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
        let image = inputs.image("image")?;
        let (w, h, c) = (image.width, image.height, image.channels);
        let luma_of = |px: &[f64]| {
            if c >= 3 {
                (px[0] + px[1] + px[2]) / 3.0
            } else {
                px[0]
            }
        };
        let mut gray = Vec::with_capacity(w * h);
        let mut pixel = vec![0.0f64; c];
        for y in 0..h {
            for x in 0..w {
                for (k, v) in pixel.iter_mut().enumerate() {
                    let i = x * c + k;
                    *v = match image.samples {
                        Samples::U8(_) => image
                            .row_u8(y)
                            .and_then(|r| r.get(i))
                            .map_or(0.0, |&s| f64::from(s)),
                        Samples::U16(_) => image
                            .row_u16(y)
                            .and_then(|r| r.get(i))
                            .map_or(0.0, |&s| f64::from(s) / 257.0),
                        Samples::F32(_) => image
                            .row_f32(y)
                            .and_then(|r| r.get(i))
                            .map_or(0.0, |&s| f64::from(s) * 255.0),
                    };
                }
                gray.push(luma_of(&pixel));
            }
        }
        let segments = detect_segments(&gray, w, h, &self.params)?;
        let mut data = Vec::with_capacity(segments.len() * SEGMENT_COLUMNS);
        for s in &segments {
            data.extend_from_slice(&[s.x1, s.y1, s.x2, s.y2, s.width, s.p, s.log_nfa]);
        }
        let debug = draw_segments(&gray, w, h, &segments);
        let count = i64::try_from(segments.len()).unwrap_or(i64::MAX);
        Ok(OutputValues::new()
            .with(
                "segments",
                OutputValue::Matrix {
                    rows: segments.len(),
                    cols: SEGMENT_COLUMNS,
                    data,
                },
            )
            .integer("count", count)
            .with(
                "debug",
                OutputValue::Image {
                    width: w,
                    height: h,
                    channels: 3,
                    samples: OwnedSamples::U8(debug),
                },
            ))
    }
}

ocellus_plugin::export_plugin!(name: "lines", ops: [Lsd]);
