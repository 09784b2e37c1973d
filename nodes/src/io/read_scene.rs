//! `io.read_scene`: a renderable [`Scene`] from a RON scene file — materials with textures,
//! meshes from OBJ/PLY files or generated, analytic shapes, lights and cameras.
//!
//! The file is read with the engine's span-keeping RON parser, so every error names
//! `file:line:col` and unknown fields or material names come with a suggestion.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::diag::suggest;
use ocellus_engine::image_io::{DecodeLimits, read_image};
use ocellus_engine::ron_syntax::{self, RonValue, Spanned};
use ocellus_engine::value::{
    Camera, CameraModel, Channels, Image, Light, Material, PixelData, Pose, Scene, SceneCamera,
    SceneObject, Shading, Shape, Texture, TextureFilter, TextureWrap,
};
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

use crate::render::primitives::{bumpy_icosphere, vertex_normals};
use crate::render::raycast::LookAtCamera;
use crate::render::scene::{quaternion_from_matrix, scene_camera_from_look_at};

ocellus_engine::params! {
    /// Parameters of [`ReadScene`].
    pub struct ReadSceneParams {
        /// The scene file (RON, format in the operator docs); relative paths resolve against
        /// the graph file's folder, paths inside it against the scene file's folder. Required.
        path: PathBuf = PathBuf::new(),
    }
}

/// A scene file and the files it names, read.
#[derive(Debug)]
pub struct LoadedScene {
    /// The scene.
    pub scene: Scene,
    /// Every mesh and image file the scene read, in reading order (for cache keys).
    pub files: Vec<PathBuf>,
}

/// Where a problem is: the file and a byte offset in it.
struct Ctx<'a> {
    path: &'a Path,
    src: &'a str,
    dir: PathBuf,
    files: Vec<PathBuf>,
}

type V<'s> = &'s Spanned<RonValue>;

impl Ctx<'_> {
    fn err(&self, at: &Spanned<RonValue>, message: impl std::fmt::Display) -> String {
        let (line, col) = ron_syntax::line_col(self.src, at.span.start);
        format!("{}:{line}:{col}: {message}", self.path.display())
    }

    /// The fields of a (possibly named) struct, checked against `allowed`.
    fn fields<'s>(
        &self,
        v: V<'s>,
        what: &str,
        allowed: &[&str],
    ) -> Result<BTreeMap<&'s str, V<'s>>, String> {
        let RonValue::Struct { fields, .. } = &v.value else {
            let empty = match &v.value {
                RonValue::Unit => true,
                RonValue::Tuple { items, .. } => items.is_empty(),
                _ => false,
            };
            if empty {
                return Ok(BTreeMap::new());
            }
            return Err(self.err(
                v,
                format!(
                    "{what} must be a struct `( … )`, found {}",
                    v.value.kind_name()
                ),
            ));
        };
        let mut out = BTreeMap::new();
        for (name, value) in fields {
            if !allowed.contains(&name.value.as_str()) {
                let hint = suggest(&name.value, allowed.iter().copied())
                    .map(|s| format!(" (did you mean `{s}`?)"))
                    .unwrap_or_else(|| format!(" (fields: {})", allowed.join(", ")));
                return Err(self.err(
                    value,
                    format!("unknown {what} field `{}`{hint}", name.value),
                ));
            }
            out.insert(name.value.as_str(), value);
        }
        Ok(out)
    }

    fn f64(&self, v: V<'_>, what: &str) -> Result<f64, String> {
        let x = match v.value {
            RonValue::Int(i) => i as f64,
            RonValue::Float(f) => f,
            _ => {
                return Err(self.err(
                    v,
                    format!("`{what}` must be a number, found {}", v.value.kind_name()),
                ));
            }
        };
        if x.is_nan() {
            return Err(self.err(v, format!("`{what}` is NaN")));
        }
        Ok(x)
    }

    fn finite(&self, v: V<'_>, what: &str) -> Result<f64, String> {
        let x = self.f64(v, what)?;
        if !x.is_finite() {
            return Err(self.err(v, format!("`{what}` must be finite")));
        }
        Ok(x)
    }

    fn vec<const N: usize>(&self, v: V<'_>, what: &str) -> Result<[f64; N], String> {
        let items = match &v.value {
            RonValue::Tuple { items, name: None } => items,
            RonValue::List(items) => items,
            _ => {
                return Err(self.err(
                    v,
                    format!(
                        "`{what}` must be {N} numbers `(…)`, found {}",
                        v.value.kind_name()
                    ),
                ));
            }
        };
        if items.len() != N {
            return Err(self.err(
                v,
                format!("`{what}` needs {N} numbers, found {}", items.len()),
            ));
        }
        let mut out = [0.0; N];
        for (o, item) in out.iter_mut().zip(items) {
            *o = self.finite(item, what)?;
        }
        Ok(out)
    }

    fn color(&self, v: V<'_>, what: &str) -> Result<[f32; 3], String> {
        let c = self.vec::<3>(v, what)?;
        if c.iter().any(|&x| x < 0.0) {
            return Err(self.err(v, format!("`{what}` must not be negative")));
        }
        Ok(c.map(|x| x as f32))
    }

    fn unit_range(&self, v: V<'_>, what: &str) -> Result<f32, String> {
        let x = self.finite(v, what)?;
        if !(0.0..=1.0).contains(&x) {
            return Err(self.err(v, format!("`{what}` must be in [0, 1], got {x}")));
        }
        Ok(x as f32)
    }

    fn uint(
        &self,
        v: V<'_>,
        what: &str,
        range: std::ops::RangeInclusive<i64>,
    ) -> Result<i64, String> {
        match v.value {
            RonValue::Int(i) if range.contains(&i) => Ok(i),
            RonValue::Int(i) => Err(self.err(
                v,
                format!(
                    "`{what}` must be {}..={}, got {i}",
                    range.start(),
                    range.end()
                ),
            )),
            _ => Err(self.err(
                v,
                format!("`{what}` must be an integer, found {}", v.value.kind_name()),
            )),
        }
    }

    fn string<'s>(&self, v: V<'s>, what: &str) -> Result<&'s str, String> {
        match &v.value {
            RonValue::Str(s) => Ok(s),
            _ => Err(self.err(
                v,
                format!("`{what}` must be a string, found {}", v.value.kind_name()),
            )),
        }
    }

    fn ident<'s>(&self, v: V<'s>, what: &str, allowed: &[&str]) -> Result<&'s str, String> {
        let s = match &v.value {
            RonValue::Ident(s) | RonValue::Str(s) => s.as_str(),
            _ => return Err(self.err(v, format!("`{what}` must be one of {}", allowed.join(", ")))),
        };
        if !allowed.contains(&s) {
            let hint = suggest(s, allowed.iter().copied())
                .map(|x| format!(" (did you mean `{x}`?)"))
                .unwrap_or_default();
            return Err(self.err(
                v,
                format!(
                    "`{what}` must be one of {}, got `{s}`{hint}",
                    allowed.join(", ")
                ),
            ));
        }
        Ok(s)
    }

    /// `Name(fields…)` → the name and the struct value.
    fn variant<'s>(&self, v: V<'s>, what: &str, allowed: &[&str]) -> Result<&'s str, String> {
        let name = match &v.value {
            RonValue::Struct { name: Some(n), .. } | RonValue::Tuple { name: Some(n), .. } => n,
            _ => {
                return Err(self.err(
                    v,
                    format!("{what} must be one of {}(…)", allowed.join("(…), ")),
                ));
            }
        };
        if !allowed.contains(&name.value.as_str()) {
            let hint = suggest(&name.value, allowed.iter().copied())
                .map(|x| format!(" (did you mean `{x}`?)"))
                .unwrap_or_default();
            return Err(self.err(v, format!("unknown {what} `{}`{hint}", name.value)));
        }
        Ok(name.value.as_str())
    }

    fn list<'s>(&self, v: V<'s>, what: &str) -> Result<&'s [Spanned<RonValue>], String> {
        match &v.value {
            RonValue::List(items) => Ok(items),
            _ => Err(self.err(
                v,
                format!(
                    "`{what}` must be a list `[…]`, found {}",
                    v.value.kind_name()
                ),
            )),
        }
    }

    fn option<'s>(&self, v: V<'s>) -> Option<V<'s>> {
        match &v.value {
            RonValue::Option(None) => None,
            RonValue::Option(Some(inner)) => Some(inner),
            _ => Some(v),
        }
    }

    fn file(&mut self, v: V<'_>, what: &str) -> Result<PathBuf, String> {
        let rel = self.string(v, what)?;
        if rel.is_empty() {
            return Err(self.err(v, format!("`{what}` is empty")));
        }
        let p = self.dir.join(rel);
        self.files.push(p.clone());
        Ok(p)
    }

    fn texture(&mut self, v: V<'_>, what: &str) -> Result<Option<Texture>, String> {
        let Some(v) = self.option(v) else {
            return Ok(None);
        };
        let f = self.fields(
            v,
            what,
            &[
                "image",
                "checker",
                "noise",
                "wrap",
                "filter",
                "border",
                "max_anisotropy",
                "uv_scale",
            ],
        )?;
        let image = match (f.get("image"), f.get("checker"), f.get("noise")) {
            (Some(p), None, None) => {
                let path = self.file(p, "image")?;
                read_image(&path, &DecodeLimits::default()).map_err(|e| self.err(p, e))?
            }
            (None, Some(c), None) => self.checker(c)?,
            (None, None, Some(c)) => self.noise(c)?,
            _ => {
                return Err(self.err(
                    v,
                    format!("{what} needs exactly one of `image`, `checker` or `noise`"),
                ));
            }
        };
        let wrap = match f.get("wrap") {
            None => TextureWrap::Repeat,
            Some(w) => match self.ident(
                w,
                "wrap",
                &[
                    "repeat",
                    "mirrored_repeat",
                    "clamp_to_edge",
                    "clamp_to_border",
                ],
            )? {
                "repeat" => TextureWrap::Repeat,
                "mirrored_repeat" => TextureWrap::MirroredRepeat,
                "clamp_to_edge" => TextureWrap::ClampToEdge,
                _ => TextureWrap::ClampToBorder,
            },
        };
        let filter = match f.get("filter") {
            None => TextureFilter::Trilinear,
            Some(w) => match self.ident(
                w,
                "filter",
                &["nearest", "bilinear", "trilinear", "anisotropic"],
            )? {
                "nearest" => TextureFilter::Nearest,
                "bilinear" => TextureFilter::Bilinear,
                "trilinear" => TextureFilter::Trilinear,
                _ => TextureFilter::Anisotropic,
            },
        };
        let border = match f.get("border") {
            None => [0.0, 0.0, 0.0, 1.0],
            Some(b) => self.vec::<4>(b, "border")?.map(|x| x as f32),
        };
        let max_anisotropy = match f.get("max_anisotropy") {
            None => 8,
            Some(m) => self.uint(m, "max_anisotropy", 1..=16)? as u32,
        };
        let uv_scale = match f.get("uv_scale") {
            None => [1.0, 1.0],
            Some(s) => self.vec::<2>(s, "uv_scale")?.map(|x| x as f32),
        };
        Ok(Some(Texture {
            image: Arc::new(image),
            wrap,
            filter,
            border,
            max_anisotropy,
            uv_scale,
        }))
    }

    /// A generated checkerboard: `cells × cells` squares over `size × size` RGB f32 texels,
    /// colour `a` where the top-left square is.
    fn checker(&self, v: V<'_>) -> Result<Image, String> {
        let f = self.fields(v, "checker", &["cells", "size", "a", "b"])?;
        let cells = f
            .get("cells")
            .map_or(Ok(8), |c| self.uint(c, "cells", 1..=4096))? as usize;
        let size = f
            .get("size")
            .map_or(Ok(256), |c| self.uint(c, "size", 1..=8192))? as usize;
        let a = f.get("a").map_or(Ok([0.9; 3]), |c| self.color(c, "a"))?;
        let b = f.get("b").map_or(Ok([0.1; 3]), |c| self.color(c, "b"))?;
        checker_image(size, cells.min(size), a, b).map_err(|e| self.err(v, e))
    }

    /// Generated value noise: `size × size` RGB f32 texels blending `a` and `b` by a sum of
    /// `octaves` lattice-noise layers, the first with `cells × cells` lattice cells, each next
    /// one at twice the frequency and half the amplitude; seeded by `seed`, tileable.
    fn noise(&self, v: V<'_>) -> Result<Image, String> {
        let f = self.fields(v, "noise", &["cells", "size", "octaves", "seed", "a", "b"])?;
        let cells = f
            .get("cells")
            .map_or(Ok(8), |c| self.uint(c, "cells", 1..=4096))? as usize;
        let size = f
            .get("size")
            .map_or(Ok(256), |c| self.uint(c, "size", 1..=8192))? as usize;
        let octaves = f
            .get("octaves")
            .map_or(Ok(4), |c| self.uint(c, "octaves", 1..=16))? as usize;
        let seed = f
            .get("seed")
            .map_or(Ok(0), |c| self.uint(c, "seed", 0..=i64::from(u32::MAX)))?
            as u64;
        let a = f.get("a").map_or(Ok([0.9; 3]), |c| self.color(c, "a"))?;
        let b = f.get("b").map_or(Ok([0.1; 3]), |c| self.color(c, "b"))?;
        noise_image(size, cells.min(size), octaves, seed, a, b).map_err(|e| self.err(v, e))
    }

    fn material(&mut self, v: V<'_>, index: usize) -> Result<Material, String> {
        let f = self.fields(
            v,
            "material",
            &[
                "name",
                "albedo",
                "albedo_texture",
                "normal_texture",
                "roughness",
                "roughness_texture",
                "metalness",
                "metalness_texture",
                "emission",
                "emission_texture",
                "specular",
                "shininess",
                "transmission",
                "ior",
                "opacity",
                "shading",
            ],
        )?;
        let d = Material::default();
        let name = match f.get("name") {
            Some(n) => self.string(n, "name")?.to_string(),
            None => format!("material{index}"),
        };
        let shading = match f.get("shading") {
            None => d.shading,
            Some(s) => match self.ident(
                s,
                "shading",
                &[
                    "unlit",
                    "flat",
                    "gouraud",
                    "lambert",
                    "phong",
                    "blinn_phong",
                    "pbr",
                ],
            )? {
                "unlit" => Shading::Unlit,
                "flat" => Shading::Flat,
                "gouraud" => Shading::Gouraud,
                "lambert" => Shading::Lambert,
                "phong" => Shading::Phong,
                "blinn_phong" => Shading::BlinnPhong,
                _ => Shading::Pbr,
            },
        };
        let tex = |ctx: &mut Self, key: &str| -> Result<Option<Texture>, String> {
            match f.get(key) {
                Some(t) => ctx.texture(t, key),
                None => Ok(None),
            }
        };
        let albedo_texture = tex(self, "albedo_texture")?;
        let normal_texture = tex(self, "normal_texture")?;
        let roughness_texture = tex(self, "roughness_texture")?;
        let metalness_texture = tex(self, "metalness_texture")?;
        let emission_texture = tex(self, "emission_texture")?;
        let shininess = f
            .get("shininess")
            .map_or(Ok(f64::from(d.shininess)), |x| self.finite(x, "shininess"))?;
        let ior = f
            .get("ior")
            .map_or(Ok(f64::from(d.ior)), |x| self.finite(x, "ior"))?;
        if shininess < 0.0 {
            return Err(self.err(v, "`shininess` must be ≥ 0"));
        }
        if ior < 1.0 {
            return Err(self.err(v, "`ior` must be ≥ 1"));
        }
        Ok(Material {
            name,
            albedo: f
                .get("albedo")
                .map_or(Ok(d.albedo), |x| self.color(x, "albedo"))?,
            albedo_texture,
            normal_texture,
            roughness: f
                .get("roughness")
                .map_or(Ok(d.roughness), |x| self.unit_range(x, "roughness"))?,
            roughness_texture,
            metalness: f
                .get("metalness")
                .map_or(Ok(d.metalness), |x| self.unit_range(x, "metalness"))?,
            metalness_texture,
            emission: f
                .get("emission")
                .map_or(Ok(d.emission), |x| self.color(x, "emission"))?,
            emission_texture,
            specular: f
                .get("specular")
                .map_or(Ok(d.specular), |x| self.unit_range(x, "specular"))?,
            shininess: shininess as f32,
            transmission: f
                .get("transmission")
                .map_or(Ok(d.transmission), |x| self.unit_range(x, "transmission"))?,
            ior: ior as f32,
            opacity: f
                .get("opacity")
                .map_or(Ok(d.opacity), |x| self.unit_range(x, "opacity"))?,
            shading,
        })
    }

    fn shape(&mut self, v: V<'_>) -> Result<Shape, String> {
        let kind = self.variant(
            v,
            "shape",
            &["Mesh", "Icosphere", "Sphere", "Plane", "Quadric"],
        )?;
        Ok(match kind {
            "Mesh" => {
                let f = self.fields(v, "Mesh", &["path"])?;
                let p = f
                    .get("path")
                    .ok_or_else(|| self.err(v, "`Mesh` needs a `path`"))?;
                let path = self.file(p, "path")?;
                let mesh = crate::io::read_mesh::read_mesh(&path).map_err(|e| self.err(p, e))?;
                Shape::Mesh(Arc::new(mesh))
            }
            "Icosphere" => {
                let f = self.fields(v, "Icosphere", &["subdivisions", "amplitude", "seed"])?;
                let subdiv = f
                    .get("subdivisions")
                    .map_or(Ok(3), |x| self.uint(x, "subdivisions", 0..=8))?
                    as u32;
                let amplitude = f
                    .get("amplitude")
                    .map_or(Ok(0.0), |x| self.finite(x, "amplitude"))?;
                if !(0.0..0.5).contains(&amplitude) {
                    return Err(self.err(v, "`amplitude` must be in [0, 0.5)"));
                }
                let seed = f
                    .get("seed")
                    .map_or(Ok(0), |x| self.uint(x, "seed", 0..=i64::MAX))?
                    as u64;
                let mut mesh = bumpy_icosphere(subdiv, amplitude as f32, seed);
                mesh.normals = Some(vertex_normals(&mesh.positions, &mesh.triangles));
                Shape::Mesh(Arc::new(mesh))
            }
            "Sphere" => {
                let f = self.fields(v, "Sphere", &["center", "radius"])?;
                let radius = f
                    .get("radius")
                    .map_or(Ok(1.0), |x| self.finite(x, "radius"))?;
                if radius <= 0.0 {
                    return Err(self.err(v, "`radius` must be > 0"));
                }
                Shape::Sphere {
                    center: f
                        .get("center")
                        .map_or(Ok([0.0; 3]), |x| self.vec(x, "center"))?,
                    radius,
                }
            }
            "Plane" => {
                let f = self.fields(v, "Plane", &["point", "normal", "half_extent"])?;
                let normal = f
                    .get("normal")
                    .map_or(Ok([0.0, 1.0, 0.0]), |x| self.vec(x, "normal"))?;
                if normal.iter().all(|&c| c == 0.0) {
                    return Err(self.err(v, "plane `normal` is zero"));
                }
                let half_extent = f
                    .get("half_extent")
                    .map_or(Ok(f64::INFINITY), |x| self.f64(x, "half_extent"))?;
                if half_extent <= 0.0 {
                    return Err(
                        self.err(v, "`half_extent` must be > 0 (inf for an infinite plane)")
                    );
                }
                Shape::Plane {
                    point: f
                        .get("point")
                        .map_or(Ok([0.0; 3]), |x| self.vec(x, "point"))?,
                    normal,
                    half_extent,
                }
            }
            _ => {
                let f = self.fields(v, "Quadric", &["coefficients", "min", "max"])?;
                let c = f
                    .get("coefficients")
                    .ok_or_else(|| self.err(v, "`Quadric` needs `coefficients`"))?;
                let min = f.get("min").map_or(Ok([-1.0; 3]), |x| self.vec(x, "min"))?;
                let max = f.get("max").map_or(Ok([1.0; 3]), |x| self.vec(x, "max"))?;
                if (0..3).any(|k| min[k] >= max[k]) {
                    return Err(self.err(v, "quadric box needs `min` < `max` on every axis"));
                }
                Shape::Quadric {
                    coefficients: self.vec(c, "coefficients")?,
                    min,
                    max,
                }
            }
        })
    }

    fn object(
        &mut self,
        v: V<'_>,
        index: usize,
        materials: &[Material],
    ) -> Result<SceneObject, String> {
        let f = self.fields(
            v,
            "object",
            &[
                "name",
                "shape",
                "material",
                "translation",
                "rotation_deg",
                "scale",
            ],
        )?;
        let name = match f.get("name") {
            Some(n) => self.string(n, "name")?.to_string(),
            None => format!("object{index}"),
        };
        let s = f
            .get("shape")
            .ok_or_else(|| self.err(v, format!("object `{name}` needs a `shape`")))?;
        let shape = self.shape(s)?;
        let material = match f.get("material") {
            None if materials.is_empty() => {
                return Err(self.err(
                    v,
                    format!("object `{name}` names no material and the scene has none"),
                ));
            }
            None => 0,
            Some(m) => {
                let want = self.string(m, "material")?;
                match materials.iter().position(|x| x.name == want) {
                    Some(i) => i as u32,
                    None => {
                        let hint = suggest(want, materials.iter().map(|x| x.name.as_str()))
                            .map(|s| format!(" (did you mean `{s}`?)"))
                            .unwrap_or_default();
                        return Err(self.err(m, format!("unknown material `{want}`{hint}")));
                    }
                }
            }
        };
        let translation = f
            .get("translation")
            .map_or(Ok([0.0; 3]), |x| self.vec(x, "translation"))?;
        let rotation_deg = f
            .get("rotation_deg")
            .map_or(Ok([0.0; 3]), |x| self.vec(x, "rotation_deg"))?;
        let scale = f
            .get("scale")
            .map_or(Ok(1.0), |x| self.finite(x, "scale"))?;
        if scale <= 0.0 {
            return Err(self.err(v, "`scale` must be > 0"));
        }
        Ok(SceneObject {
            name,
            shape,
            world_from_object: Pose {
                rotation: quaternion_from_matrix(&euler_xyz_deg(rotation_deg)),
                translation,
            },
            scale,
            material,
        })
    }

    fn light(&mut self, v: V<'_>) -> Result<Light, String> {
        let kind = self.variant(v, "light", &["Point", "Directional", "Area", "Environment"])?;
        Ok(match kind {
            "Point" => {
                let f = self.fields(v, "Point", &["position", "intensity"])?;
                Light::Point {
                    position: f
                        .get("position")
                        .map_or(Ok([0.0; 3]), |x| self.vec(x, "position"))?,
                    intensity: f
                        .get("intensity")
                        .map_or(Ok([1.0; 3]), |x| self.color(x, "intensity"))?,
                }
            }
            "Directional" => {
                let f = self.fields(v, "Directional", &["direction", "irradiance"])?;
                let d = f
                    .get("direction")
                    .map_or(Ok([0.0, -1.0, 0.0]), |x| self.vec(x, "direction"))?;
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if n == 0.0 {
                    return Err(self.err(v, "light `direction` is zero"));
                }
                Light::Directional {
                    direction: d.map(|c| c / n),
                    irradiance: f
                        .get("irradiance")
                        .map_or(Ok([1.0; 3]), |x| self.color(x, "irradiance"))?,
                }
            }
            "Area" => {
                let f = self.fields(v, "Area", &["corner", "edge_u", "edge_v", "radiance"])?;
                let need = |k: &str| {
                    f.get(k)
                        .ok_or_else(|| self.err(v, format!("`Area` needs `{k}`")))
                };
                let (eu, ev) = (
                    self.vec::<3>(need("edge_u")?, "edge_u")?,
                    self.vec::<3>(need("edge_v")?, "edge_v")?,
                );
                let c = [
                    eu[1] * ev[2] - eu[2] * ev[1],
                    eu[2] * ev[0] - eu[0] * ev[2],
                    eu[0] * ev[1] - eu[1] * ev[0],
                ];
                if c.iter().all(|&x| x == 0.0) {
                    return Err(self.err(v, "area light edges are parallel or zero"));
                }
                Light::Area {
                    corner: self.vec(need("corner")?, "corner")?,
                    edge_u: eu,
                    edge_v: ev,
                    radiance: f
                        .get("radiance")
                        .map_or(Ok([1.0; 3]), |x| self.color(x, "radiance"))?,
                }
            }
            _ => {
                let f = self.fields(v, "Environment", &["radiance", "map"])?;
                let map = match f.get("map") {
                    Some(m) => self.texture(m, "map")?,
                    None => None,
                };
                Light::Environment {
                    radiance: f
                        .get("radiance")
                        .map_or(Ok([1.0; 3]), |x| self.color(x, "radiance"))?,
                    map,
                }
            }
        })
    }

    fn camera(&self, v: V<'_>) -> Result<SceneCamera, String> {
        let f = self.fields(
            v,
            "camera",
            &[
                "width",
                "height",
                "fov_y_deg",
                "eye",
                "target",
                "up",
                "fx",
                "fy",
                "cx",
                "cy",
                "camera_from_world",
                "aperture_radius",
                "focus_distance",
            ],
        )?;
        let width = f
            .get("width")
            .map_or(Ok(640), |x| self.uint(x, "width", 1..=16_384))? as usize;
        let height = f
            .get("height")
            .map_or(Ok(480), |x| self.uint(x, "height", 1..=16_384))? as usize;
        let mut c = if f.contains_key("fx") || f.contains_key("camera_from_world") {
            for k in ["fov_y_deg", "eye", "target", "up"] {
                if let Some(x) = f.get(k) {
                    return Err(self.err(
                        x,
                        format!(
                            "`{k}` is for look-at cameras; this one gives `fx`/`camera_from_world`"
                        ),
                    ));
                }
            }
            let need = |k: &str| {
                f.get(k)
                    .ok_or_else(|| self.err(v, format!("an intrinsics camera needs `{k}`")))
            };
            let fx = self.finite(need("fx")?, "fx")?;
            let fy = f.get("fy").map_or(Ok(fx), |x| self.finite(x, "fy"))?;
            let cx = f
                .get("cx")
                .map_or(Ok(0.5 * (width as f64 - 1.0)), |x| self.finite(x, "cx"))?;
            let cy = f
                .get("cy")
                .map_or(Ok(0.5 * (height as f64 - 1.0)), |x| self.finite(x, "cy"))?;
            if fx <= 0.0 || fy <= 0.0 {
                return Err(self.err(v, "`fx` and `fy` must be > 0"));
            }
            let p = need("camera_from_world")?;
            let pf = self.fields(p, "camera_from_world", &["rotation", "translation"])?;
            let rotation = pf
                .get("rotation")
                .map_or(Ok([1.0, 0.0, 0.0, 0.0]), |x| self.vec::<4>(x, "rotation"))?;
            if rotation.iter().all(|&q| q == 0.0) {
                return Err(self.err(p, "`rotation` quaternion is zero"));
            }
            SceneCamera {
                camera: Camera {
                    model: CameraModel::Pinhole,
                    width: width as u32,
                    height: height as u32,
                    params: vec![fx, fy, cx, cy],
                },
                camera_from_world: Pose {
                    rotation,
                    translation: pf
                        .get("translation")
                        .map_or(Ok([0.0; 3]), |x| self.vec(x, "translation"))?,
                },
                aperture_radius: 0.0,
                focus_distance: 1.0,
            }
        } else {
            let fov = f
                .get("fov_y_deg")
                .map_or(Ok(45.0), |x| self.finite(x, "fov_y_deg"))?;
            let eye = f
                .get("eye")
                .map_or(Ok([0.0, 0.0, 5.0]), |x| self.vec(x, "eye"))?;
            let target = f
                .get("target")
                .map_or(Ok([0.0; 3]), |x| self.vec(x, "target"))?;
            let up = f
                .get("up")
                .map_or(Ok([0.0, 1.0, 0.0]), |x| self.vec(x, "up"))?;
            let la = LookAtCamera::new(width, height, fov, eye, target, up)
                .map_err(|e| self.err(v, e))?;
            scene_camera_from_look_at(&la)
        };
        if let Some(a) = f.get("aperture_radius") {
            c.aperture_radius = self.finite(a, "aperture_radius")?;
            if c.aperture_radius < 0.0 {
                return Err(self.err(a, "`aperture_radius` must be ≥ 0"));
            }
        }
        if let Some(d) = f.get("focus_distance") {
            c.focus_distance = self.finite(d, "focus_distance")?;
            if c.focus_distance <= 0.0 {
                return Err(self.err(d, "`focus_distance` must be > 0"));
            }
        }
        Ok(c)
    }
}

/// `size × size` RGB f32 checkerboard of `cells × cells` squares, `a` at the top-left.
pub fn checker_image(size: usize, cells: usize, a: [f32; 3], b: [f32; 3]) -> Result<Image, String> {
    let mut data = Vec::with_capacity(size * size * 3);
    for y in 0..size {
        for x in 0..size {
            let (cx, cy) = (x * cells / size, y * cells / size);
            data.extend_from_slice(if (cx + cy) % 2 == 0 { &a } else { &b });
        }
    }
    Image::new(size, size, Channels::Rgb, PixelData::F32(data)).map_err(|e| e.to_string())
}

/// A hash of lattice point `(x, y)` of octave `o` to [0, 1).
fn lattice_value(seed: u64, o: usize, x: usize, y: usize) -> f32 {
    // SplitMix64's finalizer, applied to the seed first so that different seeds give
    // unrelated lattices (not translates of one another), then to the seeded lattice point.
    let mix = |mut z: u64| {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let point = ((o as u64) << 48) ^ ((y as u64) << 24) ^ x as u64;
    let z = mix(mix(seed) ^ point);
    (z >> 40) as f32 / (1u64 << 24) as f32
}

/// `size × size` RGB f32 value noise (see the scene format's `noise` texture): octave `o` has
/// `cells·2ᵒ` lattice cells per side (capped at `size`), smoothstep-interpolated, amplitude
/// `2⁻ᵒ`; the sum is normalized to [0, 1] by its range and blends `a` (0) to `b` (1). The
/// lattice wraps, so the texture tiles.
pub fn noise_image(
    size: usize,
    cells: usize,
    octaves: usize,
    seed: u64,
    a: [f32; 3],
    b: [f32; 3],
) -> Result<Image, String> {
    if size == 0 || cells == 0 {
        return Err("noise needs size and cells ≥ 1".into());
    }
    let mut sum = vec![0f32; size * size];
    let mut amplitude = 1.0f32;
    for o in 0..octaves {
        let n = (cells << o.min(20)).min(size);
        for y in 0..size {
            let fy = (y as f32 + 0.5) * n as f32 / size as f32 - 0.5;
            let y0 = fy.floor();
            let ty = fy - y0;
            let ty = ty * ty * (3.0 - 2.0 * ty);
            let y0 = (y0 as i64).rem_euclid(n as i64) as usize;
            let y1 = (y0 + 1) % n;
            for x in 0..size {
                let fx = (x as f32 + 0.5) * n as f32 / size as f32 - 0.5;
                let x0 = fx.floor();
                let tx = fx - x0;
                let tx = tx * tx * (3.0 - 2.0 * tx);
                let x0 = (x0 as i64).rem_euclid(n as i64) as usize;
                let x1 = (x0 + 1) % n;
                let v = |xx, yy| lattice_value(seed, o, xx, yy);
                let top = v(x0, y0) * (1.0 - tx) + v(x1, y0) * tx;
                let bottom = v(x0, y1) * (1.0 - tx) + v(x1, y1) * tx;
                sum[y * size + x] += amplitude * (top * (1.0 - ty) + bottom * ty);
            }
        }
        amplitude *= 0.5;
    }
    let lo = sum.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = sum.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let range = if hi > lo { hi - lo } else { 1.0 };
    let mut data = Vec::with_capacity(size * size * 3);
    for s in sum {
        let t = (s - lo) / range;
        for c in 0..3 {
            data.push(a[c] + (b[c] - a[c]) * t);
        }
    }
    Image::new(size, size, Channels::Rgb, PixelData::F32(data)).map_err(|e| e.to_string())
}

/// The rotation `Rz·Ry·Rx` (about x first, then y, then z; fixed axes), row-major.
pub fn euler_xyz_deg(deg: [f64; 3]) -> [f64; 9] {
    let [a, b, c] = deg.map(f64::to_radians);
    let (sa, ca) = a.sin_cos();
    let (sb, cb) = b.sin_cos();
    let (sc, cc) = c.sin_cos();
    [
        cc * cb,
        cc * sb * sa - sc * ca,
        cc * sb * ca + sc * sa,
        sc * cb,
        sc * sb * sa + cc * ca,
        sc * sb * ca - cc * sa,
        -sb,
        cb * sa,
        cb * ca,
    ]
}

/// Parses a scene file's text; `path` names it in errors and its folder anchors relative paths.
pub fn parse_scene(src: &str, path: &Path) -> Result<LoadedScene, String> {
    let root = ron_syntax::parse(src).map_err(|e| {
        let (line, col) = ron_syntax::line_col(src, e.span.start);
        format!("{}:{line}:{col}: {e}", path.display())
    })?;
    let mut ctx = Ctx {
        path,
        src,
        dir: path.parent().map(Path::to_path_buf).unwrap_or_default(),
        files: Vec::new(),
    };
    let f = ctx.fields(
        &root,
        "scene",
        &["materials", "objects", "lights", "cameras"],
    )?;
    let mut scene = Scene::default();
    if let Some(m) = f.get("materials") {
        for (i, item) in ctx.list(m, "materials")?.iter().enumerate() {
            let mat = ctx.material(item, i)?;
            if scene.materials.iter().any(|x| x.name == mat.name) {
                return Err(ctx.err(item, format!("material `{}` is defined twice", mat.name)));
            }
            scene.materials.push(mat);
        }
    }
    if scene.materials.is_empty() {
        scene.materials.push(Material {
            name: "default".into(),
            ..Material::default()
        });
    }
    if let Some(o) = f.get("objects") {
        for (i, item) in ctx.list(o, "objects")?.iter().enumerate() {
            let obj = ctx.object(item, i, &scene.materials)?;
            scene.objects.push(obj);
        }
    }
    if let Some(l) = f.get("lights") {
        for item in ctx.list(l, "lights")? {
            let light = ctx.light(item)?;
            scene.lights.push(light);
        }
    }
    if let Some(c) = f.get("cameras") {
        for item in ctx.list(c, "cameras")? {
            scene.cameras.push(ctx.camera(item)?);
        }
    }
    if scene.cameras.is_empty() {
        return Err(format!("{}: the scene has no `cameras`", path.display()));
    }
    Ok(LoadedScene {
        scene,
        files: ctx.files,
    })
}

/// The files a scene source names (none if it does not parse), remembered per source text and
/// path: parsing builds the scene's procedural textures, which takes far longer than reading
/// the file, and an animation fingerprints its scene once per frame.
fn referenced_files(src: &str, path: &Path) -> Vec<PathBuf> {
    type Known = std::collections::HashMap<[u8; 32], Vec<PathBuf>>;
    static KNOWN: std::sync::OnceLock<std::sync::Mutex<Known>> = std::sync::OnceLock::new();
    let mut key_bytes = src.as_bytes().to_vec();
    key_bytes.extend_from_slice(path.as_os_str().as_encoded_bytes());
    let key = ocellus_engine::cache::content_hash(&key_bytes);
    let known = KNOWN.get_or_init(Default::default);
    if let Some(files) = known.lock().ok().and_then(|k| k.get(&key).cloned()) {
        return files;
    }
    // A scene that does not parse (yet: a file it names may be missing) is not remembered.
    let Ok(loaded) = parse_scene(src, path) else {
        return Vec::new();
    };
    if let Ok(mut k) = known.lock() {
        k.insert(key, loaded.files.clone());
    }
    loaded.files
}

/// Reads and parses a scene file.
pub fn read_scene(path: &Path) -> Result<LoadedScene, OpError> {
    let src = ocellus_engine::limits::read_text(path).map_err(|e| OpError::io(path, e))?;
    parse_scene(&src, path).map_err(OpError::failed)
}

/// `io.read_scene`. See [`parse_scene`].
pub struct ReadScene {
    params: ReadSceneParams,
}

impl Op for ReadScene {
    type Params = ReadSceneParams;
    const ID: &'static str = "io.read_scene";
    const SUMMARY: &'static str =
        "Read a renderable scene (materials, meshes, shapes, lights, cameras) from a RON file.";
    const DOC: &'static str = r#"
Reads a scene description (RON). Every field has a default; unknown fields are errors with a
suggestion, and errors name file:line:col. Paths inside the file resolve against its folder.

    (
        materials: [
            (name: "floor", albedo: (0.8, 0.8, 0.8), shading: blinn_phong, specular: 0.2,
             albedo_texture: Some((checker: (cells: 8, size: 256, a: (0.9, 0.9, 0.9),
                                  b: (0.2, 0.2, 0.2)), filter: trilinear, uv_scale: (0.25, 0.25)))),
            (name: "gold", albedo: (1.0, 0.78, 0.34), metalness: 1.0, roughness: 0.3, shading: pbr),
        ],
        objects: [
            (name: "ground", shape: Plane(point: (0, 0, 0), normal: (0, 1, 0), half_extent: 4.0),
             material: "floor"),
            (name: "blob", shape: Mesh(path: "bumpy_sphere.ply"), material: "gold",
             translation: (0, 1, 0), rotation_deg: (0, 30, 0), scale: 0.5),
            (name: "ball", shape: Sphere(center: (1.5, 0.5, 0), radius: 0.5)),
        ],
        lights: [
            Point(position: (2, 4, 3), intensity: (30, 30, 30)),
            Directional(direction: (-1, -2, -1), irradiance: (1, 1, 1)),
            Area(corner: (-1, 3, -1), edge_u: (2, 0, 0), edge_v: (0, 0, 2), radiance: (5, 5, 5)),
            Environment(radiance: (0.05, 0.05, 0.05)),
        ],
        cameras: [(width: 320, height: 240, fov_y_deg: 45, eye: (0, 2, 6), target: (0, 0.5, 0))],
    )

Materials: `albedo` (linear RGB), `roughness`, `metalness`, `specular`, `transmission`,
`opacity` in [0, 1]; `shininess` ≥ 0; `ior` ≥ 1; `emission` (radiance); `shading` one of
unlit, flat, gouraud, lambert (default), phong, blinn_phong, pbr; textures `albedo_texture`,
`normal_texture`, `roughness_texture`, `metalness_texture`, `emission_texture`, each
`(image: "file.png")` (read as linear values, no sRGB decoding) or a generated
`(checker: (cells, size, a, b))` or value noise `(noise: (cells, size, octaves, seed, a, b))`
(`octaves` layers of smoothly interpolated seeded lattice noise, the first with `cells` cells
per side, each next at twice the frequency and half the amplitude, blending `a` to `b`), with
`wrap` (repeat, mirrored_repeat, clamp_to_edge,
clamp_to_border), `filter` (nearest, bilinear, trilinear, anisotropic), `border` (RGBA),
`max_anisotropy` (1–16, default 8) and `uv_scale`. With no materials the scene gets one default
material, which objects without `material` use (otherwise they use the first).

Shapes: `Mesh(path)` (OBJ or PLY, as io.read_mesh), `Icosphere(subdivisions, amplitude, seed)`
(a generated unit icosphere with seeded radial bumps and smooth normals), `Sphere(center, radius)`,
`Plane(point, normal, half_extent)` (a square; `inf`, the default, is infinite),
`Quadric(coefficients, min, max)` (the upper triangle of the symmetric 4×4 Q, clipped to a box).
Objects are placed by `scale` (uniform), then `rotation_deg` (about x, then y, then z, fixed
axes), then `translation`.

Lights: Point (intensity, W/sr), Directional (unit direction of travel, irradiance),
Area (parallelogram corner + edges, emitting towards edge_u × edge_v), Environment (radiance,
optional equirectangular `map` texture).

Cameras: look-at (`width`, `height`, `fov_y_deg`, `eye`, `target`, `up`: as render.raycast) or
intrinsics (`fx`, `fy`, `cx`, `cy` with pixel centres at integers, `camera_from_world:
(rotation: (w, x, y, z), translation)`); both take `aperture_radius` (0: pinhole) and
`focus_distance` for a thin lens. At least one camera is required.

Example:
    "scene": (op: "io.read_scene", params: (path: "data/render_scene.ron")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "scene",
            PortType::Scene,
            "The scene: materials, objects, lights and cameras.",
        )]
    }

    fn new(params: ReadSceneParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        Ok(ReadScene { params })
    }
}

impl Operator for ReadScene {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let loaded = read_scene(&self.params.path)?;
        Ok(Outputs::new().with("scene", Value::Scene(Arc::new(loaded.scene))))
    }

    /// The scene file and every file it reads decide the result.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let path = &self.params.path;
        let src = ocellus_engine::limits::read_file(path).map_err(|e| OpError::io(path, e))?;
        let text = String::from_utf8_lossy(&src);
        let mut all = src.clone();
        // The files named inside; a scene that does not parse fails in `run` with its message.
        for f in &referenced_files(&text, path) {
            let bytes = ocellus_engine::limits::read_file(f).map_err(|e| OpError::io(f, e))?;
            all.extend_from_slice(&ocellus_engine::cache::content_hash(&bytes));
        }
        Ok(ocellus_engine::cache::content_hash(&all).to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(src: &str) -> Result<Scene, String> {
        parse_scene(src, Path::new("/nonexistent/scene.ron")).map(|l| l.scene)
    }

    #[test]
    fn a_full_scene_parses() {
        let s = parse(
            r#"(
            materials: [
                (name: "floor", albedo: (0.5, 0.5, 0.5), shading: blinn_phong, specular: 0.25,
                 albedo_texture: Some((checker: (cells: 4, size: 8), filter: nearest, wrap: clamp_to_edge, uv_scale: (2, 3)))),
                (name: "glass", transmission: 1.0, ior: 1.5, roughness: 0.0),
            ],
            objects: [
                (name: "ground", shape: Plane(normal: (0, 2, 0), half_extent: 4.0), material: "floor"),
                (name: "ball", shape: Sphere(center: (0, 1, 0), radius: 0.5), material: "glass",
                 translation: (1, 0, 0), rotation_deg: (0, 90, 0), scale: 2),
                (shape: Icosphere(subdivisions: 1)),
                (shape: Quadric(coefficients: [1, 0, 0, 0, 1, 0, 0, 1, 0, -1])),
            ],
            lights: [Point(position: (0, 3, 0), intensity: (10, 10, 10)), Directional(direction: (0, -2, 0)),
                     Area(corner: (0, 2, 0), edge_u: (1, 0, 0), edge_v: (0, 0, 1)), Environment(radiance: (0.1, 0.1, 0.1))],
            cameras: [(width: 32, height: 24, eye: (0, 1, 5)), (width: 8, height: 8, fx: 10, camera_from_world: (translation: (0, 0, 3)), aperture_radius: 0.1, focus_distance: 3)],
        )"#,
        )
        .unwrap();
        assert_eq!(s.materials.len(), 2);
        let t = s.materials[0].albedo_texture.as_ref().unwrap();
        assert_eq!(
            (t.image.width(), t.wrap, t.filter, t.uv_scale),
            (
                8,
                TextureWrap::ClampToEdge,
                TextureFilter::Nearest,
                [2.0, 3.0]
            )
        );
        assert_eq!(s.materials[1].transmission, 1.0);
        assert_eq!(s.objects.len(), 4);
        assert_eq!(s.objects[1].material, 1);
        assert_eq!(s.objects[2].material, 0);
        assert_eq!(s.objects[2].name, "object2");
        // rotation_deg (0, 90, 0) is a quarter turn about y.
        let r = s.objects[1].world_from_object.rotation_matrix();
        let x = [r[0], r[3], r[6]];
        assert!((x[0]).abs() < 1e-12 && (x[2] + 1.0).abs() < 1e-12, "{x:?}");
        assert_eq!(s.objects[1].scale, 2.0);
        match &s.objects[2].shape {
            Shape::Mesh(m) => assert_eq!(m.triangles.len(), 80),
            other => panic!("{other:?}"),
        }
        assert!(
            matches!(s.objects[0].shape, Shape::Plane { half_extent, .. } if half_extent == 4.0)
        );
        match s.lights[1] {
            Light::Directional { direction, .. } => assert_eq!(direction, [0.0, -1.0, 0.0]),
            _ => panic!(),
        }
        assert_eq!(s.cameras.len(), 2);
        assert_eq!(s.cameras[1].camera.params, vec![10.0, 10.0, 3.5, 3.5]);
        assert_eq!(s.cameras[1].aperture_radius, 0.1);
    }

    #[test]
    fn checker_colours_alternate_from_the_top_left() {
        let img = checker_image(4, 2, [1.0; 3], [0.0; 3]).unwrap();
        let PixelData::F32(d) = img.data() else {
            panic!()
        };
        let at = |x: usize, y: usize| d[(y * 4 + x) * 3];
        assert_eq!(
            (at(0, 0), at(1, 1), at(2, 0), at(2, 2), at(3, 1)),
            (1.0, 1.0, 0.0, 1.0, 0.0)
        );
    }

    #[test]
    fn noise_spans_both_colours_is_seeded_and_tiles() {
        let img = noise_image(64, 4, 3, 7, [0.0; 3], [1.0; 3]).unwrap();
        let PixelData::F32(d) = img.data() else {
            panic!()
        };
        let lo = d.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = d.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert_eq!((lo, hi), (0.0, 1.0));
        // Same seed, same texture; another seed, another texture.
        assert_eq!(img, noise_image(64, 4, 3, 7, [0.0; 3], [1.0; 3]).unwrap());
        assert_ne!(img, noise_image(64, 4, 3, 8, [0.0; 3], [1.0; 3]).unwrap());
        // Seeds are not lattice translates of each other: no shift of seed 8's texture by
        // whole lattice cells (16 texels) reproduces seed 7's.
        let other = noise_image(64, 4, 3, 8, [0.0; 3], [1.0; 3]).unwrap();
        let PixelData::F32(e) = other.data() else {
            panic!()
        };
        for (dx, dy) in [(16, 0), (0, 16), (48, 0), (16, 16)] {
            let same = (0..64 * 64).all(|i| {
                let (x, y) = (i % 64, i / 64);
                d[i * 3] == e[(((y + dy) % 64) * 64 + (x + dx) % 64) * 3]
            });
            assert!(!same, "seed 8 shifted by ({dx}, {dy}) equals seed 7");
        }
        // Tileable: the mean jump across the wrap (63 → 0, a mid-cell position of every
        // octave) is like the jumps at the other mid-cell positions of every octave (15 → 16,
        // 31 → 32, 47 → 48); a texture that did not tile would jump there like two unrelated
        // columns (0 and 32: mean jump ≈ 0.17 here, against ≤ 0.07 for these).
        let at = |x: usize, y: usize| d[(y * 64 + x) * 3];
        let jump =
            |a: usize, b: usize| (0..64).map(|y| (at(a, y) - at(b, y)).abs()).sum::<f32>() / 64.0;
        let same_phase = [15, 31, 47]
            .map(|x| jump(x, x + 1))
            .into_iter()
            .fold(0.0, f32::max);
        let (wrap, unrelated) = (jump(63, 0), jump(0, 32));
        assert!(
            wrap <= 2.5 * same_phase && 2.0 * wrap < unrelated,
            "wrap {wrap}, same-phase {same_phase}, unrelated {unrelated}"
        );
    }

    #[test]
    fn errors_name_line_and_column_with_suggestions() {
        let e =
            parse("(\n  objects: [(shape: Sphere(radius: 1), materal: \"x\")],\n cameras: [()])")
                .unwrap_err();
        assert!(
            e.contains("scene.ron:2:") && e.contains("did you mean `material`"),
            "{e}"
        );
        let e = parse("(materials: [(name: \"steel\")], objects: [(shape: Sphere(), material: \"stel\")], cameras: [()])").unwrap_err();
        assert!(
            e.contains("unknown material `stel`") && e.contains("`steel`"),
            "{e}"
        );
        let e = parse("(objects: [(shape: Spher())], cameras: [()])").unwrap_err();
        assert!(e.contains("did you mean `Sphere`"), "{e}");
        let e = parse("(cameras: [(width: 0)])").unwrap_err();
        assert!(e.contains("`width` must be 1..=16384"), "{e}");
        let e = parse("(objects: [], cameras: [])").unwrap_err();
        assert!(e.contains("no `cameras`"), "{e}");
        let e = parse("(cameras: [(eye: (0, 0, 0), target: (0, 0, 0))])").unwrap_err();
        assert!(e.contains("coincide"), "{e}");
        let e = parse("(objects: [(shape: Sphere(radius: NaN))], cameras: [()])").unwrap_err();
        assert!(e.contains("NaN"), "{e}");
        let e =
            parse("(objects: [(shape: Mesh(path: \"missing.ply\"))], cameras: [()])").unwrap_err();
        assert!(e.contains("missing.ply"), "{e}");
        let e = parse("(materials: [(roughness: 2)], cameras: [()])").unwrap_err();
        assert!(e.contains("[0, 1]"), "{e}");
        let e = parse(
            "(lights: [Area(corner: (0,0,0), edge_u: (1,0,0), edge_v: (2,0,0))], cameras: [()])",
        )
        .unwrap_err();
        assert!(e.contains("parallel"), "{e}");
        let e = parse("(cameras: [(").unwrap_err();
        assert!(e.contains("scene.ron:1:"), "{e}");
    }

    #[test]
    fn euler_angles_compose_in_xyz_order() {
        let r = euler_xyz_deg([90.0, 90.0, 0.0]);
        // x then y: the y axis goes to z (about x), then z goes to x (about y).
        let y = [r[1], r[4], r[7]];
        assert!(
            (y[0] - 1.0).abs() < 1e-12 && y[1].abs() < 1e-12 && y[2].abs() < 1e-12,
            "{y:?}"
        );
        let q = quaternion_from_matrix(&r);
        let back = Pose {
            rotation: q,
            translation: [0.0; 3],
        }
        .rotation_matrix();
        for k in 0..9 {
            assert!((back[k] - r[k]).abs() < 1e-12);
        }
    }
}
