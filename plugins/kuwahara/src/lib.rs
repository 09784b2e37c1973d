//! Ocellus plugin `kuwahara`: the anisotropic Kuwahara filter, guided by a structure tensor —
//! the painterly, edge-preserving smoothing of Kyprianidis, Kang and Döllner, "Image and Video
//! Abstraction by Anisotropic Kuwahara Filtering", Computer Graphics Forum 28(7), 2009.
//!
//! Build: `cargo build --release -p ocellus-plugin-kuwahara`; load with
//! `ocellus run graph.ron --plugin target/release/libocellus_plugin_kuwahara.so`.

pub mod algo;

use ocellus_plugin::{
    Context, InputViews, OutputValue, OutputValues, OwnedSamples, Param, Params, PluginOp, Port,
    PortType, Samples,
};

use crate::algo::{KuwaharaParams, anisotropic_kuwahara_with};

/// `kuwahara.anisotropic`: the operator.
pub struct Anisotropic {
    params: KuwaharaParams,
}

impl PluginOp for Anisotropic {
    const ID: &'static str = "kuwahara.anisotropic";
    const SUMMARY: &'static str =
        "Anisotropic Kuwahara filter: painterly, edge-preserving smoothing.";
    const DOC: &'static str = "Kyprianidis, Kang, Döllner (CGF 2009). The smoothed structure tensor \
        gives each pixel an orientation and an anisotropy A; the filter window is an ellipse \
        stretched along the edge (semi-axes radius·(alpha+A)/alpha and radius·alpha/(alpha+A)), \
        split into `sectors` weighted sectors (polynomial sector weights of Kyprianidis et al. \
        2010). The output is the mean of the sector means weighted by 1/(1+σᵢ^sharpness), where σᵢ \
        is a sector's standard deviation in 8-bit units — so flat sectors dominate and edges stay \
        sharp. Works on gray/rgb/rgba × u8/u16/f32 (u8 and u16 are normalised to 0..1 and rounded \
        back). Example: `(op: \"kuwahara.anisotropic\", inputs: { \"image\": \"photo.image\" }, \
        params: (radius: 6.0))`.";
    const INPUTS: &'static [Port] = &[Port::new(
        "image",
        PortType::Image,
        "gray/rgb/rgba image, u8/u16/f32",
    )];
    const OUTPUTS: &'static [Port] = &[Port::new(
        "image",
        PortType::Image,
        "the filtered image, same format",
    )];
    const PARAMS: &'static [Param] = &[
        Param::float(
            "radius",
            6.0,
            "Radius of the filter window before stretching.",
        )
        .min(0.5)
        .max(256.0)
        .unit("px"),
        Param::int("sectors", 8, "Number of sectors N of the window.")
            .min(4.0)
            .max(16.0),
        Param::float(
            "sharpness",
            8.0,
            "Exponent q of the sector weights 1/(1+σ^q); larger keeps edges crisper.",
        )
        .min(0.0)
        .max(64.0),
        Param::float(
            "alpha",
            1.0,
            "Anisotropy tuning: larger values make windows rounder.",
        )
        .min(0.01)
        .max(100.0),
        Param::float(
            "tensor_sigma",
            2.0,
            "Gaussian smoothing of the structure tensor.",
        )
        .min(0.0)
        .max(64.0)
        .unit("px"),
    ];

    fn new(params: &Params) -> Result<Self, String> {
        let params = KuwaharaParams {
            radius: params.float("radius")? as f32,
            sectors: usize::try_from(params.int("sectors")?).map_err(|e| e.to_string())?,
            sharpness: params.float("sharpness")? as f32,
            alpha: params.float("alpha")? as f32,
            tensor_sigma: params.float("tensor_sigma")? as f32,
        };
        params.validate()?;
        Ok(Anisotropic { params })
    }

    fn run(&self, ctx: &Context, inputs: &InputViews) -> Result<OutputValues, String> {
        let image = inputs.image("image")?;
        let (w, h, c) = (image.width, image.height, image.channels);
        let mut normalised = Vec::with_capacity(w * h * c);
        for y in 0..h {
            match image.samples {
                Samples::U8(_) => normalised.extend(
                    image
                        .row_u8(y)
                        .unwrap_or_default()
                        .iter()
                        .map(|&v| f32::from(v) / 255.0),
                ),
                Samples::U16(_) => normalised.extend(
                    image
                        .row_u16(y)
                        .unwrap_or_default()
                        .iter()
                        .map(|&v| f32::from(v) / 65535.0),
                ),
                Samples::F32(_) => {
                    normalised.extend_from_slice(image.row_f32(y).unwrap_or_default())
                }
            }
        }
        // Bands of rows run on the host's thread pool; the result does not depend on the schedule.
        let filtered =
            anisotropic_kuwahara_with(&normalised, w, h, c, &self.params, &|n, body| {
                ctx.parallel_for(n, body);
            })?;
        let samples = match image.samples {
            Samples::U8(_) => OwnedSamples::U8(
                filtered
                    .iter()
                    .map(|&v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                    .collect(),
            ),
            Samples::U16(_) => OwnedSamples::U16(
                filtered
                    .iter()
                    .map(|&v| (v * 65535.0).round().clamp(0.0, 65535.0) as u16)
                    .collect(),
            ),
            Samples::F32(_) => OwnedSamples::F32(filtered),
        };
        Ok(OutputValues::new().with(
            "image",
            OutputValue::Image {
                width: w,
                height: h,
                channels: c,
                samples,
            },
        ))
    }
}

ocellus_plugin::export_plugin!(name: "kuwahara", ops: [Anisotropic]);
