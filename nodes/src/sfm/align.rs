//! `sfm.align`: a reconstruction moved into the frame of reference poses by the similarity that
//! best maps its camera centres onto theirs — COLMAP's `model_aligner` (geo-registration).
//!
//! Structure from motion fixes its result only up to a similarity (the gauge: where the world
//! origin is, how it is turned, and its scale). Given the true or surveyed camera_from_world of
//! the views, [`align_reconstruction`] fits `world_ref = s·Q·world_est + c` (Umeyama's least
//! squares over the registered camera centres, as `analyze.reconstruction_error` does) and
//! applies it: points `X' = s·Q·X + c`; poses `R' = R·Qᵀ`, `t' = s·t − R'·c` (the camera frame
//! scaled by `s`, so every projection — and hence every reprojection error — is unchanged).
//! Downstream, dense depth, meshes and distances come out in the reference's units and frame,
//! so they can be compared with the truth directly.

use nalgebra::Vector3;
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, Pose, Reconstruction, Value};

use crate::analyze::reconstruction_error::{
    reconstruction_input, rotation_and_centre, similarity_to_truth, truth_inputs,
};
use crate::geometry::pose_util::pose_from_rt;
use crate::geometry::transforms::Similarity3;

params! {
    /// Parameters of `sfm.align` (none).
    pub struct AlignParams {}
}

/// A reconstruction in the reference frame, and how well its cameras fit the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct Aligned {
    /// The moved reconstruction.
    pub reconstruction: Reconstruction,
    /// The similarity applied (reference from reconstruction).
    pub similarity: Similarity3,
    /// Registered images matched to a reference pose.
    pub registered: usize,
    /// RMS distance between aligned and reference camera centres, reference units.
    pub centre_rms: f64,
    /// Largest such distance.
    pub centre_max: f64,
}

/// Moves `reconstruction` into the frame of the reference camera_from_world `poses` (matched
/// to its images by `names`, or image id k + 1 ↔ poses[k]). See the module documentation.
pub fn align_reconstruction(
    reconstruction: &Reconstruction,
    poses: &[Pose],
    names: Option<&[String]>,
) -> Result<Aligned, String> {
    let (sim, view_of) = similarity_to_truth(reconstruction, poses, names)?;
    let q_t = sim.rotation.transpose();
    let mut out = reconstruction.clone();
    let (mut sum2, mut max) = (0.0f64, 0.0f64);
    for (image, &k) in out.images.iter_mut().zip(&view_of) {
        let (r, c_est) = rotation_and_centre(&image.camera_from_world);
        let r_new = r * q_t;
        let t = Vector3::from(image.camera_from_world.translation);
        let t_new = t * sim.scale - r_new * sim.translation;
        image.camera_from_world = pose_from_rt(&r_new, &t_new);
        let (_, c_ref) = rotation_and_centre(&poses[k]);
        let d = (sim.apply(&c_est.into()) - c_ref).norm();
        sum2 += d * d;
        max = max.max(d);
    }
    for point in &mut out.points {
        point.position = sim.apply(&point.position).into();
    }
    if !out
        .points
        .iter()
        .flat_map(|p| p.position)
        .all(f64::is_finite)
    {
        return Err("the alignment produced non-finite points".into());
    }
    Ok(Aligned {
        reconstruction: out,
        similarity: sim,
        registered: view_of.len(),
        centre_rms: (sum2 / view_of.len().max(1) as f64).sqrt(),
        centre_max: max,
    })
}

/// `sfm.align`. See [`align_reconstruction`].
#[derive(Debug, Clone, PartialEq)]
pub struct Align;

impl Op for Align {
    type Params = AlignParams;
    const ID: &'static str = "sfm.align";
    const SUMMARY: &'static str = "Moves a reconstruction into the frame and scale of reference \
        camera poses by the similarity fitted to the camera centres (COLMAP's model_aligner).";
    const DOC: &'static str = r#"
Structure from motion recovers a scene only up to a similarity. Given reference
camera_from_world `poses` (the truth of a synthetic capture, or surveyed cameras), this fits
world_ref = s·Q·world_est + c by least squares over the registered camera centres (Umeyama,
"Least-squares estimation of transformation parameters between two point patterns", PAMI 1991)
and applies it: points X' = s·Q·X + c, poses R' = R·Qᵀ, t' = s·t − R'·c. Projections, and so
reprojection errors, do not change. Images are matched to poses by `names` (exactly, or by the
last path component when unique), otherwise image id k + 1 is poses[k]; at least 3
registered, non-collinear centres are needed.

Metrics: `registered`, `scale` (s, reference units per reconstruction unit),
`centre_rms` and `centre_max` (aligned vs reference camera centres, reference units).

Example:
    "align": (op: "sfm.align", inputs: { "reconstruction": "ba.reconstruction", "poses": "capture.poses" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The reconstruction to move.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "Reference camera_from_world of every view.",
            ),
            PortSpec::new(
                "names",
                PortType::Text.list_of(),
                "View names, one per pose; images are matched by name when given, else image \
                 id k + 1 is poses[k].",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The reconstruction in the reference frame.",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "registered, scale, centre_rms, centre_max.",
            ),
        ]
    }

    fn new(_params: AlignParams) -> Result<Self, String> {
        Ok(Align)
    }
}

impl Operator for Align {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let reconstruction = reconstruction_input(inputs)?;
        let (poses, names) = truth_inputs(inputs)?;
        let aligned = align_reconstruction(reconstruction, &poses, names.as_deref())
            .map_err(OpError::failed)?;
        let mut m = Metrics::new();
        m.insert("registered".into(), aligned.registered as f64);
        m.insert("scale".into(), aligned.similarity.scale);
        m.insert("centre_rms".into(), aligned.centre_rms);
        m.insert("centre_max".into(), aligned.centre_max);
        Ok(Outputs::new()
            .with(
                "reconstruction",
                Value::Reconstruction(std::sync::Arc::new(aligned.reconstruction)),
            )
            .with("metrics", Value::metrics(m)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyze::reconstruction_error::reprojection_rms;
    use nalgebra::{Matrix3, Rotation3};
    use ocellus_engine::value::{Camera, CameraModel, ReconImage, ReconPoint};
    use std::collections::BTreeMap;

    /// True cameras on a ring looking at the origin, and points in front of them.
    fn truth() -> (Vec<Pose>, Vec<[f64; 3]>) {
        let poses = (0..5)
            .map(|k| {
                let a = k as f64 * 0.5;
                let eye = Vector3::new(3.0 * a.cos(), 0.5 + 0.1 * k as f64, 3.0 * a.sin());
                let z = (-eye).normalize();
                let x = Vector3::y().cross(&z).normalize();
                let y = z.cross(&x);
                let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
                pose_from_rt(&r, &(-(r * eye)))
            })
            .collect();
        let points = (0..20)
            .map(|i| {
                let f = i as f64;
                [
                    (f * 0.37).sin() * 0.8,
                    (f * 0.71).cos() * 0.5,
                    (f * 0.13).sin(),
                ]
            })
            .collect();
        (poses, points)
    }

    /// The truth seen through a similarity `world_est = (Qᵀ(X − c))/s`, with observations.
    fn estimated(q: &Matrix3<f64>, s: f64, c: &Vector3<f64>) -> Reconstruction {
        let (poses, points) = truth();
        let camera = Camera {
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        };
        let to_est = |x: &Vector3<f64>| q.transpose() * (x - c) / s;
        let mut images = Vec::new();
        for (k, p) in poses.iter().enumerate() {
            let (r, centre) = rotation_and_centre(p);
            let r_est = r * q;
            let t_est = -(r_est * to_est(&centre));
            let mut points2d = Vec::new();
            for (i, x) in points.iter().enumerate() {
                let xc = r * (Vector3::from(*x) - centre);
                points2d.push((
                    [500.0 * xc.x / xc.z + 320.0, 500.0 * xc.y / xc.z + 240.0],
                    Some(i as u64),
                ));
            }
            images.push(ReconImage {
                id: k as u32 + 1,
                camera_id: 1,
                name: format!("view_{k}"),
                camera_from_world: pose_from_rt(&r_est, &t_est),
                points2d,
            });
        }
        let points = points
            .iter()
            .enumerate()
            .map(|(i, x)| ReconPoint {
                id: i as u64,
                position: to_est(&Vector3::from(*x)).into(),
                color: [0; 3],
                error_px: 0.0,
                track: (0..5).map(|k| (k + 1, i as u32)).collect(),
            })
            .collect();
        Reconstruction {
            cameras: BTreeMap::from([(1, camera)]),
            images,
            points,
        }
    }

    #[test]
    fn a_similar_reconstruction_lands_on_the_truth() {
        let q = *Rotation3::from_euler_angles(0.3, -1.1, 2.0).matrix();
        let (s, c) = (0.25, Vector3::new(1.0, -2.0, 0.5));
        let rec = estimated(&q, s, &c);
        let (poses, points) = truth();
        let a = align_reconstruction(&rec, &poses, None).unwrap();
        assert!(
            (a.similarity.scale - s).abs() < 1e-9,
            "{}",
            a.similarity.scale
        );
        assert!(a.centre_max < 1e-9, "{}", a.centre_max);
        for (p, x) in a.reconstruction.points.iter().zip(&points) {
            let d = (Vector3::from(p.position) - Vector3::from(*x)).norm();
            assert!(d < 1e-9, "{d}");
        }
        for (image, truth) in a.reconstruction.images.iter().zip(&poses) {
            let (r, c) = rotation_and_centre(&image.camera_from_world);
            let (r_t, c_t) = rotation_and_centre(truth);
            assert!((r - r_t).norm() < 1e-9);
            assert!((c - c_t).norm() < 1e-9);
        }
        // Projections are unchanged by the alignment.
        let before = reprojection_rms(&rec).unwrap().0;
        let after = reprojection_rms(&a.reconstruction).unwrap().0;
        assert!(before < 1e-9 && after < 1e-9, "{before} {after}");
    }

    #[test]
    fn too_few_views_is_an_error() {
        let q = Matrix3::identity();
        let mut rec = estimated(&q, 1.0, &Vector3::zeros());
        rec.images.truncate(2);
        let (poses, _) = truth();
        let e = align_reconstruction(&rec, &poses, None).unwrap_err();
        assert!(e.contains("at least 3"), "{e}");
    }
}
