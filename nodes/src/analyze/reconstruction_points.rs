//! `analyze.reconstruction_points`: the 3-D points of a reconstruction as a coloured point
//! cloud, filtered by track length and reprojection error — the cloud `--emit` writes as PLY
//! for MeshLab, Blender or CloudCompare.
//!
//! The algorithm is [`reconstruction_points`]; [`ReconstructionPoints`] is the thin operator
//! around it.

use std::sync::Arc;

use crate::analyze::reconstruction_error::reconstruction_input;
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{PointCloud, Reconstruction, Value};

params! {
    /// Parameters of `analyze.reconstruction_points`.
    pub struct ReconstructionPointsParams {
        /// Keep points observed in at least this many images (track entries). Default 2.
        min_track_length: u32 = 2,
        /// Keep points whose mean reprojection error (the point's `error_px`) is at most this;
        /// None (the default) keeps every error, i.e. +∞.
        max_error_px: Option<f64> = None => [min = 0.0, unit = "px"],
    }
}

/// The points of `reconstruction` with at least `min_track_length` track entries and
/// `error_px ≤ max_error_px` (all errors when `None`), in the reconstruction's order, as a point
/// cloud with their colours (positions rounded to f32).
pub fn reconstruction_points(
    reconstruction: &Reconstruction,
    min_track_length: usize,
    max_error_px: Option<f64>,
) -> PointCloud {
    let kept = reconstruction.points.iter().filter(|p| {
        p.track.len() >= min_track_length && max_error_px.is_none_or(|max| p.error_px <= max)
    });
    let (positions, colors) = kept
        .map(|p| (p.position.map(|v| v as f32), p.color))
        .unzip();
    PointCloud {
        positions,
        colors: Some(colors),
        normals: None,
    }
}

/// `analyze.reconstruction_points`. See [`reconstruction_points`].
#[derive(Debug, Clone, PartialEq)]
pub struct ReconstructionPoints {
    params: ReconstructionPointsParams,
}

impl Op for ReconstructionPoints {
    type Params = ReconstructionPointsParams;
    const ID: &'static str = "analyze.reconstruction_points";
    const SUMMARY: &'static str = "The 3-D points of a reconstruction as a coloured point cloud, filtered by track length \
         and reprojection error.";
    const DOC: &'static str = r#"
Turns the sparse points of a reconstruction (io.read_colmap, io.read_bal, bundle adjustment,
structure from motion) into a PointCloud with their sRGB colours, keeping a point when its
track has at least `min_track_length` observations and its mean reprojection error
(`error_px`) is at most `max_error_px` (no limit by default; note COLMAP writes -1 for an
unknown error, which every limit keeps). Points keep the reconstruction's order; positions
are rounded to f32. `--emit` writes the cloud as binary PLY with colours, ready for MeshLab
or Blender; `count` is the number of points kept.

Example:
    "cloud": (op: "analyze.reconstruction_points", inputs: { "reconstruction": "sparse.reconstruction" },
              params: (min_track_length: 3, max_error_px: 2.0)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "reconstruction",
            PortType::Reconstruction,
            "The reconstruction whose points are taken.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "points",
                PortType::PointCloud,
                "The kept points with their colours.",
            ),
            PortSpec::new("count", PortType::Integer, "Number of points kept."),
        ]
    }

    fn new(params: ReconstructionPointsParams) -> Result<Self, String> {
        if let Some(max) = params.max_error_px
            && (max.is_nan() || max < 0.0)
        {
            return Err(format!("`max_error_px` must be at least 0, got {max}"));
        }
        Ok(ReconstructionPoints { params })
    }
}

impl Operator for ReconstructionPoints {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let reconstruction = reconstruction_input(inputs)?;
        let cloud = reconstruction_points(
            reconstruction,
            self.params.min_track_length as usize,
            self.params.max_error_px,
        );
        let count = cloud.positions.len() as i64;
        Ok(Outputs::new()
            .with("points", Value::PointCloud(Arc::new(cloud)))
            .with("count", Value::Integer(count)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::value::ReconPoint;

    fn point(id: u64, track: usize, error_px: f64) -> ReconPoint {
        ReconPoint {
            id,
            position: [id as f64, 0.5, -1.25],
            color: [id as u8, 2 * id as u8, 255],
            error_px,
            track: (0..track as u32).map(|k| (k + 1, 0)).collect(),
        }
    }

    fn rec() -> Reconstruction {
        Reconstruction {
            points: vec![
                point(1, 1, 0.1),
                point(2, 2, 0.5),
                point(3, 3, 4.0),
                point(4, 5, 1.0),
                point(5, 2, -1.0),
            ],
            ..Reconstruction::default()
        }
    }

    #[test]
    fn filters_by_track_and_error() {
        let all = reconstruction_points(&rec(), 0, None);
        assert_eq!(all.positions.len(), 5);
        assert_eq!(all.positions[2], [3.0, 0.5, -1.25]);
        assert_eq!(all.colors.as_ref().unwrap()[3], [4, 8, 255]);
        let ids = |c: &PointCloud| c.positions.iter().map(|p| p[0] as u64).collect::<Vec<_>>();
        assert_eq!(ids(&reconstruction_points(&rec(), 2, None)), [2, 3, 4, 5]);
        assert_eq!(ids(&reconstruction_points(&rec(), 3, None)), [3, 4]);
        assert_eq!(ids(&reconstruction_points(&rec(), 2, Some(1.0))), [2, 4, 5]);
        let c = reconstruction_points(&rec(), 2, Some(1.0));
        assert_eq!(c.colors.unwrap(), [[2, 4, 255], [4, 8, 255], [5, 10, 255]]);
        assert!(reconstruction_points(&rec(), 6, None).positions.is_empty());
    }

    #[test]
    fn op_outputs_cloud_and_count() {
        let op = ReconstructionPoints::new(ReconstructionPointsParams::default()).unwrap();
        let specs = ReconstructionPoints::inputs();
        let values = [Some(Value::Reconstruction(Arc::new(rec())))];
        let ctx = RunContext {
            node: "cloud".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        assert_eq!(out.take("count"), Some(Value::Integer(4)));
        let Some(Value::PointCloud(cloud)) = out.take("points") else {
            panic!("expected a point cloud");
        };
        assert_eq!(cloud.positions.len(), 4);
        assert!(
            ReconstructionPoints::new(ReconstructionPointsParams {
                min_track_length: 2,
                max_error_px: Some(f64::NAN),
            })
            .is_err()
        );
    }
}
