//! `describe.features`: one node for "detect and describe" that switches between SIFT and ORB.
//!
//! Pipelines that compare feature types (and the feature-matching example graph) keep the same
//! graph and change one parameter. The node is a thin switch over [`super::sift`] and
//! [`super::orb`] with their OpenCV defaults; use `describe.sift` / `describe.orb` directly for
//! their other parameters.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::{param_enum, params};

use super::orb::{Orb, OrbParams};
use super::sift::{Sift, SiftParams};

param_enum! {
    /// Feature type of `describe.features`.
    pub enum FeatureMethod {
        /// SIFT (DoG keypoints, 128-d float descriptors): more accurate, slower.
        Sift = "sift",
        /// ORB (oriented FAST, 256-bit binary descriptors): faster, less invariant.
        Orb = "orb",
    }
}

#[allow(clippy::derivable_impls)]
impl Default for FeatureMethod {
    fn default() -> Self {
        FeatureMethod::Sift
    }
}

params! {
    /// Parameters of `describe.features`.
    pub struct FeaturesParams {
        /// `"sift"` or `"orb"`. Default "sift".
        method: FeatureMethod = FeatureMethod::Sift,
        /// Keep the `max_features` strongest keypoints (SIFT: 0 keeps all; ORB: at least 1).
        /// Default 2000.
        max_features: u32 = 2000 => [max = 1000000],
    }
}

/// `describe.features`: SIFT or ORB keypoints and descriptors, chosen by `method`.
pub enum Features {
    /// SIFT with OpenCV's defaults and `max_features`.
    Sift(Sift),
    /// ORB with OpenCV's defaults and `max_features`.
    Orb(Orb),
}

impl Op for Features {
    type Params = FeaturesParams;
    const ID: &'static str = "describe.features";
    const SUMMARY: &'static str =
        "Keypoints and descriptors by SIFT or ORB, chosen by one parameter.";
    const DOC: &'static str = r#"
Detect and describe with `method: "sift"` (`describe.sift`: Lowe's DoG keypoints, 128-d float
descriptors in OpenCV's 0..255 range) or `method: "orb"` (`describe.orb`: oriented FAST on an
8-level pyramid, 256-bit steered BRIEF), each with OpenCV's default settings, keeping the
`max_features` strongest keypoints. SIFT is the accurate choice under scale and viewpoint
change; ORB is several times faster. Match SIFT descriptors with L2 and ORB's with Hamming
(`match.brute_force` picks the norm from the descriptor type).

References: D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004;
E. Rublee et al., "ORB: an efficient alternative to SIFT or SURF", ICCV 2011.

Example:
    "detect": (op: "describe.features", inputs: { "image": ["left.image", "right.image"] },
               params: (method: "orb", max_features: 1000)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "Image to detect and describe (any format).",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "keypoints",
                PortType::Keypoints,
                "Keypoints in input-image pixels (x right, y down, 0-based).",
            ),
            PortSpec::new(
                "descriptors",
                PortType::Descriptors,
                "One descriptor row per keypoint (SIFT: 128 floats; ORB: 32 bytes).",
            ),
        ]
    }

    fn new(params: FeaturesParams) -> Result<Self, String> {
        match params.method {
            FeatureMethod::Sift => Ok(Features::Sift(Sift::new(SiftParams {
                max_features: params.max_features,
                ..SiftParams::default()
            })?)),
            FeatureMethod::Orb => {
                if params.max_features == 0 {
                    return Err("`max_features` must be at least 1 with method \"orb\"".into());
                }
                Ok(Features::Orb(Orb::new(OrbParams {
                    max_features: params.max_features,
                    ..OrbParams::default()
                })?))
            }
        }
    }
}

impl Operator for Features {
    fn run(&self, ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        match self {
            Features::Sift(op) => op.run(ctx, inputs),
            Features::Orb(op) => op.run(ctx, inputs),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::orb::orb_detect_and_compute;
    use crate::describe::sift::sift_detect_and_compute;
    use ocellus_engine::value::{Channels, Descriptors, Image, Value};

    fn texture(w: usize, h: usize) -> Image {
        let mut data = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64, y as f64);
                let v = 128.0
                    + 60.0 * ((fx * 0.21).sin() * (fy * 0.17).cos())
                    + 50.0 * (((fx - 40.0).powi(2) + (fy - 30.0).powi(2)).sqrt() * 0.35).sin();
                data[y * w + x] = v.clamp(0.0, 255.0) as u8;
            }
        }
        Image::from_u8(w, h, Channels::Gray, data).unwrap()
    }

    fn run(method: FeatureMethod, max_features: u32, image: &Image) -> (usize, Descriptors) {
        let op = Features::new(FeaturesParams {
            method,
            max_features,
        })
        .unwrap();
        let specs = Features::inputs();
        let ctx = RunContext {
            node: "detect".into(),
            threads: 1,
            element: None,
        };
        let values = vec![Some(Value::image(image.clone()))];
        let mut outputs = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let (Some(Value::Keypoints(k)), Some(Value::Descriptors(d))) =
            (outputs.take("keypoints"), outputs.take("descriptors"))
        else {
            panic!("missing outputs");
        };
        (k.len(), d.as_ref().clone())
    }

    #[test]
    fn switches_between_sift_and_orb_with_their_defaults() {
        let image = texture(160, 120);
        let (n, d) = run(FeatureMethod::Sift, 50, &image);
        let (kp, want) = sift_detect_and_compute(
            &image,
            &SiftParams {
                max_features: 50,
                ..SiftParams::default()
            },
        )
        .unwrap();
        assert!(n > 0 && n <= 50);
        assert_eq!(n, kp.len());
        assert_eq!(d, want);
        assert!(matches!(d, Descriptors::Float { dim: 128, .. }));

        let (n, d) = run(FeatureMethod::Orb, 60, &image);
        let (kp, want) = orb_detect_and_compute(
            &image,
            &OrbParams {
                max_features: 60,
                ..OrbParams::default()
            },
        )
        .unwrap();
        assert!(n > 0);
        assert_eq!(n, kp.len());
        assert_eq!(d, want);
        assert!(matches!(d, Descriptors::Binary { bytes: 32, .. }));
    }

    #[test]
    fn orb_needs_at_least_one_feature() {
        let params = FeaturesParams {
            method: FeatureMethod::Orb,
            max_features: 0,
        };
        assert!(Features::new(params).is_err());
        let params = FeaturesParams {
            method: FeatureMethod::Sift,
            max_features: 0,
        };
        assert!(Features::new(params).is_ok());
    }
}
