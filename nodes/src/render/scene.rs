//! Scenes for the renderers: the pinhole/thin-lens view of a [`SceneCamera`], and the
//! conversion from the look-at parameters of `render.raycast`.

use ocellus_engine::value::{Camera, CameraModel, Distortion, Pose, SceneCamera};

use super::raycast::LookAtCamera;

/// A pinhole camera (optionally with a thin lens) ready for projecting and generating rays.
///
/// Conventions are the geometry family's: camera x right, y down, z forward;
/// `x_camera = R · x_world + t` from [`SceneCamera::camera_from_world`]; pixel centres at
/// integer coordinates, so pixel `(0, 0)` covers `[-0.5, 0.5]²`.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Focal lengths, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Skew (K[0][1]).
    pub skew: f64,
    /// Rotation of `camera_from_world`, row-major.
    pub rotation: [f64; 9],
    /// Translation of `camera_from_world`.
    pub translation: [f64; 3],
    /// Camera centre in world coordinates, `−Rᵀ t`.
    pub eye: [f64; 3],
    /// Thin-lens aperture radius, world units (0: pinhole).
    pub aperture_radius: f64,
    /// Focus distance along the optical axis, world units.
    pub focus_distance: f64,
}

impl View {
    /// The view of a scene camera, or why it cannot be rendered: non-finite or non-positive
    /// focal lengths, a size outside 1..=16384, lens distortion (renderers draw straight
    /// lines; undistorted cameras only) or a negative aperture.
    pub fn new(c: &SceneCamera) -> Result<View, String> {
        let cam = &c.camera;
        let (width, height) = (cam.width as usize, cam.height as usize);
        if !(1..=16_384).contains(&width) || !(1..=16_384).contains(&height) {
            return Err(format!(
                "camera size must be 1..=16384 on each side, got {width}×{height}"
            ));
        }
        let k = cam.intrinsics();
        let distorted = match cam.distortion() {
            Distortion::None => false,
            Distortion::RadialTangential(d) => d.iter().any(|&c| c != 0.0),
            // An equidistant fisheye bends rays even with zero coefficients.
            Distortion::Fisheye(_) => true,
        };
        if distorted {
            return Err(
                "the renderers take undistorted pinhole cameras; this camera has lens distortion"
                    .into(),
            );
        }
        let finite = [k.fx, k.fy, k.cx, k.cy, k.skew]
            .iter()
            .chain(&c.camera_from_world.rotation)
            .chain(&c.camera_from_world.translation)
            .all(|v| v.is_finite());
        let positive = k.fx > 0.0 && k.fy > 0.0;
        if !(finite && positive) {
            return Err(format!(
                "camera intrinsics and pose must be finite with fx, fy > 0 (fx {}, fy {})",
                k.fx, k.fy
            ));
        }
        if !(c.aperture_radius >= 0.0 && c.aperture_radius.is_finite()) {
            return Err(format!(
                "`aperture_radius` must be finite and ≥ 0, got {}",
                c.aperture_radius
            ));
        }
        if c.aperture_radius > 0.0 && !(c.focus_distance > 0.0 && c.focus_distance.is_finite()) {
            return Err(format!(
                "a thin lens needs a finite `focus_distance` > 0, got {}",
                c.focus_distance
            ));
        }
        let rotation = c.camera_from_world.rotation_matrix();
        let t = c.camera_from_world.translation;
        let eye = [0, 1, 2].map(|j| -(0..3).map(|i| rotation[3 * i + j] * t[i]).sum::<f64>());
        Ok(View {
            width,
            height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: k.skew,
            rotation,
            translation: t,
            eye,
            aperture_radius: c.aperture_radius,
            focus_distance: c.focus_distance,
        })
    }

    /// A world point in camera coordinates.
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        [0, 1, 2].map(|i| {
            r[3 * i] * p[0] + r[3 * i + 1] * p[1] + r[3 * i + 2] * p[2] + self.translation[i]
        })
    }

    /// A camera-frame direction in world coordinates (`Rᵀ d`).
    pub fn to_world_direction(&self, d: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        [0, 1, 2].map(|j| r[j] * d[0] + r[3 + j] * d[1] + r[6 + j] * d[2])
    }

    /// Pixel coordinates `(u, v)` and depth `z` of a world point; `None` when `z ≤ 0`.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 3]> {
        let [x, y, z] = self.to_camera(p);
        (z > 0.0).then(|| {
            let (a, b) = (x / z, y / z);
            [
                self.fx * a + self.skew * b + self.cx,
                self.fy * b + self.cy,
                z,
            ]
        })
    }

    /// The camera-frame direction (not normalized, z = 1) through pixel coordinates `(u, v)`.
    pub fn camera_direction(&self, u: f64, v: f64) -> [f64; 3] {
        let b = (v - self.cy) / self.fy;
        let a = (u - self.cx - self.skew * b) / self.fx;
        [a, b, 1.0]
    }

    /// The unit world-space ray direction through pixel coordinates `(u, v)` (pixel centres at
    /// integers), from [`View::eye`].
    pub fn ray_direction(&self, u: f64, v: f64) -> [f64; 3] {
        let d = self.to_world_direction(self.camera_direction(u, v));
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.map(|c| c / n)
    }

    /// A thin-lens ray through pixel coordinates `(u, v)` whose origin is the lens point
    /// `(lens_x, lens_y)` on the unit disk scaled by the aperture (Potmesil & Chakravarty 1981;
    /// pbrt's `PerspectiveCamera`): all rays through one pixel meet on the plane of focus.
    /// Returns origin and unit direction in world coordinates; with a zero aperture it is the
    /// pinhole ray.
    pub fn lens_ray(&self, u: f64, v: f64, lens: [f64; 2]) -> ([f64; 3], [f64; 3]) {
        let d = self.camera_direction(u, v);
        if self.aperture_radius == 0.0 {
            return (self.eye, self.ray_direction(u, v));
        }
        let focus = d.map(|c| c * self.focus_distance);
        let o = [
            lens[0] * self.aperture_radius,
            lens[1] * self.aperture_radius,
            0.0,
        ];
        let dc = [focus[0] - o[0], focus[1] - o[1], focus[2]];
        let ow = self.to_world_direction(o);
        let origin = [0, 1, 2].map(|k| self.eye[k] + ow[k]);
        let dw = self.to_world_direction(dc);
        let n = (dw[0] * dw[0] + dw[1] * dw[1] + dw[2] * dw[2]).sqrt();
        (origin, dw.map(|c| c / n))
    }
}

/// The scene camera equal to a look-at camera: same rays through every pixel centre
/// (`cx = (width − 1)/2` because pixel centres sit at integers here and at half-integers in
/// [`LookAtCamera::ray`]).
pub fn scene_camera_from_look_at(c: &LookAtCamera) -> SceneCamera {
    // Rows of R are the camera axes in world coordinates.
    let r = [
        c.right[0],
        c.right[1],
        c.right[2],
        c.down[0],
        c.down[1],
        c.down[2],
        c.forward[0],
        c.forward[1],
        c.forward[2],
    ];
    let t = [0, 1, 2].map(|i| -(0..3).map(|j| r[3 * i + j] * c.eye[j]).sum::<f64>());
    SceneCamera {
        camera: Camera {
            model: CameraModel::Pinhole,
            width: c.width as u32,
            height: c.height as u32,
            params: vec![
                c.focal_px,
                c.focal_px,
                0.5 * (c.width as f64 - 1.0),
                0.5 * (c.height as f64 - 1.0),
            ],
        },
        camera_from_world: Pose {
            rotation: quaternion_from_matrix(&r),
            translation: t,
        },
        aperture_radius: 0.0,
        focus_distance: 1.0,
    }
}

/// Unit quaternion `[w, x, y, z]` of a rotation matrix (Shepperd 1978: the largest diagonal
/// combination is the pivot, so it is stable for every rotation).
pub fn quaternion_from_matrix(r: &[f64; 9]) -> [f64; 4] {
    let (m00, m01, m02, m10, m11, m12, m20, m21, m22) =
        (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]);
    let trace = m00 + m11 + m22;
    let q = if trace > m00.max(m11).max(m22) {
        let s = 2.0 * (1.0 + trace).sqrt();
        [0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s]
    } else if m00 >= m11 && m00 >= m22 {
        let s = 2.0 * (1.0 + m00 - m11 - m22).sqrt();
        [(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s]
    } else if m11 >= m22 {
        let s = 2.0 * (1.0 + m11 - m00 - m22).sqrt();
        [(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s]
    } else {
        let s = 2.0 * (1.0 + m22 - m00 - m11).sqrt();
        [(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let q = q.map(|v| v / n);
    if q[0] < 0.0 { q.map(|v| -v) } else { q }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_and_scene_camera_give_the_same_rays() {
        let la = LookAtCamera::new(
            64,
            48,
            50.0,
            [1.0, 2.0, 3.0],
            [0.0, 0.5, -1.0],
            [0.0, 1.0, 0.0],
        )
        .expect("camera");
        let view = View::new(&scene_camera_from_look_at(&la)).expect("view");
        for (x, y) in [(0, 0), (63, 0), (17, 29), (63, 47)] {
            let a = la.ray(x, y);
            let b = view.ray_direction(x as f64, y as f64);
            for k in 0..3 {
                assert!((a.direction[k] as f64 - b[k]).abs() < 1e-6, "{x},{y}");
                assert!((view.eye[k] - [1.0, 2.0, 3.0][k]).abs() < 1e-12);
            }
        }
        // Projection inverts the ray.
        let p = [0.3, 0.4, -0.5];
        let [u, v, z] = view.project(p).expect("in front");
        let d = view.ray_direction(u, v);
        let dist = (0..3)
            .map(|k| (p[k] - view.eye[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        for k in 0..3 {
            assert!((view.eye[k] + dist * d[k] - p[k]).abs() < 1e-9);
        }
        assert!(z > 0.0);
    }

    #[test]
    fn thin_lens_rays_meet_on_the_focus_plane() {
        let la = LookAtCamera::new(32, 32, 60.0, [0.0, 0.0, 5.0], [0.0; 3], [0.0, 1.0, 0.0])
            .expect("camera");
        let mut c = scene_camera_from_look_at(&la);
        c.aperture_radius = 0.2;
        c.focus_distance = 4.0;
        let view = View::new(&c).expect("view");
        let meet = |lens: [f64; 2]| {
            let (o, d) = view.lens_ray(7.0, 20.0, lens);
            // Intersect with the plane z_world = 1 (camera z = 4).
            let s = (1.0 - o[2]) / d[2];
            [o[0] + s * d[0], o[1] + s * d[1]]
        };
        let a = meet([0.0, 0.0]);
        for lens in [[1.0, 0.0], [-0.5, 0.5], [0.0, -1.0]] {
            let b = meet(lens);
            assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
        }
    }

    #[test]
    fn distorted_cameras_and_bad_lenses_are_refused() {
        let la = LookAtCamera::new(8, 8, 60.0, [0.0, 0.0, 5.0], [0.0; 3], [0.0, 1.0, 0.0])
            .expect("camera");
        let mut c = scene_camera_from_look_at(&la);
        c.aperture_radius = -1.0;
        assert!(View::new(&c).is_err());
        c.aperture_radius = 0.0;
        c.camera.model = CameraModel::RadialTangential;
        c.camera.params = vec![10.0, 10.0, 4.0, 4.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0];
        assert!(View::new(&c).unwrap_err().contains("distortion"));
    }
}
