//! A small ray caster for two-view test fixtures with known geometry: textured rectangles
//! (walls, a floor, boxes) seen by pinhole cameras, rendered to 8-bit gray images.
//!
//! It exists to produce `graphs/data/two_view_*` (see [`two_view_fixture`]) and the ground truth
//! the two-view tests compare against; it is deliberately minimal and will be replaced by the
//! real renderer. Per pixel: 2×2 supersamples, each a ray from the camera centre; the nearest
//! rectangle hit is shaded with a procedural texture (two octaves of value noise with
//! smoothstep-bilinear interpolation, plus discs and squares on a jittered grid, giving
//! blob- and corner-like detail at several scales for feature detectors) times a Lambertian
//! factor for a fixed light direction. Rays that miss everything get a constant dark gray.
//! Everything is plain `f64` arithmetic in a fixed order, so a render is reproducible
//! bit for bit.

use nalgebra::{Matrix3, Rotation3, Vector3};
use ocellus_engine::value::{Camera, Channels, Image, PixelData};

use super::pose_util::Intrinsics;

/// A textured rectangle `origin + a·u + b·v`, `a, b ∈ [0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quad {
    /// One corner, world units.
    pub origin: Vector3<f64>,
    /// First edge (full length).
    pub u: Vector3<f64>,
    /// Second edge (full length).
    pub v: Vector3<f64>,
    /// Texture seed.
    pub seed: u64,
}

impl Quad {
    /// Unit normal `u × v / |u × v|`.
    pub fn normal(&self) -> Vector3<f64> {
        self.u.cross(&self.v).normalize()
    }

    /// Distance from `p` to the rectangle (world units).
    pub fn distance(&self, p: &Vector3<f64>) -> f64 {
        let d = p - self.origin;
        let a = (d.dot(&self.u) / self.u.norm_squared()).clamp(0.0, 1.0);
        let b = (d.dot(&self.v) / self.v.norm_squared()).clamp(0.0, 1.0);
        (self.origin + self.u * a + self.v * b - p).norm()
    }

    /// Ray parameter and texture coordinates (world units along `u`, `v`) of the hit of
    /// `o + s·d`, `s > 0`.
    fn hit(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, f64, f64)> {
        let n = self.u.cross(&self.v);
        let den = n.dot(d);
        if den.abs() < 1e-12 {
            return None;
        }
        let s = n.dot(&(self.origin - o)) / den;
        if s <= 1e-9 {
            return None;
        }
        let rel = o + d * s - self.origin;
        let (uu, vv) = (self.u.norm_squared(), self.v.norm_squared());
        let a = rel.dot(&self.u) / uu;
        let b = rel.dot(&self.v) / vv;
        if !(0.0..=1.0).contains(&a) || !(0.0..=1.0).contains(&b) {
            return None;
        }
        Some((s, a * uu.sqrt(), b * vv.sqrt()))
    }
}

/// The five visible faces (no bottom) of a box standing on the floor plane `y = floor_y`
/// (y points down), centred at `(cx, cz)` with half sizes `hx, hz`, height `h`, turned by
/// `yaw` radians about the vertical axis.
#[allow(clippy::too_many_arguments)]
pub fn box_faces(
    cx: f64,
    cz: f64,
    hx: f64,
    hz: f64,
    h: f64,
    floor_y: f64,
    yaw: f64,
    seed: u64,
) -> Vec<Quad> {
    let rot = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw);
    let ex = rot * Vector3::new(2.0 * hx, 0.0, 0.0);
    let ez = rot * Vector3::new(0.0, 0.0, 2.0 * hz);
    let up = Vector3::new(0.0, -h, 0.0);
    let c0 = Vector3::new(cx, floor_y, cz) - ex * 0.5 - ez * 0.5;
    vec![
        Quad {
            origin: c0,
            u: ex,
            v: up,
            seed,
        },
        Quad {
            origin: c0 + ez,
            u: ex,
            v: up,
            seed: seed + 1,
        },
        Quad {
            origin: c0,
            u: ez,
            v: up,
            seed: seed + 2,
        },
        Quad {
            origin: c0 + ex,
            u: ez,
            v: up,
            seed: seed + 3,
        },
        Quad {
            origin: c0 + up,
            u: ex,
            v: ez,
            seed: seed + 4,
        },
    ]
}

fn hash(x: i64, y: i64, seed: u64) -> u64 {
    let mut z = (x as u64)
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F))
        .wrapping_add(seed.wrapping_mul(0x1656_67B1_9E37_79F9));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn unit(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Value noise in [0, 1): lattice values at spacing `cell`, smoothstep-bilinear in between.
fn value_noise(a: f64, b: f64, cell: f64, seed: u64) -> f64 {
    let (x, y) = (a / cell, b / cell);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (i, j) = (x0 as i64, y0 as i64);
    let v = |di: i64, dj: i64| unit(hash(i + di, j + dj, seed));
    let top = v(0, 0) + (v(1, 0) - v(0, 0)) * sx;
    let bottom = v(0, 1) + (v(1, 1) - v(0, 1)) * sx;
    top + (bottom - top) * sy
}

/// Gray level in [0, 1] of the procedural texture at surface coordinates `(a, b)` (world
/// units).
pub fn texture(a: f64, b: f64, seed: u64) -> f64 {
    let mut g =
        0.25 + 0.4 * value_noise(a, b, 0.4, seed) + 0.25 * value_noise(a, b, 0.11, seed ^ 0x5555);
    // One shape per cell of a 0.3-unit grid: a disc or a square, sometimes none.
    let cell = 0.3;
    let (ci, cj) = ((a / cell).floor() as i64, (b / cell).floor() as i64);
    let h = hash(ci, cj, seed ^ 0xABCD);
    let kind = h & 3;
    if kind != 0 {
        let r = cell * (0.12 + 0.22 * unit(hash(ci, cj, seed ^ 0x1111)));
        let cx = (ci as f64 + 0.5) * cell + (cell * 0.5 - r) * (2.0 * unit(h) - 1.0);
        let cy = (cj as f64 + 0.5) * cell
            + (cell * 0.5 - r) * (2.0 * unit(hash(ci, cj, seed ^ 0x2222)) - 1.0);
        let (dx, dy) = (a - cx, b - cy);
        let inside = if kind == 1 {
            (dx.abs()).max(dy.abs()) <= r
        } else {
            dx * dx + dy * dy <= r * r
        };
        if inside {
            g = if (h >> 8) & 1 == 0 {
                0.05 + 0.15 * unit(h >> 3)
            } else {
                0.8 + 0.2 * unit(h >> 3)
            };
        }
    }
    g
}

/// A pinhole camera with its pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SyntheticCamera {
    /// Intrinsics.
    pub k: Intrinsics,
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Rotation camera_from_world.
    pub r: Matrix3<f64>,
    /// Translation camera_from_world.
    pub t: Vector3<f64>,
}

impl SyntheticCamera {
    /// Camera centre in world coordinates.
    pub fn center(&self) -> Vector3<f64> {
        -(self.r.transpose() * self.t)
    }

    /// The engine camera (no distortion).
    pub fn camera(&self) -> Camera {
        Camera {
            model: ocellus_engine::value::CameraModel::Pinhole,
            width: self.width as u32,
            height: self.height as u32,
            params: vec![self.k.fx, self.k.fy, self.k.cx, self.k.cy],
        }
    }
}

/// The nearest hit of a ray: `(ray parameter, quad index, a, b)`.
pub fn cast(quads: &[Quad], o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, usize, f64, f64)> {
    let mut best: Option<(f64, usize, f64, f64)> = None;
    for (i, q) in quads.iter().enumerate() {
        if let Some((s, a, b)) = q.hit(o, d)
            && best.is_none_or(|bst| s < bst.0)
        {
            best = Some((s, i, a, b));
        }
    }
    best
}

/// Renders `quads` seen by `cam` as an 8-bit gray image (2×2 supersampling, Lambertian shading
/// for the light direction `(−0.3, −1, −0.5)`, i.e. from above, left and behind the cameras).
pub fn render(quads: &[Quad], cam: &SyntheticCamera) -> Image {
    let light = Vector3::new(-0.3, -1.0, -0.5).normalize();
    let normals: Vec<Vector3<f64>> = quads.iter().map(Quad::normal).collect();
    let o = cam.center();
    let rt = cam.r.transpose();
    let mut data = Vec::with_capacity(cam.width * cam.height);
    for y in 0..cam.height {
        for x in 0..cam.width {
            let mut sum = 0.0;
            for (dx, dy) in [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)] {
                let px = x as f64 + dx;
                let py = y as f64 + dy;
                let dc = Vector3::new((px - cam.k.cx) / cam.k.fx, (py - cam.k.cy) / cam.k.fy, 1.0);
                let d = rt * dc;
                sum += match cast(quads, &o, &d) {
                    Some((_, i, a, b)) => {
                        let shade = 0.45 + 0.55 * normals[i].dot(&light).abs();
                        texture(a, b, quads[i].seed) * shade
                    }
                    None => 0.1,
                };
            }
            data.push((sum * 0.25 * 255.0).round().clamp(0.0, 255.0) as u8);
        }
    }
    // The size always matches the data.
    match Image::new(cam.width, cam.height, Channels::Gray, PixelData::U8(data)) {
        Ok(image) => image,
        Err(_) => unreachable!("image size matches its data"),
    }
}

/// The scene of the two-view fixture, in camera 1's frame (x right, y down, z forward): a back
/// wall at z = 9, side walls at x = −3.2 and x = 3.6, a floor at y = 1.6 and two boxes (one
/// turned by 30°) standing on it at depths 4.3–6.7.
pub fn two_view_scene() -> Vec<Quad> {
    let floor = 1.6;
    let top = -4.6;
    let mut quads = vec![
        Quad {
            origin: Vector3::new(-6.0, top, 9.0),
            u: Vector3::new(12.0, 0.0, 0.0),
            v: Vector3::new(0.0, floor - top, 0.0),
            seed: 1,
        },
        Quad {
            origin: Vector3::new(-3.2, top, 1.0),
            u: Vector3::new(0.0, 0.0, 8.0),
            v: Vector3::new(0.0, floor - top, 0.0),
            seed: 2,
        },
        Quad {
            origin: Vector3::new(3.6, top, 1.0),
            u: Vector3::new(0.0, 0.0, 8.0),
            v: Vector3::new(0.0, floor - top, 0.0),
            seed: 3,
        },
        Quad {
            origin: Vector3::new(-6.0, floor, 1.0),
            u: Vector3::new(12.0, 0.0, 0.0),
            v: Vector3::new(0.0, 0.0, 8.0),
            seed: 4,
        },
    ];
    quads.extend(box_faces(-0.9, 5.0, 0.7, 0.7, 1.4, floor, 0.0, 10));
    quads.extend(box_faces(1.3, 6.0, 0.5, 0.5, 2.0, floor, 0.52, 20));
    quads
}

/// The fixture's cameras: 640×480, f = 520 px, principal point (320, 240). Camera 1 is the
/// world frame; camera 2 sits 1 unit to the right (slightly up and forward) and is turned
/// 10° towards the scene about its vertical axis and 2° about its horizontal one.
pub fn two_view_cameras() -> (SyntheticCamera, SyntheticCamera) {
    let k = Intrinsics {
        fx: 520.0,
        fy: 520.0,
        cx: 320.0,
        cy: 240.0,
    };
    let c1 = SyntheticCamera {
        k,
        width: 640,
        height: 480,
        r: Matrix3::identity(),
        t: Vector3::zeros(),
    };
    // world_from_camera2 turns the optical axis towards −x (yaw) and slightly down (pitch).
    let yaw = Rotation3::from_axis_angle(&Vector3::y_axis(), -10f64.to_radians());
    let pitch = Rotation3::from_axis_angle(&Vector3::x_axis(), -2f64.to_radians());
    let world_from_cam2 = (yaw * pitch).into_inner();
    let r2 = world_from_cam2.transpose();
    let center2 = Vector3::new(1.0, -0.1, 0.2);
    let c2 = SyntheticCamera {
        r: r2,
        t: -(r2 * center2),
        ..c1
    };
    (c1, c2)
}

/// The two-view fixture: the left and right images of [`two_view_scene`] seen by
/// [`two_view_cameras`], and the camera (both views share it).
pub fn two_view_fixture() -> (Image, Image, Camera) {
    let scene = two_view_scene();
    let (c1, c2) = two_view_cameras();
    (render(&scene, &c1), render(&scene, &c2), c1.camera())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quads_hit_where_expected() {
        let q = Quad {
            origin: Vector3::new(-1.0, -1.0, 5.0),
            u: Vector3::new(2.0, 0.0, 0.0),
            v: Vector3::new(0.0, 2.0, 0.0),
            seed: 0,
        };
        let (s, a, b) = q
            .hit(&Vector3::zeros(), &Vector3::new(0.1, 0.0, 1.0))
            .unwrap();
        assert!((s - 5.0).abs() < 1e-12 && (a - 1.5).abs() < 1e-12 && (b - 1.0).abs() < 1e-12);
        assert!(
            q.hit(&Vector3::zeros(), &Vector3::new(1.0, 0.0, 1.0))
                .is_none()
        );
        assert!(
            q.hit(&Vector3::zeros(), &Vector3::new(0.0, 0.0, -1.0))
                .is_none()
        );
        assert!((q.distance(&Vector3::new(0.0, 0.0, 3.0)) - 2.0).abs() < 1e-12);
        assert!((q.distance(&Vector3::new(3.0, 0.0, 5.0)) - 2.0).abs() < 1e-12);
    }

    #[test]
    fn texture_has_contrast_and_is_deterministic() {
        let v: Vec<f64> = (0..400)
            .map(|i| texture(f64::from(i) * 0.013, f64::from(i % 17) * 0.07, 5))
            .collect();
        let (lo, hi) = v
            .iter()
            .fold((1.0f64, 0.0f64), |(l, h), x| (l.min(*x), h.max(*x)));
        assert!(lo < 0.25 && hi > 0.75, "{lo} {hi}");
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
        assert_eq!(texture(0.3, 0.7, 5), texture(0.3, 0.7, 5));
    }

    #[test]
    fn boxes_are_closed_and_cameras_see_the_scene() {
        let scene = two_view_scene();
        let (_, c2) = two_view_cameras();
        assert!((c2.center() - Vector3::new(1.0, -0.1, 0.2)).norm() < 1e-12);
        // The centre ray of camera 1 hits the first box's front face at z = 4.3.
        let hit = cast(
            &scene,
            &Vector3::zeros(),
            &Vector3::new(-0.9 / 4.3, 0.9 / 4.3, 1.0),
        );
        let (s, i, _, _) = hit.unwrap();
        assert_eq!(i, 4);
        assert!((s - 4.3).abs() < 1e-9);
        let small = SyntheticCamera {
            width: 32,
            height: 24,
            k: Intrinsics {
                fx: 26.0,
                fy: 26.0,
                cx: 16.0,
                cy: 12.0,
            },
            ..c2
        };
        let img = render(&scene, &small);
        let PixelData::U8(d) = img.data() else {
            panic!()
        };
        assert_eq!(d.len(), 32 * 24);
        assert!(d.iter().any(|&v| v > 100) && d.iter().any(|&v| v < 60));
    }
}
