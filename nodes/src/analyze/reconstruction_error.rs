//! `analyze.reconstruction_error`: how far a reconstruction's cameras are from the true ones,
//! up to the similarity (gauge) freedom every structure-from-motion result has, and its
//! reprojection error.
//!
//! The algorithm is [`reconstruction_error`]; [`ReconstructionError`] is the thin operator
//! around it.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};
use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, Pose, Reconstruction, Value};

use crate::geometry::pose_util::rotation_angle_deg;
use crate::geometry::transforms::{Pair3, Similarity3, umeyama};
use crate::optimize::camera_model::project;

params! {
    /// Parameters of `analyze.reconstruction_error` (none).
    pub struct ReconstructionErrorParams {}
}

/// The errors of a reconstruction against the true poses; see [`reconstruction_error`].
#[derive(Debug, Clone, PartialEq)]
pub struct ReconstructionReport {
    /// Views in the truth.
    pub views: usize,
    /// Reconstruction images matched to a view.
    pub registered: usize,
    /// Per registered view, in view order: `(view, rotation error °, centre error)`.
    pub per_view: Vec<(usize, f64, f64)>,
    /// Diagonal of the bounding box of all true camera centres (world units).
    pub scene_size: f64,
    /// Scale of the estimated similarity (true units per reconstruction unit).
    pub scale: f64,
    /// 3-D points of the reconstruction.
    pub points: usize,
    /// Track entries (observations) over all points.
    pub observations: usize,
    /// Root mean square of the 2-D reprojection error norms, pixels (0 without observations).
    pub reprojection_rms_px: f64,
    /// Observations whose point cannot be projected (behind a pinhole camera); not in the RMS.
    pub unprojectable: usize,
}

/// Median (mean of the two middle values for an even count; 0 when empty).
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

impl ReconstructionReport {
    /// The report as metrics (see the operator's documentation for the names).
    pub fn metrics(&self) -> Metrics {
        let mut rot: Vec<f64> = self.per_view.iter().map(|v| v.1).collect();
        let mut centre: Vec<f64> = self.per_view.iter().map(|v| v.2).collect();
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let (rot_max, centre_max) = (max(&rot), max(&centre));
        let (rot_median, centre_median) = (median(&mut rot), median(&mut centre));
        let rel = |x: f64| {
            if self.scene_size > 0.0 {
                x / self.scene_size
            } else {
                0.0
            }
        };
        let mut m = Metrics::new();
        m.insert("views".into(), self.views as f64);
        m.insert("registered".into(), self.registered as f64);
        m.insert(
            "registered_fraction".into(),
            if self.views > 0 {
                self.registered as f64 / self.views as f64
            } else {
                0.0
            },
        );
        m.insert("rotation_error_median_deg".into(), rot_median);
        m.insert("rotation_error_max_deg".into(), rot_max);
        m.insert("center_error_median".into(), centre_median);
        m.insert("center_error_max".into(), centre_max);
        m.insert("center_error_median_rel".into(), rel(centre_median));
        m.insert("center_error_max_rel".into(), rel(centre_max));
        m.insert("scene_size".into(), self.scene_size);
        m.insert("scale".into(), self.scale);
        m.insert("points".into(), self.points as f64);
        m.insert("observations".into(), self.observations as f64);
        m.insert("reprojection_rms_px".into(), self.reprojection_rms_px);
        m.insert("unprojectable".into(), self.unprojectable as f64);
        m
    }
}

/// The rotation (row-major → matrix) and centre `−Rᵀt` of a camera_from_world pose.
pub(crate) fn rotation_and_centre(pose: &Pose) -> (Matrix3<f64>, Vector3<f64>) {
    let r = Matrix3::from_row_slice(&pose.rotation_matrix());
    let c = -(r.transpose() * Vector3::from(pose.translation));
    (r, c)
}

/// The last path component of a name (`/` or `\` separated).
fn base_name(name: &str) -> &str {
    name.rsplit(['/', '\\']).next().unwrap_or(name)
}

/// For each reconstruction image (in its order), the view it shows, or an error; `list` names
/// the input holding the views in messages.
pub(crate) fn match_views(
    reconstruction: &Reconstruction,
    views: usize,
    names: Option<&[String]>,
    list: &str,
) -> Result<Vec<usize>, String> {
    let mut view_of = Vec::with_capacity(reconstruction.images.len());
    match names {
        Some(names) => {
            if names.len() != views {
                return Err(format!(
                    "`names` has {} entries but `{list}` {views}",
                    names.len()
                ));
            }
            let mut exact = HashMap::new();
            let mut base: HashMap<&str, Option<usize>> = HashMap::new();
            for (k, n) in names.iter().enumerate() {
                if exact.insert(n.as_str(), k).is_some() {
                    return Err(format!("view name `{n}` appears twice in `names`"));
                }
                // A base name shared by two views cannot be used to match.
                base.entry(base_name(n))
                    .and_modify(|v| *v = None)
                    .or_insert(Some(k));
            }
            for image in &reconstruction.images {
                let k = exact
                    .get(image.name.as_str())
                    .copied()
                    .or_else(|| base.get(base_name(&image.name)).copied().flatten())
                    .ok_or_else(|| {
                        format!("image {} `{}` matches no view name", image.id, image.name)
                    })?;
                view_of.push(k);
            }
        }
        None => {
            for image in &reconstruction.images {
                let k = (image.id as usize)
                    .checked_sub(1)
                    .filter(|&k| k < views)
                    .ok_or_else(|| {
                        format!(
                            "image id {} has no view: without `names`, image id k + 1 is \
                             {list}[k] (1..={views})",
                            image.id
                        )
                    })?;
                view_of.push(k);
            }
        }
    }
    let mut seen = vec![None; views];
    for (image, &k) in reconstruction.images.iter().zip(&view_of) {
        if let Some(other) = seen[k].replace(image.id) {
            return Err(format!(
                "images {other} and {} both match view {k}",
                image.id
            ));
        }
    }
    Ok(view_of)
}

/// The similarity `world_true = s·Q·world_est + c` fitted (Umeyama) to the registered camera
/// centres, and the view of each reconstruction image (see [`reconstruction_error`] for the
/// matching rules). At least 3 non-collinear centres are needed.
pub(crate) fn similarity_to_truth(
    reconstruction: &Reconstruction,
    truth: &[Pose],
    names: Option<&[String]>,
) -> Result<(Similarity3, Vec<usize>), String> {
    let view_of = match_views(reconstruction, truth.len(), names, "poses")?;
    let registered = view_of.len();
    if registered < 3 {
        return Err(format!(
            "{registered} registered views: the alignment needs at least 3"
        ));
    }
    let pairs: Vec<Pair3> = reconstruction
        .images
        .iter()
        .zip(&view_of)
        .map(|(image, &k)| {
            let (_, c_est) = rotation_and_centre(&image.camera_from_world);
            let (_, c_true) = rotation_and_centre(&truth[k]);
            [c_est.into(), c_true.into()]
        })
        .collect();
    let sim = umeyama(&pairs, true).ok_or_else(|| {
        "the registered camera centres are collinear or coincide: the alignment is undetermined"
            .to_string()
    })?;
    Ok((sim, view_of))
}

/// Compares `reconstruction` with the true camera_from_world `truth` of every view.
///
/// Images are matched to views by name when `names` (one per view) is given — exactly, or else
/// by the last path component when that is unique among the views — and otherwise image id
/// `k + 1` is view `k`. The similarity `world_true = s·Q·world_est + c` is Umeyama's
/// least-squares fit of the estimated camera centres `−Rᵀt` onto the true ones over the
/// registered views (at least 3, not collinear); then per view the rotation error is the angle
/// between `R_est·Qᵀ` (the aligned camera_from_world rotation) and `R_true`, and the centre
/// error `‖s·Q·c_est + c − c_true‖`. The reprojection error projects every point into each
/// image of its track with that image's camera.
pub fn reconstruction_error(
    reconstruction: &Reconstruction,
    truth: &[Pose],
    names: Option<&[String]>,
) -> Result<ReconstructionReport, String> {
    let (sim, view_of) = similarity_to_truth(reconstruction, truth, names)?;
    let registered = view_of.len();
    let estimated: Vec<_> = reconstruction
        .images
        .iter()
        .map(|i| rotation_and_centre(&i.camera_from_world))
        .collect();
    let true_poses: Vec<_> = truth.iter().map(rotation_and_centre).collect();
    let mut per_view: Vec<(usize, f64, f64)> = estimated
        .iter()
        .zip(&view_of)
        .map(|((r, c), &k)| {
            let (r_true, c_true) = &true_poses[k];
            let aligned = r * sim.rotation.transpose();
            let c_aligned = sim.rotation * c * sim.scale + sim.translation;
            (
                k,
                rotation_angle_deg(r_true, &aligned),
                (c_aligned - c_true).norm(),
            )
        })
        .collect();
    per_view.sort_by_key(|v| v.0);

    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for (_, c) in &true_poses {
        lo = lo.inf(c);
        hi = hi.sup(c);
    }
    let scene_size = (hi - lo).norm();

    let (rms, observations, unprojectable) = reprojection_rms(reconstruction)?;
    Ok(ReconstructionReport {
        views: truth.len(),
        registered,
        per_view,
        scene_size,
        scale: sim.scale,
        points: reconstruction.points.len(),
        observations,
        reprojection_rms_px: rms,
        unprojectable,
    })
}

/// RMS of the reprojection error norms (pixels), the number of observations and how many
/// of them could not be projected.
pub fn reprojection_rms(reconstruction: &Reconstruction) -> Result<(f64, usize, usize), String> {
    let images: HashMap<u32, _> = reconstruction.images.iter().map(|i| (i.id, i)).collect();
    let (mut sum, mut used, mut total, mut failed) = (0.0, 0usize, 0usize, 0usize);
    for point in &reconstruction.points {
        for &(image_id, index) in &point.track {
            total += 1;
            let image = images.get(&image_id).ok_or_else(|| {
                format!(
                    "point {}: track names image {image_id}, which is missing",
                    point.id
                )
            })?;
            let camera = reconstruction
                .cameras
                .get(&image.camera_id)
                .ok_or_else(|| {
                    format!("image {image_id}: camera {} is missing", image.camera_id)
                })?;
            let (observed, _) = image.points2d.get(index as usize).ok_or_else(|| {
                format!(
                    "point {}: track entry ({image_id}, {index}) is beyond image {image_id}'s {} 2-D points",
                    point.id,
                    image.points2d.len()
                )
            })?;
            let r = image.camera_from_world.rotation_matrix();
            let t = image.camera_from_world.translation;
            let x = point.position;
            let p: [f64; 3] = std::array::from_fn(|i| {
                r[3 * i] * x[0] + r[3 * i + 1] * x[1] + r[3 * i + 2] * x[2] + t[i]
            });
            match project(camera.model, &camera.params, p) {
                Some(proj) => {
                    let (dx, dy) = (proj.pixel[0] - observed[0], proj.pixel[1] - observed[1]);
                    sum += dx * dx + dy * dy;
                    used += 1;
                }
                None => failed += 1,
            }
        }
    }
    let rms = if used > 0 {
        (sum / used as f64).sqrt()
    } else {
        0.0
    };
    Ok((rms, total, failed))
}

/// `analyze.reconstruction_error`. See [`reconstruction_error`].
#[derive(Debug, Clone, PartialEq)]
pub struct ReconstructionError;

impl Op for ReconstructionError {
    type Params = ReconstructionErrorParams;
    const ID: &'static str = "analyze.reconstruction_error";
    const SUMMARY: &'static str = "Camera rotation and centre errors of a reconstruction against \
        true poses, after a similarity alignment, and its reprojection error.";
    const DOC: &'static str = r#"
Scores a structure-from-motion result against ground truth. `poses` holds the true
camera_from_world of every view (e.g. io.read_poses or capture.render); each image of the
reconstruction is matched to a view: with `names` (one per view, in the order of `poses`,
e.g. from io.read_poses or capture.sequence) by its name — exactly, or else by the last path
component when that is unique among the views; without `names`, image id k + 1 is poses[k].
An image that matches no view, or two images matching one view, is an error.

Alignment: a reconstruction is only defined up to a similarity, so the one mapping the
estimated camera centres −Rᵀt onto the true ones, world_true = s·Q·world_est + c, is fitted by
least squares (Umeyama, "Least-squares estimation of transformation parameters between two
point patterns", PAMI 1991) over all registered views; at least 3 non-collinear centres are
needed. Per registered view: rotation error = angle between R_est·Qᵀ (the aligned rotation)
and R_true, degrees; centre error = ‖s·Q·c_est + c − c_true‖, true world units.

Metrics: `views`, `registered`, `registered_fraction`; `rotation_error_median_deg`,
`rotation_error_max_deg`; `center_error_median`, `center_error_max` and the same divided by
`scene_size` (`center_error_median_rel`, `center_error_max_rel`), where scene_size is the
diagonal of the bounding box of the true camera centres of all views; `scale` (s); `points`,
`observations` (track entries); `reprojection_rms_px`, the root mean square of the 2-D error
norm over all observations, each point projected into each image of its track through its
camera model (observations a pinhole camera cannot see, behind it, are left out and counted
in `unprojectable`). Medians of an even count are the mean of the two middle values.

Example:
    "score": (op: "analyze.reconstruction_error",
              inputs: { "reconstruction": "sfm.reconstruction", "poses": "truth.poses",
                        "names": "truth.names" }),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "reconstruction",
                PortType::Reconstruction,
                "The reconstruction to score.",
            ),
            PortSpec::new(
                "poses",
                PortType::Pose.list_of(),
                "The true camera_from_world of every view.",
            ),
            PortSpec::new(
                "names",
                PortType::Text.list_of(),
                "The view names, one per pose; images are matched by name when given, else \
                 image id k + 1 is poses[k].",
            )
            .optional(),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "Registration, rotation, centre and reprojection errors (see the documentation).",
        )]
    }

    fn new(_params: ReconstructionErrorParams) -> Result<Self, String> {
        Ok(ReconstructionError)
    }
}

fn list<'a>(inputs: &Inputs<'a>, port: &str) -> Result<Option<&'a [Value]>, OpError> {
    match inputs.get(port) {
        None => Ok(None),
        Some(Value::List(l)) => Ok(Some(&l.items)),
        Some(other) => Err(OpError::input(
            port,
            format!("expected a list, got {}", other.port_type()),
        )),
    }
}

/// The required `reconstruction` input.
pub(crate) fn reconstruction_input<'a>(
    inputs: &Inputs<'a>,
) -> Result<&'a std::sync::Arc<Reconstruction>, OpError> {
    match inputs.require("reconstruction")? {
        Value::Reconstruction(r) => Ok(r),
        other => Err(OpError::input(
            "reconstruction",
            format!("expected Reconstruction, got {}", other.port_type()),
        )),
    }
}

/// The `poses` (required) and `names` (optional) inputs of the operators that compare a
/// reconstruction with the truth.
pub(crate) fn truth_inputs(
    inputs: &Inputs<'_>,
) -> Result<(Vec<Pose>, Option<Vec<String>>), OpError> {
    let poses = list(inputs, "poses")?
        .ok_or_else(|| OpError::input("poses", "not connected"))?
        .iter()
        .map(|v| match v {
            Value::Pose(p) => Ok(*p),
            other => Err(OpError::input(
                "poses",
                format!("expected Pose elements, got {}", other.port_type()),
            )),
        })
        .collect::<Result<Vec<_>, _>>()?;
    let names = list(inputs, "names")?
        .map(|items| {
            items
                .iter()
                .map(|v| match v {
                    Value::Text(t) => Ok(t.to_string()),
                    other => Err(OpError::input(
                        "names",
                        format!("expected Text elements, got {}", other.port_type()),
                    )),
                })
                .collect::<Result<Vec<_>, _>>()
        })
        .transpose()?;
    Ok((poses, names))
}

impl Operator for ReconstructionError {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let reconstruction = reconstruction_input(inputs)?;
        let (poses, names) = truth_inputs(inputs)?;
        let report = reconstruction_error(reconstruction, &poses, names.as_deref())
            .map_err(OpError::failed)?;
        Ok(Outputs::new().with("metrics", Value::metrics(report.metrics())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use ocellus_engine::value::{Camera, CameraModel, ReconImage, ReconPoint};
    use std::collections::BTreeMap;
    use std::sync::Arc;

    fn pose(r: &Matrix3<f64>, centre: &Vector3<f64>) -> Pose {
        let t = -(r * centre);
        let rm: [f64; 9] = std::array::from_fn(|k| r[(k / 3, k % 3)]);
        Pose::from_rotation_matrix(&rm, t.into())
    }

    /// Six true views on a ring around the origin (varying height), each looking at the
    /// origin.
    fn truth() -> Vec<(Matrix3<f64>, Vector3<f64>)> {
        (0..6)
            .map(|k| {
                let a = k as f64 * std::f64::consts::PI / 3.0;
                let centre = Vector3::new(4.0 * a.cos(), 4.0 * a.sin(), 0.5 * (k % 3) as f64);
                let z = (-centre).normalize();
                let x = z.cross(&Vector3::z()).normalize();
                let y = z.cross(&x);
                (
                    Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]),
                    centre,
                )
            })
            .collect()
    }

    /// The known gauge: world_true = S·Q·world_est + C.
    const S: f64 = 2.5;
    fn q() -> Matrix3<f64> {
        *Rotation3::from_scaled_axis(Vector3::new(0.3, -0.7, 1.1)).matrix()
    }
    fn c() -> Vector3<f64> {
        Vector3::new(1.0, -2.0, 3.0)
    }

    fn to_est(x_true: &Vector3<f64>) -> Vector3<f64> {
        q().transpose() * (x_true - c()) / S
    }

    /// The truth seen through the gauge, one PINHOLE camera, points observed exactly.
    fn reconstruction() -> Reconstruction {
        let mut cameras = BTreeMap::new();
        cameras.insert(
            3,
            Camera {
                model: CameraModel::Pinhole,
                width: 640,
                height: 480,
                params: vec![500.0, 520.0, 320.0, 240.0],
            },
        );
        let world: Vec<Vector3<f64>> = (0..5)
            .map(|j| Vector3::new(0.3 * j as f64 - 0.6, 0.2 * (j % 2) as f64, 0.1 * j as f64))
            .collect();
        let mut images = Vec::new();
        let mut tracks = vec![Vec::new(); world.len()];
        for (k, (r, centre)) in truth().iter().enumerate() {
            let camera_from_world = pose(&(r * q()), &to_est(centre));
            let rm = Matrix3::from_row_slice(&camera_from_world.rotation_matrix());
            let t = Vector3::from(camera_from_world.translation);
            let mut points2d = Vec::new();
            for (j, x) in world.iter().enumerate() {
                let p = rm * to_est(x) + t;
                if p.z > 0.0 {
                    tracks[j].push((k as u32 + 1, points2d.len() as u32));
                    points2d.push((
                        [500.0 * p.x / p.z + 320.0, 520.0 * p.y / p.z + 240.0],
                        Some(j as u64),
                    ));
                }
            }
            images.push(ReconImage {
                id: k as u32 + 1,
                camera_id: 3,
                name: format!("v{k}.png"),
                camera_from_world,
                points2d,
            });
        }
        let points = world
            .iter()
            .zip(tracks)
            .enumerate()
            .map(|(j, (x, track))| ReconPoint {
                id: j as u64,
                position: to_est(x).into(),
                color: [0, 0, 0],
                error_px: 0.0,
                track,
            })
            .collect();
        Reconstruction {
            cameras,
            images,
            points,
        }
    }

    fn true_poses() -> Vec<Pose> {
        truth().iter().map(|(r, c)| pose(r, c)).collect()
    }

    #[test]
    fn a_similar_reconstruction_has_no_error() {
        let rec = reconstruction();
        let report = reconstruction_error(&rec, &true_poses(), None).unwrap();
        assert_eq!((report.views, report.registered), (6, 6));
        assert!((report.scale - S).abs() < 1e-9, "{}", report.scale);
        for &(_, rot, centre) in &report.per_view {
            assert!(rot <= 1e-9 && centre <= 1e-9, "{rot} {centre}");
        }
        assert_eq!(report.observations, 30);
        assert_eq!(report.unprojectable, 0);
        assert!(report.reprojection_rms_px < 1e-9);
        // Bounding box of the ring: x in [−4, 4], y in ±4·sin 60°, z in [0, 1].
        let h = 4.0 * (std::f64::consts::PI / 3.0).sin();
        let expected = (64.0 + 4.0 * h * h + 1.0f64).sqrt();
        assert!((report.scene_size - expected).abs() < 1e-12);
        let m = report.metrics();
        assert_eq!(m["registered_fraction"], 1.0);
        assert_eq!(m["points"], 5.0);
    }

    #[test]
    fn one_degree_off_is_reported() {
        let mut rec = reconstruction();
        // Turn camera 2 by 1° about its own axis, keeping its centre.
        let image = &mut rec.images[2];
        let (r, centre) = rotation_and_centre(&image.camera_from_world);
        let turn = *Rotation3::from_scaled_axis(Vector3::new(0.0, 1f64.to_radians(), 0.0)).matrix();
        image.camera_from_world = pose(&(turn * r), &centre);
        let m = reconstruction_error(&rec, &true_poses(), None)
            .unwrap()
            .metrics();
        assert!((m["rotation_error_max_deg"] - 1.0).abs() < 1e-9, "{m:?}");
        assert!(m["rotation_error_median_deg"] < 1e-9, "{m:?}");
        assert!(m["center_error_max"] < 1e-9, "{m:?}");
        // The observations no longer match camera 2: the reprojection error grows.
        assert!(m["reprojection_rms_px"] > 1.0, "{m:?}");
    }

    #[test]
    fn reprojection_rms_by_hand() {
        let mut rec = reconstruction();
        let n = reprojection_rms(&rec).unwrap().1;
        rec.images[0].points2d[0].0[0] += 3.0;
        rec.images[0].points2d[0].0[1] -= 4.0;
        let (rms, total, failed) = reprojection_rms(&rec).unwrap();
        assert_eq!((total, failed), (n, 0));
        assert!((rms - (25.0 / n as f64).sqrt()).abs() < 1e-9, "{rms}");
    }

    #[test]
    fn images_are_matched_by_name() {
        let mut rec = reconstruction();
        // New ids, reversed order, one name with a folder; drop view 4.
        rec.images.reverse();
        for (i, image) in rec.images.iter_mut().enumerate() {
            image.id = 100 + i as u32;
        }
        rec.images[0].name = "images/v5.png".into();
        rec.images.retain(|i| i.name != "v4.png");
        rec.points.clear();
        let names: Vec<String> = (0..6).map(|k| format!("v{k}.png")).collect();
        let report = reconstruction_error(&rec, &true_poses(), Some(&names)).unwrap();
        assert_eq!((report.views, report.registered), (6, 5));
        assert_eq!(
            report.per_view.iter().map(|v| v.0).collect::<Vec<_>>(),
            [0, 1, 2, 3, 5]
        );
        assert!(report.per_view.iter().all(|v| v.1 < 1e-9 && v.2 < 1e-9));
        assert!((report.metrics()["registered_fraction"] - 5.0 / 6.0).abs() < 1e-15);
        // Ids no longer say the view.
        let err = reconstruction_error(&rec, &true_poses(), None).unwrap_err();
        assert!(err.contains("image id 100 has no view"), "{err}");
        rec.images[1].name = "other.png".into();
        let err = reconstruction_error(&rec, &true_poses(), Some(&names)).unwrap_err();
        assert!(err.contains("`other.png` matches no view"), "{err}");
        let err = reconstruction_error(&rec, &true_poses(), Some(&names[..5])).unwrap_err();
        assert!(err.contains("`names` has 5 entries but `poses` 6"), "{err}");
    }

    #[test]
    fn too_few_or_collinear_views_are_errors() {
        let mut rec = reconstruction();
        rec.images.truncate(2);
        rec.points.clear();
        let err = reconstruction_error(&rec, &true_poses(), None).unwrap_err();
        assert!(err.contains("2 registered views"), "{err}");
        let line: Vec<Pose> = (0..3)
            .map(|k| pose(&Matrix3::identity(), &Vector3::new(k as f64, 0.0, 0.0)))
            .collect();
        let rec = Reconstruction {
            images: line
                .iter()
                .enumerate()
                .map(|(k, p)| ReconImage {
                    id: k as u32 + 1,
                    camera_id: 1,
                    name: String::new(),
                    camera_from_world: *p,
                    points2d: Vec::new(),
                })
                .collect(),
            ..Reconstruction::default()
        };
        let err = reconstruction_error(&rec, &line, None).unwrap_err();
        assert!(err.contains("collinear"), "{err}");
        let mut dup = reconstruction();
        dup.images[1].id = 1;
        let err = reconstruction_error(&dup, &true_poses(), None).unwrap_err();
        assert!(err.contains("both match view 0"), "{err}");
    }

    #[test]
    fn op_reads_lists() {
        let rec = reconstruction();
        let specs = ReconstructionError::inputs();
        let poses = true_poses().into_iter().map(Value::Pose).collect();
        let values = [
            Some(Value::Reconstruction(Arc::new(rec))),
            Some(Value::list(PortType::Pose, poses)),
            None,
        ];
        let ctx = RunContext {
            node: "score".into(),
            threads: 1,
            element: None,
        };
        let mut out = ReconstructionError
            .run(&ctx, &Inputs::new(&specs, &values))
            .unwrap();
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("expected metrics");
        };
        assert_eq!(m["registered"], 6.0);
        assert!((m["scale"] - S).abs() < 1e-9);
    }
}
