//! `render.bvh` (acceleration structure over a mesh) and `render.raycast` (one primary ray per
//! pixel of a pinhole camera, nearest hit).

use std::sync::Arc;

use ocellus_engine::value::{Bvh, Channels, Image, PixelData};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};
use rayon::prelude::*;

use super::bvh::{BvhOptions, Ray, build_bvh, intersect};

ocellus_engine::params! {
    /// Parameters of [`BuildBvh`].
    pub struct BuildBvhParams {
        /// Centroid bins per axis in the SAH sweep, 2..=256. More bins find slightly better
        /// splits at a higher build cost. Default 16.
        bins: u32 = 16,
        /// Most triangles per leaf, 1..=64. Default 4.
        max_leaf_size: u32 = 4,
        /// Cost of visiting an inner node relative to one ray–triangle test, > 0; lower values
        /// build deeper trees with smaller leaves. Default 1.
        traversal_cost: f64 = 1.0,
    }
}

/// `render.bvh`: a binned-SAH bounding-volume hierarchy over a mesh's triangles. See
/// [`build_bvh`].
#[derive(Debug, Clone)]
pub struct BuildBvh {
    options: BvhOptions,
}

impl Op for BuildBvh {
    type Params = BuildBvhParams;
    const ID: &'static str = "render.bvh";
    const SUMMARY: &'static str =
        "Builds a bounding-volume hierarchy (binned SAH) over a triangle mesh for ray casting.";
    const DOC: &'static str = r#"
Builds a binary bounding-volume hierarchy over every triangle of `mesh` with the binned
surface-area heuristic (Wald 2007): at each node the triangle centroids are binned into `bins`
bins along each axis and the split minimizing `traversal_cost + (A_L·N_L + A_R·N_R)/A` (in
units of one triangle test) is taken, unless a leaf of at most `max_leaf_size` triangles is
cheaper. Nodes whose centroids all coincide are split by halves. Large subtrees are built in
parallel; the tree is the same for any thread count. Non-finite vertices and out-of-range
indices are errors; degenerate triangles are kept (rays never hit them).

Outputs `bvh` (the root, then sibling pairs; triangles in leaf order with their corners; the mesh).
`--emit` writes its shape: triangles, nodes, leaves, depth, largest leaf, root box.

Reference: Wald, "On fast construction of SAH-based bounding volume hierarchies" (IEEE RT
2007); Pharr, Jakob & Humphreys, "Physically Based Rendering" §4.3.

Example:
    "bvh": (op: "render.bvh", inputs: { "mesh": "mesh.mesh" }, params: (max_leaf_size: 4)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new("mesh", PortType::Mesh, "The triangle mesh.")]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "bvh",
            PortType::Bvh,
            "The hierarchy, with the mesh it was built over.",
        )]
    }

    fn new(p: BuildBvhParams) -> Result<Self, String> {
        let options = BvhOptions {
            bins: p.bins as usize,
            max_leaf_size: p.max_leaf_size as usize,
            traversal_cost: p.traversal_cost as f32,
        };
        options.validate()?;
        Ok(BuildBvh { options })
    }
}

impl Operator for BuildBvh {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = match inputs.require("mesh")? {
            Value::Mesh(m) => m.clone(),
            other => {
                return Err(OpError::input(
                    "mesh",
                    format!("expected Mesh, got {}", other.port_type()),
                ));
            }
        };
        let bvh =
            build_bvh(mesh, &self.options).map_err(|e| OpError::input("mesh", e.to_string()))?;
        Ok(Outputs::new().with("bvh", Value::Bvh(Arc::new(bvh))))
    }
}

ocellus_engine::params! {
    /// Parameters of [`Raycast`].
    pub struct RaycastParams {
        /// Image width, pixels, 1..=16384. Default 640.
        width: u32 = 640,
        /// Image height, pixels, 1..=16384. Default 480.
        height: u32 = 480,
        /// Vertical field of view, degrees, in (0, 180). Default 60.
        fov_y_deg: f64 = 60.0,
        /// Camera centre, world units. Default (0, 0, −3).
        eye: [f64; 3] = [0.0, 0.0, -3.0],
        /// Point the camera looks at. Default the origin.
        target: [f64; 3] = [0.0, 0.0, 0.0],
        /// World direction that appears up in the image (must not be parallel to the view
        /// direction). Default +y.
        up: [f64; 3] = [0.0, 1.0, 0.0],
    }
}

/// A pinhole camera looking from `eye` at `target`: image x runs along `right = f × up`
/// (normalized), image y down (along `−(right × f)`), square pixels, principal point at the
/// image centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LookAtCamera {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Camera centre.
    pub eye: [f64; 3],
    /// Unit view direction.
    pub forward: [f64; 3],
    /// Unit image-x direction.
    pub right: [f64; 3],
    /// Unit image-y direction (down in the image).
    pub down: [f64; 3],
}

fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn unit3(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    (n > 0.0 && n.is_finite()).then(|| [a[0] / n, a[1] / n, a[2] / n])
}

impl LookAtCamera {
    /// The camera, or why the parameters do not define one.
    pub fn new(
        width: usize,
        height: usize,
        fov_y_deg: f64,
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
    ) -> Result<LookAtCamera, String> {
        if !(1..=16_384).contains(&width) || !(1..=16_384).contains(&height) {
            return Err(format!(
                "`width` and `height` must be 1..=16384, got {width}×{height}"
            ));
        }
        if !(fov_y_deg > 0.0 && fov_y_deg < 180.0) {
            return Err(format!("`fov_y_deg` must be in (0, 180), got {fov_y_deg}"));
        }
        if !eye.iter().chain(&target).chain(&up).all(|v| v.is_finite()) {
            return Err("`eye`, `target` and `up` must be finite".into());
        }
        let forward = unit3(sub3(target, eye)).ok_or("`eye` and `target` coincide")?;
        let right = cross3(forward, up);
        let right = unit3(right)
            .filter(|_| {
                let n = (right[0] * right[0] + right[1] * right[1] + right[2] * right[2]).sqrt();
                let up_n = (up[0] * up[0] + up[1] * up[1] + up[2] * up[2]).sqrt();
                n > 1e-9 * up_n
            })
            .ok_or("`up` is zero or parallel to the view direction")?;
        let true_up = cross3(right, forward);
        let down = [-true_up[0], -true_up[1], -true_up[2]];
        let focal_px = 0.5 * height as f64 / (0.5 * fov_y_deg.to_radians()).tan();
        Ok(LookAtCamera {
            width,
            height,
            focal_px,
            eye,
            forward,
            right,
            down,
        })
    }

    /// The unit ray through the centre of pixel `(x, y)`.
    pub fn ray(&self, x: usize, y: usize) -> Ray {
        let px = (x as f64 + 0.5 - 0.5 * self.width as f64) / self.focal_px;
        let py = (y as f64 + 0.5 - 0.5 * self.height as f64) / self.focal_px;
        let d = [0, 1, 2].map(|k| self.forward[k] + px * self.right[k] + py * self.down[k]);
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        Ray {
            origin: self.eye.map(|v| v as f32),
            direction: d.map(|v| (v / n) as f32),
            t_min: 0.0,
            t_max: f32::INFINITY,
        }
    }
}

/// Side of the square pixel tiles traced as one work item (coherent rays share cache lines of
/// the hierarchy).
const TILE: usize = 16;

/// Distance along each pixel's unit ray to the nearest hit (`+∞` on a miss), row-major, and the
/// number of hits.
pub fn raycast_depth(bvh: &Bvh, camera: &LookAtCamera) -> (Vec<f32>, usize) {
    let (w, h) = (camera.width, camera.height);
    let tiles_x = w.div_ceil(TILE);
    let tiles = tiles_x * h.div_ceil(TILE);
    let traced: Vec<(Vec<f32>, usize)> = (0..tiles)
        .into_par_iter()
        .map(|tile| {
            let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
            let (x1, y1) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
            let mut depth = Vec::with_capacity((x1 - x0) * (y1 - y0));
            let mut hits = 0;
            for y in y0..y1 {
                for x in x0..x1 {
                    match intersect(bvh, &camera.ray(x, y)) {
                        Some(hit) => {
                            depth.push(hit.t);
                            hits += 1;
                        }
                        None => depth.push(f32::INFINITY),
                    }
                }
            }
            (depth, hits)
        })
        .collect();
    let mut depth = vec![f32::INFINITY; w * h];
    let mut hits = 0;
    for (tile, (values, n)) in traced.iter().enumerate() {
        let (x0, y0) = ((tile % tiles_x) * TILE, (tile / tiles_x) * TILE);
        let tw = (x0 + TILE).min(w) - x0;
        for (row, chunk) in values.chunks(tw).enumerate() {
            let start = (y0 + row) * w + x0;
            depth[start..start + tw].copy_from_slice(chunk);
        }
        hits += n;
    }
    (depth, hits)
}

/// `render.raycast`. See [`raycast_depth`].
#[derive(Debug, Clone)]
pub struct Raycast {
    camera: LookAtCamera,
}

impl Op for Raycast {
    type Params = RaycastParams;
    const ID: &'static str = "render.raycast";
    const SUMMARY: &'static str =
        "Casts one primary ray per pixel of a pinhole camera into a BVH: depth and hit count.";
    const DOC: &'static str = r#"
Casts one ray through the centre of every pixel of a pinhole camera at `eye` looking at
`target` with vertical field of view `fov_y_deg`, square pixels and the principal point at the
image centre. Image x runs to the right of the view direction (`forward × up`), image y down.
Each ray finds the nearest triangle (two-sided watertight intersection in f32, stack traversal
of the BVH nearest child first): rays through shared edges and vertices never slip through.

Outputs `depth`, a `width × height` f32 gray image of the distance from `eye` along each unit
ray to the nearest hit (`+∞` where the ray misses; along the ray, not the z depth), and `hits`
(Integer), the number of pixels that hit. Rows are traced in parallel; the result is the same
for any thread count.

Reference: Woop, Benthin & Wald, "Watertight ray/triangle intersection" (JCGT 2013);
Kay & Kajiya, "Ray tracing complex scenes" (SIGGRAPH 1986).

Example:
    "rays": (op: "render.raycast", inputs: { "bvh": "bvh.bvh" },
             params: (width: 640, height: 480, fov_y_deg: 40.0, eye: (0.0, 0.0, -3.0),
                      target: (0.0, 0.0, 0.0), up: (0.0, 1.0, 0.0))),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "bvh",
            PortType::Bvh,
            "The scene's hierarchy.",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "depth",
                PortType::Image,
                "f32 gray: distance along the unit ray to the nearest hit, +inf on a miss.",
            ),
            PortSpec::new("hits", PortType::Integer, "Pixels whose ray hit."),
        ]
    }

    fn new(p: RaycastParams) -> Result<Self, String> {
        let camera = LookAtCamera::new(
            p.width as usize,
            p.height as usize,
            p.fov_y_deg,
            p.eye,
            p.target,
            p.up,
        )?;
        Ok(Raycast { camera })
    }
}

impl Operator for Raycast {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let bvh = match inputs.require("bvh")? {
            Value::Bvh(b) => b,
            other => {
                return Err(OpError::input(
                    "bvh",
                    format!("expected Bvh, got {}", other.port_type()),
                ));
            }
        };
        let (depth, hits) = raycast_depth(bvh, &self.camera);
        let image = Image::new(
            self.camera.width,
            self.camera.height,
            Channels::Gray,
            PixelData::F32(depth),
        )
        .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("depth", Value::image(image))
            .with("hits", Value::Integer(hits as i64)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::primitives::bumpy_icosphere;
    use ocellus_engine::value::Mesh;

    #[test]
    fn camera_axes_follow_the_convention() {
        // Looking along +z with +y up: image x is forward × up = −x, image y is −y.
        let c = LookAtCamera::new(4, 2, 90.0, [0.0; 3], [0.0, 0.0, 5.0], [0.0, 1.0, 0.0]).unwrap();
        assert_eq!(c.forward, [0.0, 0.0, 1.0]);
        assert_eq!(c.right, [-1.0, 0.0, 0.0]);
        assert_eq!(c.down, [0.0, -1.0, 0.0]);
        assert!((c.focal_px - 1.0).abs() < 1e-12, "h/2 / tan(45°)");
        // The top-left pixel's ray points right-handed-left (+x) and up (+y).
        let r = c.ray(0, 0);
        assert!(r.direction[0] > 0.0 && r.direction[1] > 0.0 && r.direction[2] > 0.0);
        let n: f32 = r.direction.iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-6);
        for bad in [
            LookAtCamera::new(0, 2, 60.0, [0.0; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
            LookAtCamera::new(2, 2, 180.0, [0.0; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
            LookAtCamera::new(2, 2, 60.0, [0.0; 3], [0.0; 3], [0.0, 1.0, 0.0]),
            LookAtCamera::new(2, 2, 60.0, [0.0; 3], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0]),
            LookAtCamera::new(2, 2, 60.0, [f64::NAN; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
        ] {
            assert!(bad.is_err());
        }
    }

    #[test]
    fn depth_of_a_plane_is_the_analytic_distance() {
        // The plane z = 2 as two huge triangles, camera at the origin looking along +z: the
        // distance along pixel (x, y)'s unit ray is 2 / cos θ = 2 |d| / d_z.
        let s = 100.0;
        let mesh = Mesh {
            positions: vec![[-s, -s, 2.0], [s, -s, 2.0], [s, s, 2.0], [-s, s, 2.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            ..Mesh::default()
        };
        let bvh = build_bvh(Arc::new(mesh), &BvhOptions::default()).unwrap();
        let camera =
            LookAtCamera::new(33, 21, 70.0, [0.0; 3], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]).unwrap();
        let (depth, hits) = raycast_depth(&bvh, &camera);
        assert_eq!(hits, 33 * 21);
        for y in 0..21 {
            for x in 0..33 {
                let px = (x as f64 + 0.5 - 16.5) / camera.focal_px;
                let py = (y as f64 + 0.5 - 10.5) / camera.focal_px;
                let expected = 2.0 * (1.0 + px * px + py * py).sqrt();
                let got = f64::from(depth[y * 33 + x]);
                assert!(
                    (got - expected).abs() < 1e-5 * expected,
                    "({x},{y}) {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn sphere_silhouette_and_nearest_depth() {
        // Unit sphere from distance 3: the centre pixel is at distance 2 (±tessellation), the
        // hit fraction matches the sphere's angular radius, and corners miss (+inf).
        let mesh = bumpy_icosphere(5, 0.0, 1);
        let bvh = build_bvh(Arc::new(mesh), &BvhOptions::default()).unwrap();
        let (w, h) = (101, 101);
        let camera =
            LookAtCamera::new(w, h, 60.0, [0.0, 0.0, -3.0], [0.0; 3], [0.0, 1.0, 0.0]).unwrap();
        let (depth, hits) = raycast_depth(&bvh, &camera);
        let centre = depth[50 * w + 50];
        assert!((centre - 2.0).abs() < 2e-3, "{centre}");
        assert_eq!(depth[0], f32::INFINITY);
        // Angular radius asin(1/3); disc radius in pixels f · tan(asin(1/3)).
        let r_px = camera.focal_px * (1.0f64 / 3.0).asin().tan();
        let expected = std::f64::consts::PI * r_px * r_px;
        let rel = (hits as f64 - expected).abs() / expected;
        assert!(rel < 0.02, "hits {hits} vs disc area {expected:.0}");
        // Deterministic for any thread count.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| raycast_depth(&bvh, &camera));
        assert_eq!(one.0, depth);
        assert_eq!(one.1, hits);
    }
}
