//! `io.read_mesh`: read a triangle mesh from a Wavefront OBJ, PLY or STL file.
//!
//! **Wavefront OBJ** (the text geometry format of Wavefront Technologies' Advanced Visualizer),
//! read by [`parse_obj`]: `v x y z` (also `v x y z w`, `w` ignored, and `v x y z r g b` with an
//! sRGB-encoded color 0..1), `vt u [v [w]]`, `vn x y z`, and `f` faces whose corners are `v`,
//! `v/vt`, `v//vn` or `v/vt/vn`. Indices are 1-based, or negative: `-1` is the element defined
//! last before the face. `#` starts a comment; `o`, `g`, `s`, `usemtl`, `mtllib`, `l`, `p`,
//! `vp` and the other display/render statements are ignored; free-form geometry (`curv`,
//! `surf`, …) and unknown statements are errors.
//!
//! OBJ indexes positions, texture coordinates and normals separately, the [`Mesh`] per vertex.
//! Each distinct `(v, vt, vn)` corner becomes one output vertex, so a position used with two
//! different uvs (a texture seam) is split in two. Output vertices are ordered by position, and
//! the corners of one position by first appearance; when no position needs splitting, vertex
//! `i` is the file's `v` number `i + 1` and the triangles keep the file's indices. A position no
//! face uses is kept (with the attributes of its own index) when the faces use no attributes or
//! the file lists attributes per vertex (as many `vt`/`vn` as `v`, the layout the engine's
//! emitter writes), and dropped otherwise, since no face gives it attributes. A file without
//! faces gets uvs and normals when it lists exactly one per vertex. Either all face corners of a
//! file carry a `vt` (a `vn`) or none do.
//!
//! **PLY** (the Polygon File Format of Greg Turk, Stanford 1994), read by [`parse_ply`]: an
//! ASCII header (`ply`, `format ascii|binary_little_endian|binary_big_endian 1.0`, `comment`,
//! `obj_info`, `element NAME N`, `property TYPE NAME`, `property list CTYPE ITYPE NAME`,
//! `end_header`) then the elements in ASCII or binary. Every scalar type is accepted (`char`
//! `uchar` `short` `ushort` `int` `uint` `float` `double` and `int8` … `float64`). The
//! `vertex` element gives `x y z`, optionally `nx ny nz`, `u v` (or `s t`, `texture_u
//! texture_v`) and `red green blue`; the `face` element's `vertex_indices` (or `vertex_index`)
//! list gives the polygons. Vertex properties `tx ty tz tw` (all four; as the engine's writer
//! emits them) are read as tangents: `xyz` normalized (unless already unit to within 4 ulp, so
//! written tangents read back bit for bit), `w` reduced to its sign ±1 (0 is an error). Other
//! elements and properties, lists included, are skipped (`tx ty tz` without `tw` too).
//! Bytes after the last element of a binary file are ignored; an ASCII file may only have
//! whitespace there.
//!
//! **STL** (3D Systems' stereolithography format), read by [`parse_stl`], binary or ASCII. The
//! size decides first: a file of exactly `84 + 50·n` bytes, `n` the `u32` at byte 80, is binary
//! even when its 80-byte header starts with `solid` (many exporters write that). Otherwise a
//! file that starts with `solid` (after optional whitespace, any case) and holds no NUL byte is
//! ASCII, and anything else is a binary file whose size does not match its count: an error
//! ([`MeshError::Truncated`] when it is shorter, [`MeshError::StlSize`] when longer). ASCII:
//! `solid [name]`, then `facet normal nx ny nz` / `outer loop` / three `vertex x y z` /
//! `endloop` / `endfacet` per triangle, then `endsolid [name]` (keywords in any case; more
//! `solid` blocks may follow and are appended). STL stores every triangle's three corner
//! positions; the reader welds corners with bitwise-identical positions (`0.0` and `-0.0` stay
//! apart) into one vertex, numbered in order of first appearance, so the result is an indexed
//! mesh and the same file always gives the same mesh. Facet normals are parsed (ASCII: they must
//! be numbers) and then ignored: they are often zero or stale, and the triangle's corner order
//! already gives its orientation (compute vertex normals with `mesh.normals`). The binary
//! attribute byte count is ignored. Degenerate triangles are kept as the file has them.
//!
//! All formats: polygons are fan-triangulated (`a b c d` → `a b c`, `a c d`), keeping their
//! counter-clockwise order, and faces with fewer than 3 corners are errors; normals are
//! normalized (a zero normal is an error); positions, normals, uvs and colors must be finite
//! 32-bit floats. Colors: the engine's emitter writes linear mesh colors sRGB-encoded (floats
//! 0..1 in OBJ, bytes in PLY), so OBJ colors and integer PLY colors (divided by the type's
//! maximum, 255 for `uchar`) are decoded with the sRGB curve back to linear RGB;
//! `float`/`double` PLY colors are taken as linear.
//!
//! Limits against hostile files, each a typed [`MeshError`] naming the line (text) or byte
//! offset (binary PLY and STL): at most [`MAX_VERTICES`] vertices, [`MAX_FACES`] faces,
//! [`MAX_ELEMENT_RECORDS`] records of any other PLY element and [`MAX_TRIANGLES`] triangles,
//! [`MAX_LIST_LEN`] entries in any list or polygon, and no PLY element count larger than the
//! bytes after the header can hold (checked before anything is allocated); a binary STL's count
//! must match its size exactly, also checked before allocating.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ocellus_engine::value::Mesh;
use ocellus_engine::{
    Inputs, Op, OpError, Operator, Outputs, PortSpec, PortType, RunContext, Value,
};

/// Most vertices in a mesh file (PLY: declared; OBJ: `v`, `vt` or `vn` lines, and output
/// vertices after splitting).
pub const MAX_VERTICES: usize = 100_000_000;
/// Most faces declared in a PLY header.
pub const MAX_FACES: usize = 100_000_000;
/// Most records in any other PLY element.
pub const MAX_ELEMENT_RECORDS: usize = 100_000_000;
/// Most triangles after fan triangulation.
pub const MAX_TRIANGLES: usize = 100_000_000;
/// Most entries in a PLY list property and most corners of a polygon.
pub const MAX_LIST_LEN: usize = 1000;

/// Where in a mesh file a problem is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Location {
    /// A 1-based line: OBJ files, PLY headers and ASCII PLY bodies.
    Line(usize),
    /// A 0-based byte offset from the start of the file: binary PLY bodies and binary STL.
    Byte(usize),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line(n) => write!(f, "line {n}"),
            Location::Byte(n) => write!(f, "byte {n}"),
        }
    }
}

/// Errors reading a Wavefront OBJ or PLY mesh.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// The file name ends in none of `.obj`, `.ply`, `.stl`.
    #[error(
        "`{}`: unknown mesh format; the file name must end in .obj (Wavefront OBJ), .ply (PLY) \
         or .stl (STL)",
        path.display()
    )]
    UnknownExtension {
        /// The path.
        path: PathBuf,
    },
    /// A malformed statement, header line or record.
    #[error("{at}: {message}")]
    Syntax {
        /// Where.
        at: Location,
        /// What is wrong.
        message: String,
    },
    /// Well-formed content this reader does not handle (a PLY version or property type, OBJ
    /// free-form geometry).
    #[error("{at}: unsupported: {message}")]
    Unsupported {
        /// Where.
        at: Location,
        /// What.
        message: String,
    },
    /// A token that is not a number of the expected type.
    #[error("{at}: {what} `{token}` is not a valid {expected}")]
    BadNumber {
        /// Where.
        at: Location,
        /// Which value.
        what: String,
        /// The text found.
        token: String,
        /// The type expected.
        expected: &'static str,
    },
    /// NaN, an infinity, or a value beyond the `f32` range where a finite number is required.
    #[error("{at}: {what} is {value}, not a finite 32-bit float")]
    NonFinite {
        /// Where.
        at: Location,
        /// Which value.
        what: String,
        /// The value found.
        value: String,
    },
    /// An index past the elements defined (or 0 in OBJ).
    #[error("{at}: {what} {index} is out of range ({count} defined)")]
    IndexOutOfRange {
        /// Where.
        at: Location,
        /// Which index.
        what: String,
        /// The index as written.
        index: i64,
        /// How many elements it may refer to.
        count: usize,
    },
    /// Some vertices or face corners have an attribute that others lack.
    #[error("{at}: {message}")]
    MixedAttributes {
        /// Where.
        at: Location,
        /// What differs.
        message: String,
    },
    /// A normal of length 0.
    #[error("{at}: {what} has length 0")]
    ZeroNormal {
        /// Where.
        at: Location,
        /// Which normal.
        what: String,
    },
    /// More elements than a limit allows.
    #[error("{at}: {count} {what} exceed the limit of {limit}{}", limit_flag(*.limit))]
    TooMany {
        /// Where.
        at: Location,
        /// What is counted.
        what: &'static str,
        /// How many (at least).
        count: u64,
        /// The limit.
        limit: u64,
    },
    /// A PLY element count larger than the rest of the file could hold.
    #[error(
        "{at}: the header declares {count} `{element}` records, which need at least {needed} \
         bytes, but the file has {available} after the header"
    )]
    CountExceedsData {
        /// The element's header line.
        at: Location,
        /// The element.
        element: String,
        /// Its declared count.
        count: u64,
        /// Bytes needed by this and the earlier elements, at the least.
        needed: u64,
        /// Bytes after the header.
        available: u64,
    },
    /// A list or polygon longer than [`MAX_LIST_LEN`].
    #[error("{at}: a list of {len} entries is longer than the limit of {limit}")]
    ListTooLong {
        /// Where.
        at: Location,
        /// Its length.
        len: u64,
        /// The limit.
        limit: usize,
    },
    /// The file ends early.
    #[error("{at}: the file ends before {what}")]
    Truncated {
        /// Where the missing data should start.
        at: Location,
        /// What is missing.
        what: String,
    },
    /// A face with fewer than 3 corners.
    #[error("{at}: a face with {corners} corners (at least 3 are needed)")]
    DegenerateFace {
        /// Where.
        at: Location,
        /// Its corner count.
        corners: usize,
    },
    /// A binary STL longer than its triangle count says (shorter ones are
    /// [`MeshError::Truncated`]).
    #[error(
        "{at}: the binary STL header declares {count} triangles, which take 84 + 50 × {count} = \
         {expected} bytes, but the file has {actual}"
    )]
    StlSize {
        /// The count's offset (byte 80).
        at: Location,
        /// The declared triangle count.
        count: u64,
        /// The size that count implies.
        expected: u64,
        /// The file's size.
        actual: u64,
    },
}

impl MeshError {
    /// Where in the file the problem is (`None` for [`MeshError::UnknownExtension`]).
    pub fn location(&self) -> Option<Location> {
        match self {
            MeshError::UnknownExtension { .. } => None,
            MeshError::Syntax { at, .. }
            | MeshError::Unsupported { at, .. }
            | MeshError::BadNumber { at, .. }
            | MeshError::NonFinite { at, .. }
            | MeshError::IndexOutOfRange { at, .. }
            | MeshError::MixedAttributes { at, .. }
            | MeshError::ZeroNormal { at, .. }
            | MeshError::TooMany { at, .. }
            | MeshError::CountExceedsData { at, .. }
            | MeshError::ListTooLong { at, .. }
            | MeshError::Truncated { at, .. }
            | MeshError::DegenerateFace { at, .. }
            | MeshError::StlSize { at, .. } => Some(*at),
        }
    }
}

/// sRGB-encoded → linear, the inverse of the emitter's `linear_to_srgb` (same knee). Values
/// above 1 follow the power segment, values below 0 the linear one.
fn srgb_to_linear(s: f64) -> f64 {
    if s == 1.0 {
        1.0
    } else if s <= 12.92 * 0.003_130_8 {
        s / 12.92
    } else {
        ((s + 0.055) / 1.055).powf(2.4)
    }
}

/// The unit vector along `n`, or `None` for a zero vector.
fn normalize(n: [f32; 3]) -> Option<[f32; 3]> {
    let n = n.map(f64::from);
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    (len > 0.0 && len.is_finite()).then(|| n.map(|c| (c / len) as f32))
}

/// A tangent's unit direction: kept bit for bit when already unit to within 4 ulp (as written),
/// else normalized; `None` for a zero vector.
fn unit_tangent(t: [f32; 3]) -> Option<[f32; 3]> {
    let len = t.map(f64::from).iter().map(|c| c * c).sum::<f64>().sqrt();
    if (len - 1.0).abs() <= 4.0 * f64::from(f32::EPSILON) {
        Some(t)
    } else {
        normalize(t)
    }
}

/// Fan triangulation of one polygon (at least 3 corners).
fn fan(polygon: &[u32], triangles: &mut Vec<[u32; 3]>) {
    if let Some((&first, rest)) = polygon.split_first() {
        for pair in rest.windows(2) {
            triangles.push([first, pair[0], pair[1]]);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Wavefront OBJ.

/// Absent `vt`/`vn` in a corner.
const NONE: u32 = u32::MAX;

/// Statements that do not change the geometry.
const OBJ_IGNORED: &[&str] = &[
    "o",
    "g",
    "s",
    "usemtl",
    "mtllib",
    "l",
    "p",
    "vp",
    "mg",
    "usemap",
    "maplib",
    "lod",
    "bevel",
    "c_interp",
    "d_interp",
    "shadow_obj",
    "trace_obj",
    "ctech",
    "stech",
];

/// Free-form geometry statements.
const OBJ_FREE_FORM: &[&str] = &[
    "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim", "hole", "scrv", "sp",
    "end", "con",
];

/// One `f` statement: `len` corners from `start` in [`ObjReader::corners`].
struct Polygon {
    line: usize,
    start: usize,
    len: usize,
}

#[derive(Default)]
struct ObjReader {
    positions: Vec<[f32; 3]>,
    colors: Vec<[f32; 3]>,
    /// Line of the first `v` and whether it has a color.
    first_vertex: Option<(usize, bool)>,
    texcoords: Vec<[f32; 2]>,
    normals: Vec<[f32; 3]>,
    /// `(v, vt, vn)`, 0-based, `NONE` when absent.
    corners: Vec<[u32; 3]>,
    polygons: Vec<Polygon>,
    /// Line of the first corner and whether it has `vt` and `vn`.
    pattern: Option<(usize, bool, bool)>,
    triangles: usize,
}

/// The first `N` tokens and the total count.
fn args<'a, const N: usize>(tokens: impl Iterator<Item = &'a str>) -> ([&'a str; N], usize) {
    let mut out = [""; N];
    let mut n = 0;
    for t in tokens {
        if let Some(slot) = out.get_mut(n) {
            *slot = t;
        }
        n += 1;
    }
    (out, n)
}

fn obj_f32(token: &str, at: Location, what: &str) -> Result<f32, MeshError> {
    let v: f32 = token.parse().map_err(|_| MeshError::BadNumber {
        at,
        what: what.to_string(),
        token: token.to_string(),
        expected: "number",
    })?;
    if !v.is_finite() {
        return Err(MeshError::NonFinite {
            at,
            what: what.to_string(),
            value: token.to_string(),
        });
    }
    Ok(v)
}

/// A 1-based or negative OBJ index, 0-based. Positive indices are checked against the final
/// counts once the whole file is read (a face may name a later vertex).
fn obj_index(token: &str, defined: usize, at: Location, what: &str) -> Result<u32, MeshError> {
    let what = || format!("{what} index");
    let i: i64 = token.parse().map_err(|_| MeshError::BadNumber {
        at,
        what: what(),
        token: token.to_string(),
        expected: "integer index",
    })?;
    let out_of_range = || MeshError::IndexOutOfRange {
        at,
        what: what(),
        index: i,
        count: defined,
    };
    let k = if i > 0 {
        i - 1
    } else if i < 0 {
        defined as i64 + i
    } else {
        -1
    };
    if !(0..MAX_VERTICES as i64).contains(&k) {
        return Err(out_of_range());
    }
    Ok(k as u32)
}

impl ObjReader {
    fn statement(&mut self, raw: &str, line: usize) -> Result<(), MeshError> {
        let at = Location::Line(line);
        let content = raw.split('#').next().unwrap_or("");
        let mut tokens = content.split_whitespace();
        let Some(keyword) = tokens.next() else {
            return Ok(());
        };
        match keyword {
            "v" => self.vertex(tokens, line),
            "vt" => self.texcoord(tokens, at),
            "vn" => self.normal(tokens, at),
            "f" => self.face(tokens, line),
            k if OBJ_IGNORED.contains(&k) => Ok(()),
            k if OBJ_FREE_FORM.contains(&k) => Err(MeshError::Unsupported {
                at,
                message: format!("`{k}`: free-form curves and surfaces"),
            }),
            k => Err(MeshError::Syntax {
                at,
                message: format!("unknown statement `{k}`"),
            }),
        }
    }

    fn vertex<'a>(
        &mut self,
        tokens: impl Iterator<Item = &'a str>,
        line: usize,
    ) -> Result<(), MeshError> {
        let at = Location::Line(line);
        let (a, n) = args::<7>(tokens);
        let has_color = match n {
            3 | 4 => false,
            6 => true,
            _ => {
                return Err(MeshError::Syntax {
                    at,
                    message: format!(
                        "`v` takes `x y z`, `x y z w` or `x y z r g b`; found {n} values"
                    ),
                });
            }
        };
        if self.positions.len() >= MAX_VERTICES {
            return Err(MeshError::TooMany {
                at,
                what: "vertices",
                count: self.positions.len() as u64 + 1,
                limit: MAX_VERTICES as u64,
            });
        }
        match self.first_vertex {
            None => self.first_vertex = Some((line, has_color)),
            Some((first, c)) if c != has_color => {
                let (this, that) = if has_color {
                    ("has", "has none")
                } else {
                    ("has no", "has one")
                };
                return Err(MeshError::MixedAttributes {
                    at,
                    message: format!(
                        "this vertex {this} color, but the vertex on line {first} {that}"
                    ),
                });
            }
            Some(_) => {}
        }
        let p = [
            obj_f32(a[0], at, "x")?,
            obj_f32(a[1], at, "y")?,
            obj_f32(a[2], at, "z")?,
        ];
        if n == 4 {
            obj_f32(a[3], at, "w")?;
        }
        if has_color {
            let mut c = [0.0f32; 3];
            for (k, (dst, name)) in c.iter_mut().zip(["red", "green", "blue"]).enumerate() {
                *dst = srgb_to_linear(f64::from(obj_f32(a[3 + k], at, name)?)) as f32;
            }
            self.colors.push(c);
        }
        self.positions.push(p);
        Ok(())
    }

    fn texcoord<'a>(
        &mut self,
        tokens: impl Iterator<Item = &'a str>,
        at: Location,
    ) -> Result<(), MeshError> {
        let (a, n) = args::<3>(tokens);
        if !(1..=3).contains(&n) {
            return Err(MeshError::Syntax {
                at,
                message: format!("`vt` takes `u`, `u v` or `u v w`; found {n} values"),
            });
        }
        if self.texcoords.len() >= MAX_VERTICES {
            return Err(MeshError::TooMany {
                at,
                what: "texture coordinates",
                count: self.texcoords.len() as u64 + 1,
                limit: MAX_VERTICES as u64,
            });
        }
        let u = obj_f32(a[0], at, "u")?;
        let v = if n >= 2 { obj_f32(a[1], at, "v")? } else { 0.0 };
        if n == 3 {
            obj_f32(a[2], at, "w")?;
        }
        self.texcoords.push([u, v]);
        Ok(())
    }

    fn normal<'a>(
        &mut self,
        tokens: impl Iterator<Item = &'a str>,
        at: Location,
    ) -> Result<(), MeshError> {
        let (a, n) = args::<3>(tokens);
        if n != 3 {
            return Err(MeshError::Syntax {
                at,
                message: format!("`vn` takes `x y z`; found {n} values"),
            });
        }
        if self.normals.len() >= MAX_VERTICES {
            return Err(MeshError::TooMany {
                at,
                what: "normals",
                count: self.normals.len() as u64 + 1,
                limit: MAX_VERTICES as u64,
            });
        }
        let v = [
            obj_f32(a[0], at, "normal x")?,
            obj_f32(a[1], at, "normal y")?,
            obj_f32(a[2], at, "normal z")?,
        ];
        let unit = normalize(v).ok_or_else(|| MeshError::ZeroNormal {
            at,
            what: format!("normal {}", self.normals.len() + 1),
        })?;
        self.normals.push(unit);
        Ok(())
    }

    fn corner(&self, token: &str, at: Location) -> Result<[u32; 3], MeshError> {
        let mut parts = token.split('/');
        let v = parts.next().unwrap_or("");
        let vt = parts.next().unwrap_or("");
        let vn = parts.next().unwrap_or("");
        if parts.next().is_some() {
            return Err(MeshError::Syntax {
                at,
                message: format!("face corner `{token}` has more than 3 `/`-separated parts"),
            });
        }
        if v.is_empty() {
            return Err(MeshError::Syntax {
                at,
                message: format!("face corner `{token}` has no vertex index"),
            });
        }
        let v = obj_index(v, self.positions.len(), at, "vertex")?;
        let vt = if vt.is_empty() {
            NONE
        } else {
            obj_index(vt, self.texcoords.len(), at, "texture coordinate")?
        };
        let vn = if vn.is_empty() {
            NONE
        } else {
            obj_index(vn, self.normals.len(), at, "normal")?
        };
        Ok([v, vt, vn])
    }

    fn face<'a>(
        &mut self,
        tokens: impl Iterator<Item = &'a str> + Clone,
        line: usize,
    ) -> Result<(), MeshError> {
        let at = Location::Line(line);
        let n = tokens.clone().count();
        if n < 3 {
            return Err(MeshError::DegenerateFace { at, corners: n });
        }
        if n > MAX_LIST_LEN {
            return Err(MeshError::ListTooLong {
                at,
                len: n as u64,
                limit: MAX_LIST_LEN,
            });
        }
        if self.triangles + (n - 2) > MAX_TRIANGLES {
            return Err(MeshError::TooMany {
                at,
                what: "triangles",
                count: (self.triangles + n - 2) as u64,
                limit: MAX_TRIANGLES as u64,
            });
        }
        let start = self.corners.len();
        for token in tokens {
            let corner = self.corner(token, at)?;
            let (has_vt, has_vn) = (corner[1] != NONE, corner[2] != NONE);
            match self.pattern {
                None => self.pattern = Some((line, has_vt, has_vn)),
                Some((first, t0, n0)) if (t0, n0) != (has_vt, has_vn) => {
                    let form = |t: bool, n: bool| match (t, n) {
                        (false, false) => "`v`",
                        (true, false) => "`v/vt`",
                        (false, true) => "`v//vn`",
                        (true, true) => "`v/vt/vn`",
                    };
                    self.corners.truncate(start);
                    return Err(MeshError::MixedAttributes {
                        at,
                        message: format!(
                            "face corner `{token}` has the form {}, but the faces from line \
                             {first} on use {}; all corners must name the same attributes",
                            form(has_vt, has_vn),
                            form(t0, n0)
                        ),
                    });
                }
                Some(_) => {}
            }
            self.corners.push(corner);
        }
        self.triangles += n - 2;
        self.polygons.push(Polygon {
            line,
            start,
            len: n,
        });
        Ok(())
    }

    /// Checks the deferred positive indices and builds the per-vertex mesh.
    fn finish(self, lines: usize) -> Result<Mesh, MeshError> {
        let (nv, nt, nn) = (
            self.positions.len(),
            self.texcoords.len(),
            self.normals.len(),
        );
        for poly in &self.polygons {
            let at = Location::Line(poly.line);
            let corners = self
                .corners
                .get(poly.start..poly.start + poly.len)
                .unwrap_or(&[]);
            for c in corners {
                for (index, count, what) in [
                    (c[0], nv, "vertex index"),
                    (c[1], nt, "texture coordinate index"),
                    (c[2], nn, "normal index"),
                ] {
                    if index != NONE && index as usize >= count {
                        return Err(MeshError::IndexOutOfRange {
                            at,
                            what: what.to_string(),
                            index: i64::from(index) + 1,
                            count,
                        });
                    }
                }
            }
        }
        let colors = matches!(self.first_vertex, Some((_, true))).then_some(self.colors);
        let per_vertex = |n: usize| n == nv && nv > 0;
        if self.polygons.is_empty() {
            return Ok(Mesh {
                normals: per_vertex(nn).then_some(self.normals),
                uvs: per_vertex(nt).then_some(self.texcoords),
                positions: self.positions,
                triangles: Vec::new(),
                colors,
                tangents: None,
            });
        }
        let (uses_vt, uses_vn) = self.pattern.map_or((false, false), |(_, t, n)| (t, n));
        let mut triangles = Vec::with_capacity(self.triangles);
        let mut polygon = Vec::with_capacity(16);
        if !uses_vt && !uses_vn {
            for poly in &self.polygons {
                polygon.clear();
                let corners = self
                    .corners
                    .get(poly.start..poly.start + poly.len)
                    .unwrap_or(&[]);
                polygon.extend(corners.iter().map(|c| c[0]));
                fan(&polygon, &mut triangles);
            }
            return Ok(Mesh {
                positions: self.positions,
                triangles,
                normals: None,
                uvs: None,
                colors,
                tangents: None,
            });
        }

        // Distinct corners in order of first appearance, then ordered by position (stable).
        let mut first_ids: HashMap<[u32; 3], u32> = HashMap::new();
        let mut distinct: Vec<[u32; 3]> = Vec::new();
        let mut corner_ids: Vec<u32> = Vec::with_capacity(self.corners.len());
        for c in &self.corners {
            let id = *first_ids.entry(*c).or_insert_with(|| {
                distinct.push(*c);
                (distinct.len() - 1) as u32
            });
            corner_ids.push(id);
        }
        drop(first_ids);
        let mut order: Vec<u32> = (0..distinct.len() as u32).collect();
        order.sort_by_key(|&d| distinct.get(d as usize).map_or(0, |c| c[0]));
        let keep_unused = (!uses_vt || nt == nv) && (!uses_vn || nn == nv);
        let mut new_id = vec![0u32; distinct.len()];
        let mut vertices: Vec<[u32; 3]> = Vec::with_capacity(distinct.len());
        let mut next = order.iter().peekable();
        for i in 0..nv as u32 {
            let mut used = false;
            while let Some(&&d) = next.peek() {
                let Some(&c) = distinct.get(d as usize) else {
                    break;
                };
                if c[0] != i {
                    break;
                }
                next.next();
                if let Some(slot) = new_id.get_mut(d as usize) {
                    *slot = vertices.len() as u32;
                }
                vertices.push(c);
                used = true;
            }
            if !used && keep_unused {
                let attr = |uses: bool| if uses { i } else { NONE };
                vertices.push([i, attr(uses_vt), attr(uses_vn)]);
            }
            if vertices.len() > MAX_VERTICES {
                return Err(MeshError::TooMany {
                    at: Location::Line(lines),
                    what: "vertices after splitting",
                    count: vertices.len() as u64,
                    limit: MAX_VERTICES as u64,
                });
            }
        }
        for poly in &self.polygons {
            polygon.clear();
            let ids = corner_ids
                .get(poly.start..poly.start + poly.len)
                .unwrap_or(&[]);
            polygon.extend(
                ids.iter()
                    .map(|&d| new_id.get(d as usize).copied().unwrap_or(0)),
            );
            fan(&polygon, &mut triangles);
        }
        // Every index below was checked above.
        let attribute = |k: usize| vertices.iter().map(move |c| c[k] as usize);
        Ok(Mesh {
            positions: attribute(0).map(|v| self.positions[v]).collect(),
            triangles,
            normals: uses_vn.then(|| attribute(2).map(|n| self.normals[n]).collect()),
            uvs: uses_vt.then(|| attribute(1).map(|t| self.texcoords[t]).collect()),
            colors: colors.map(|c| attribute(0).map(|v| c[v]).collect()),
            tangents: None,
        })
    }
}

/// Parses a Wavefront OBJ file (see the [module documentation](self)). Errors name the 1-based
/// line.
pub fn parse_obj(text: &str) -> Result<Mesh, MeshError> {
    let mut reader = ObjReader::default();
    let mut lines = 0;
    for (index, raw) in text.lines().enumerate() {
        lines = index + 1;
        reader.statement(raw, lines)?;
    }
    reader.finish(lines)
}

// ---------------------------------------------------------------------------------------------
// PLY.

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }

    /// The range of an integer type; `None` for floats.
    fn range(self) -> Option<(i64, i64)> {
        match self {
            Scalar::I8 => Some((i8::MIN.into(), i8::MAX.into())),
            Scalar::U8 => Some((0, u8::MAX.into())),
            Scalar::I16 => Some((i16::MIN.into(), i16::MAX.into())),
            Scalar::U16 => Some((0, u16::MAX.into())),
            Scalar::I32 => Some((i32::MIN.into(), i32::MAX.into())),
            Scalar::U32 => Some((0, u32::MAX.into())),
            Scalar::F32 | Scalar::F64 => None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PlyFormat {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Debug, Clone, Copy)]
enum PropKind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
struct Property {
    name: String,
    kind: PropKind,
    line: usize,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    line: usize,
    properties: Vec<Property>,
}

#[derive(Debug)]
struct Header {
    format: PlyFormat,
    elements: Vec<Element>,
    /// Number of header lines (through `end_header`).
    lines: usize,
    /// Byte offset of the body.
    body: usize,
}

fn parse_header(bytes: &[u8]) -> Result<Header, MeshError> {
    let mut pos = 0;
    let mut line = 0;
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(rest) = bytes.get(pos..).filter(|r| !r.is_empty()) else {
            return Err(MeshError::Truncated {
                at: Location::Line(line + 1),
                what: "the end of the PLY header (`end_header`)".into(),
            });
        };
        let (raw, next) = match rest.iter().position(|&b| b == b'\n') {
            Some(k) => (rest.get(..k).unwrap_or(rest), pos + k + 1),
            None => (rest, bytes.len()),
        };
        line += 1;
        pos = next;
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        let text = String::from_utf8_lossy(raw);
        let at = Location::Line(line);
        let syntax = |message: String| MeshError::Syntax { at, message };
        let mut tokens = text.split_whitespace();
        let keyword = tokens.next().unwrap_or("");
        if line == 1 {
            if text.trim() != "ply" {
                return Err(syntax(
                    "not a PLY file: the first line must be `ply`".into(),
                ));
            }
            continue;
        }
        match keyword {
            "comment" | "obj_info" | "" => {}
            "format" => {
                let (a, n) = args::<3>(tokens);
                if n != 2 {
                    return Err(syntax("`format` takes a format and a version".into()));
                }
                if format.is_some() {
                    return Err(syntax("a second `format` line".into()));
                }
                format = Some(match a[0] {
                    "ascii" => PlyFormat::Ascii,
                    "binary_little_endian" => PlyFormat::BinaryLittleEndian,
                    "binary_big_endian" => PlyFormat::BinaryBigEndian,
                    other => {
                        return Err(MeshError::Unsupported {
                            at,
                            message: format!("PLY format `{other}`"),
                        });
                    }
                });
                if a[1] != "1.0" {
                    return Err(MeshError::Unsupported {
                        at,
                        message: format!("PLY version `{}` (only 1.0 exists)", a[1]),
                    });
                }
            }
            "element" => {
                let (a, n) = args::<3>(tokens);
                if n != 2 {
                    return Err(syntax("`element` takes a name and a count".into()));
                }
                let (name, count) = (a[0], a[1]);
                if elements.iter().any(|e| e.name == name) {
                    return Err(syntax(format!("a second `{name}` element")));
                }
                let count: u64 = count.parse().map_err(|_| MeshError::BadNumber {
                    at,
                    what: format!("the count of element `{name}`"),
                    token: count.to_string(),
                    expected: "non-negative integer",
                })?;
                let (limit, what) = match name {
                    "vertex" => (MAX_VERTICES, "vertices"),
                    "face" => (MAX_FACES, "faces"),
                    _ => (MAX_ELEMENT_RECORDS, "element records"),
                };
                let limit = (limit as u64).min(ocellus_engine::limits::get().max_list_len);
                if count > limit {
                    return Err(MeshError::TooMany {
                        at,
                        what,
                        count,
                        limit,
                    });
                }
                elements.push(Element {
                    name: name.to_string(),
                    count: count as usize,
                    line,
                    properties: Vec::new(),
                });
            }
            "property" => {
                let (a, n) = args::<5>(tokens);
                let Some(element) = elements.last_mut() else {
                    return Err(syntax("`property` before any `element`".into()));
                };
                let scalar = |name: &str| {
                    Scalar::parse(name).ok_or_else(|| MeshError::Unsupported {
                        at,
                        message: format!("property type `{name}`"),
                    })
                };
                let (kind, name) = match (a[0], n) {
                    ("list", 4) => {
                        let count = scalar(a[1])?;
                        if count.range().is_none() {
                            return Err(syntax(format!(
                                "list `{}` has a {} count; list counts are integers",
                                a[3],
                                count.name()
                            )));
                        }
                        (
                            PropKind::List {
                                count,
                                item: scalar(a[2])?,
                            },
                            a[3],
                        )
                    }
                    ("list", _) => {
                        return Err(syntax(
                            "`property list` takes a count type, an item type and a name".into(),
                        ));
                    }
                    (ty, 2) => (PropKind::Scalar(scalar(ty)?), a[1]),
                    _ => return Err(syntax("`property` takes a type and a name".into())),
                };
                if element.properties.iter().any(|p| p.name == name) {
                    return Err(syntax(format!(
                        "a second property `{name}` in element `{}`",
                        element.name
                    )));
                }
                element.properties.push(Property {
                    name: name.to_string(),
                    kind,
                    line,
                });
            }
            "end_header" => {
                let Some(format) = format else {
                    return Err(syntax("the header has no `format` line".into()));
                };
                return Ok(Header {
                    format,
                    elements,
                    lines: line,
                    body: pos,
                });
            }
            other => return Err(syntax(format!("unknown header keyword `{other}`"))),
        }
    }
}

/// Vertex attribute slots.
const SLOT_X: usize = 0;
const SLOT_NX: usize = 3;
const SLOT_U: usize = 6;
const SLOT_RED: usize = 8;
const SLOT_TX: usize = 11;
const SLOTS: usize = 15;

/// Which vertex properties feed which attribute.
struct VertexLayout {
    /// Per property, its slot.
    slots: Vec<Option<usize>>,
    normals: bool,
    uvs: bool,
    tangents: bool,
    /// Per color channel: the type's maximum for integer colors (sRGB-encoded), `None` for
    /// float colors (linear); `None` overall without colors.
    colors: Option<[Option<f64>; 3]>,
}

fn vertex_layout(element: &Element) -> Result<VertexLayout, MeshError> {
    let mut slots = vec![None; element.properties.len()];
    let find = |name: &str| {
        element
            .properties
            .iter()
            .enumerate()
            .find(|(_, p)| p.name == name)
    };
    let scalar_group = |names: &[&str],
                        slots: &mut [Option<usize>],
                        first: usize|
     -> Result<Option<Vec<Scalar>>, MeshError> {
        let found: Vec<_> = names.iter().map(|&n| find(n)).collect();
        let present = found.iter().filter(|f| f.is_some()).count();
        if present == 0 {
            return Ok(None);
        }
        if present < names.len() {
            return Err(MeshError::Syntax {
                at: Location::Line(element.line),
                message: format!(
                    "the vertex element has only some of the properties `{}`",
                    names.join(" ")
                ),
            });
        }
        let mut types = Vec::with_capacity(names.len());
        for (k, (index, p)) in found.into_iter().flatten().enumerate() {
            let PropKind::Scalar(ty) = p.kind else {
                return Err(MeshError::Syntax {
                    at: Location::Line(p.line),
                    message: format!("vertex property `{}` must be a scalar, not a list", p.name),
                });
            };
            if let Some(slot) = slots.get_mut(index) {
                *slot = Some(first + k);
            }
            types.push(ty);
        }
        Ok(Some(types))
    };
    if scalar_group(&["x", "y", "z"], &mut slots, SLOT_X)?.is_none() {
        return Err(MeshError::Syntax {
            at: Location::Line(element.line),
            message: "the vertex element has no `x y z` properties".into(),
        });
    }
    let normals = scalar_group(&["nx", "ny", "nz"], &mut slots, SLOT_NX)?.is_some();
    let mut uvs = false;
    for pair in [["u", "v"], ["s", "t"], ["texture_u", "texture_v"]] {
        if pair.iter().all(|&n| find(n).is_some()) {
            uvs = scalar_group(&pair, &mut slots, SLOT_U)?.is_some();
            break;
        }
    }
    const TANGENT: [&str; 4] = ["tx", "ty", "tz", "tw"];
    let tangents = TANGENT.iter().all(|&n| find(n).is_some())
        && scalar_group(&TANGENT, &mut slots, SLOT_TX)?.is_some();
    let colors = scalar_group(&["red", "green", "blue"], &mut slots, SLOT_RED)?.map(|types| {
        let mut scale = [None; 3];
        for (s, ty) in scale.iter_mut().zip(types) {
            *s = ty.range().map(|(_, max)| max as f64);
        }
        scale
    });
    Ok(VertexLayout {
        slots,
        normals,
        uvs,
        tangents,
        colors,
    })
}

/// The index of the face element's `vertex_indices` (or `vertex_index`) list.
fn face_indices(element: &Element) -> Result<usize, MeshError> {
    let found = ["vertex_indices", "vertex_index"].iter().find_map(|name| {
        element
            .properties
            .iter()
            .enumerate()
            .find(|(_, p)| p.name == *name)
    });
    let Some((index, p)) = found else {
        return Err(MeshError::Syntax {
            at: Location::Line(element.line),
            message: "the face element has no `vertex_indices` list".into(),
        });
    };
    match p.kind {
        PropKind::List { item, .. } if item.range().is_some() => Ok(index),
        PropKind::List { item, .. } => Err(MeshError::Syntax {
            at: Location::Line(p.line),
            message: format!(
                "`{}` has {} entries; vertex indices are integers",
                p.name,
                item.name()
            ),
        }),
        PropKind::Scalar(_) => Err(MeshError::Syntax {
            at: Location::Line(p.line),
            message: format!("`{}` must be a list", p.name),
        }),
    }
}

/// Rejects element counts the body cannot hold, before anything is allocated: a binary record
/// takes at least its scalars' and list counts' bytes; an ASCII value at least one character
/// and a separator.
fn check_sizes(header: &Header, available: usize) -> Result<(), MeshError> {
    let ascii = header.format == PlyFormat::Ascii;
    let mut needed: u64 = 0;
    for element in &header.elements {
        let record: u64 = element
            .properties
            .iter()
            .map(|p| {
                if ascii {
                    2
                } else {
                    match p.kind {
                        PropKind::Scalar(t) | PropKind::List { count: t, .. } => t.size() as u64,
                    }
                }
            })
            .sum();
        needed = needed.saturating_add(record.saturating_mul(element.count as u64));
        // The last ASCII value needs no separator.
        let short = if ascii { 1 } else { 0 };
        if needed.saturating_sub(short) > available as u64 {
            return Err(MeshError::CountExceedsData {
                at: Location::Line(element.line),
                element: element.name.clone(),
                count: element.count as u64,
                needed: needed - short,
                available: available as u64,
            });
        }
    }
    Ok(())
}

/// A PLY body: values one at a time.
trait Source {
    /// The next value of type `ty` (as `f64`, exact for every PLY type) and where it starts.
    fn scalar(
        &mut self,
        ty: Scalar,
        what: &dyn Fn() -> String,
    ) -> Result<(f64, Location), MeshError>;
    /// Skips `n` values of type `ty`.
    fn skip(&mut self, ty: Scalar, n: usize, what: &dyn Fn() -> String) -> Result<(), MeshError>;
    /// Checks what follows the last element.
    fn finish(&mut self) -> Result<(), MeshError>;
}

struct BinarySource<'a> {
    bytes: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl BinarySource<'_> {
    fn take<const N: usize>(&mut self, what: &dyn Fn() -> String) -> Result<[u8; N], MeshError> {
        match self
            .bytes
            .get(self.pos..)
            .and_then(|r| r.first_chunk::<N>())
        {
            Some(chunk) => {
                self.pos += N;
                Ok(*chunk)
            }
            None => Err(MeshError::Truncated {
                at: Location::Byte(self.pos),
                what: what(),
            }),
        }
    }
}

impl Source for BinarySource<'_> {
    fn scalar(
        &mut self,
        ty: Scalar,
        what: &dyn Fn() -> String,
    ) -> Result<(f64, Location), MeshError> {
        let at = Location::Byte(self.pos);
        let be = self.big_endian;
        macro_rules! read {
            ($t:ty, $n:literal) => {{
                let b = self.take::<$n>(what)?;
                f64::from(if be {
                    <$t>::from_be_bytes(b)
                } else {
                    <$t>::from_le_bytes(b)
                })
            }};
        }
        let v = match ty {
            Scalar::I8 => read!(i8, 1),
            Scalar::U8 => read!(u8, 1),
            Scalar::I16 => read!(i16, 2),
            Scalar::U16 => read!(u16, 2),
            Scalar::I32 => read!(i32, 4),
            Scalar::U32 => read!(u32, 4),
            Scalar::F32 => read!(f32, 4),
            Scalar::F64 => {
                let b = self.take::<8>(what)?;
                if be {
                    f64::from_be_bytes(b)
                } else {
                    f64::from_le_bytes(b)
                }
            }
        };
        Ok((v, at))
    }

    fn skip(&mut self, ty: Scalar, n: usize, what: &dyn Fn() -> String) -> Result<(), MeshError> {
        let len = n.saturating_mul(ty.size());
        if self.bytes.len().saturating_sub(self.pos) < len {
            return Err(MeshError::Truncated {
                at: Location::Byte(self.pos),
                what: what(),
            });
        }
        self.pos += len;
        Ok(())
    }

    fn finish(&mut self) -> Result<(), MeshError> {
        Ok(())
    }
}

struct AsciiSource<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> AsciiSource<'a> {
    /// The next whitespace-separated token and its line.
    fn token(&mut self) -> Option<(&'a [u8], usize)> {
        let bytes: &'a [u8] = self.bytes;
        while let Some(&b) = bytes.get(self.pos) {
            if b == b'\n' {
                self.line += 1;
            } else if !b.is_ascii_whitespace() {
                break;
            }
            self.pos += 1;
        }
        let start = self.pos;
        while bytes
            .get(self.pos)
            .is_some_and(|b| !b.is_ascii_whitespace())
        {
            self.pos += 1;
        }
        bytes
            .get(start..self.pos)
            .filter(|t| !t.is_empty())
            .map(|t| (t, self.line))
    }
}

impl Source for AsciiSource<'_> {
    fn scalar(
        &mut self,
        ty: Scalar,
        what: &dyn Fn() -> String,
    ) -> Result<(f64, Location), MeshError> {
        let Some((token, line)) = self.token() else {
            return Err(MeshError::Truncated {
                at: Location::Line(self.line),
                what: what(),
            });
        };
        let at = Location::Line(line);
        let text = std::str::from_utf8(token).ok();
        let value = match (ty, ty.range()) {
            (Scalar::F32, _) => text.and_then(|t| t.parse::<f32>().ok()).map(f64::from),
            (Scalar::F64, _) => text.and_then(|t| t.parse::<f64>().ok()),
            (_, Some((lo, hi))) => text
                .and_then(|t| t.parse::<i64>().ok())
                .filter(|v| (lo..=hi).contains(v))
                .map(|v| v as f64),
            (_, None) => None,
        };
        value.map(|v| (v, at)).ok_or_else(|| MeshError::BadNumber {
            at,
            what: what(),
            token: String::from_utf8_lossy(token).into_owned(),
            expected: ty.name(),
        })
    }

    fn skip(&mut self, _ty: Scalar, n: usize, what: &dyn Fn() -> String) -> Result<(), MeshError> {
        for _ in 0..n {
            if self.token().is_none() {
                return Err(MeshError::Truncated {
                    at: Location::Line(self.line),
                    what: what(),
                });
            }
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<(), MeshError> {
        match self.token() {
            Some((token, line)) => Err(MeshError::Syntax {
                at: Location::Line(line),
                message: format!(
                    "unexpected `{}` after the last element",
                    String::from_utf8_lossy(token)
                ),
            }),
            None => Ok(()),
        }
    }
}

/// A list's length, checked against [`MAX_LIST_LEN`].
fn list_len<S: Source>(
    src: &mut S,
    count: Scalar,
    what: &dyn Fn() -> String,
) -> Result<(usize, Location), MeshError> {
    let (len, at) = src.scalar(count, what)?;
    if len < 0.0 {
        return Err(MeshError::Syntax {
            at,
            message: format!("{}: negative list length {len}", what()),
        });
    }
    if len > MAX_LIST_LEN as f64 {
        return Err(MeshError::ListTooLong {
            at,
            len: len as u64,
            limit: MAX_LIST_LEN,
        });
    }
    Ok((len as usize, at))
}

fn skip_property<S: Source>(
    src: &mut S,
    kind: PropKind,
    what: &dyn Fn() -> String,
) -> Result<(), MeshError> {
    match kind {
        PropKind::Scalar(ty) => src.skip(ty, 1, what),
        PropKind::List { count, item } => {
            let (len, _) = list_len(src, count, what)?;
            src.skip(item, len, what)
        }
    }
}

fn read_vertices<S: Source>(
    src: &mut S,
    element: &Element,
    layout: &VertexLayout,
    mesh: &mut Mesh,
) -> Result<(), MeshError> {
    let n = element.count;
    mesh.positions.reserve_exact(n);
    let mut normals = layout.normals.then(|| Vec::with_capacity(n));
    let mut uvs = layout.uvs.then(|| Vec::with_capacity(n));
    let mut colors = layout.colors.map(|_| Vec::with_capacity(n));
    let mut tangents = layout.tangents.then(|| Vec::with_capacity(n));
    const NAMES: [&str; SLOTS] = [
        "x", "y", "z", "nx", "ny", "nz", "u", "v", "red", "green", "blue", "tx", "ty", "tz", "tw",
    ];
    for r in 0..n {
        let mut values = [0.0f64; SLOTS];
        let mut ats = [Location::Line(0); SLOTS];
        for (p, slot) in element.properties.iter().zip(&layout.slots) {
            let what = || format!("property `{}` of vertex {r}", p.name);
            match (p.kind, slot) {
                (PropKind::Scalar(ty), Some(s)) => {
                    let (v, at) = src.scalar(ty, &what)?;
                    if let (Some(dst), Some(a)) = (values.get_mut(*s), ats.get_mut(*s)) {
                        *dst = v;
                        *a = at;
                    }
                }
                (kind, _) => skip_property(src, kind, &what)?,
            }
        }
        let finite = |slot: usize, v: f64| {
            let f = v as f32;
            if f.is_finite() {
                Ok(f)
            } else {
                Err(MeshError::NonFinite {
                    at: ats[slot],
                    what: format!("{} of vertex {r}", NAMES[slot]),
                    value: v.to_string(),
                })
            }
        };
        let group = |first: usize| -> Result<[f32; 3], MeshError> {
            Ok([
                finite(first, values[first])?,
                finite(first + 1, values[first + 1])?,
                finite(first + 2, values[first + 2])?,
            ])
        };
        mesh.positions.push(group(SLOT_X)?);
        if let Some(normals) = &mut normals {
            let unit = normalize(group(SLOT_NX)?).ok_or_else(|| MeshError::ZeroNormal {
                at: ats[SLOT_NX],
                what: format!("the normal of vertex {r}"),
            })?;
            normals.push(unit);
        }
        if let Some(uvs) = &mut uvs {
            uvs.push([
                finite(SLOT_U, values[SLOT_U])?,
                finite(SLOT_U + 1, values[SLOT_U + 1])?,
            ]);
        }
        if let (Some(colors), Some(scale)) = (&mut colors, &layout.colors) {
            let mut c = [0.0f32; 3];
            for (k, (dst, s)) in c.iter_mut().zip(scale).enumerate() {
                let v = values[SLOT_RED + k];
                let linear = match s {
                    Some(max) => srgb_to_linear(v / max),
                    None => v,
                };
                *dst = finite(SLOT_RED + k, linear)?;
            }
            colors.push(c);
        }
        if let Some(tangents) = &mut tangents {
            let t = group(SLOT_TX)?;
            let w = finite(SLOT_TX + 3, values[SLOT_TX + 3])?;
            if w == 0.0 {
                return Err(MeshError::Syntax {
                    at: ats[SLOT_TX + 3],
                    message: format!(
                        "tw of vertex {r} is 0; the tangent handedness must be +1 or -1"
                    ),
                });
            }
            let unit = unit_tangent(t).ok_or_else(|| MeshError::ZeroNormal {
                at: ats[SLOT_TX],
                what: format!("the tangent of vertex {r}"),
            })?;
            tangents.push([unit[0], unit[1], unit[2], w.signum()]);
        }
    }
    mesh.normals = normals;
    mesh.uvs = uvs;
    mesh.colors = colors;
    mesh.tangents = tangents;
    Ok(())
}

fn read_faces<S: Source>(
    src: &mut S,
    element: &Element,
    indices: usize,
    vertex_count: usize,
    triangles: &mut Vec<[u32; 3]>,
) -> Result<(), MeshError> {
    // Each face takes at least one byte, so the count is bounded by the file, but a triangle
    // takes 12: grow as the faces come rather than trusting the count up front.
    triangles.reserve(element.count.min(1 << 16));
    let mut polygon: Vec<u32> = Vec::with_capacity(16);
    for r in 0..element.count {
        for (k, p) in element.properties.iter().enumerate() {
            let what = || format!("property `{}` of face {r}", p.name);
            match p.kind {
                PropKind::List { count, item } if k == indices => {
                    let (len, at) = list_len(src, count, &what)?;
                    if len < 3 {
                        return Err(MeshError::DegenerateFace { at, corners: len });
                    }
                    polygon.clear();
                    for _ in 0..len {
                        let (v, at) = src.scalar(item, &what)?;
                        if !(0.0..vertex_count as f64).contains(&v) {
                            return Err(MeshError::IndexOutOfRange {
                                at,
                                what: format!("vertex index of face {r}"),
                                index: v as i64,
                                count: vertex_count,
                            });
                        }
                        polygon.push(v as u32);
                    }
                    if triangles.len() + len - 2 > MAX_TRIANGLES {
                        return Err(MeshError::TooMany {
                            at,
                            what: "triangles",
                            count: (triangles.len() + len - 2) as u64,
                            limit: MAX_TRIANGLES as u64,
                        });
                    }
                    fan(&polygon, triangles);
                }
                kind => skip_property(src, kind, &what)?,
            }
        }
    }
    Ok(())
}

fn skip_element<S: Source>(src: &mut S, element: &Element) -> Result<(), MeshError> {
    if element.properties.is_empty() {
        return Ok(());
    }
    for r in 0..element.count {
        for p in &element.properties {
            skip_property(src, p.kind, &|| {
                format!("property `{}` of {} {r}", p.name, element.name)
            })?;
        }
    }
    Ok(())
}

fn read_body<S: Source>(
    src: &mut S,
    header: &Header,
    vertex: Option<&VertexLayout>,
    face: Option<usize>,
) -> Result<Mesh, MeshError> {
    let vertex_count = header
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .map_or(0, |e| e.count);
    let mut mesh = Mesh::default();
    for element in &header.elements {
        match (element.name.as_str(), vertex, face) {
            ("vertex", Some(layout), _) => read_vertices(src, element, layout, &mut mesh)?,
            ("face", _, Some(indices)) => {
                read_faces(src, element, indices, vertex_count, &mut mesh.triangles)?;
            }
            _ => skip_element(src, element)?,
        }
    }
    src.finish()?;
    Ok(mesh)
}

/// Parses a PLY file (Turk, Stanford 1994), ASCII or binary of either byte order (see the
/// [module documentation](self)). Errors name the line (header, ASCII body) or byte offset
/// (binary body).
pub fn parse_ply(bytes: &[u8]) -> Result<Mesh, MeshError> {
    let header = parse_header(bytes)?;
    let vertex = header
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .map(vertex_layout)
        .transpose()?;
    let face = header
        .elements
        .iter()
        .find(|e| e.name == "face")
        .map(face_indices)
        .transpose()?;
    check_sizes(&header, bytes.len().saturating_sub(header.body))?;
    let vertex = vertex.as_ref();
    match header.format {
        PlyFormat::Ascii => {
            let mut src = AsciiSource {
                bytes,
                pos: header.body,
                line: header.lines + 1,
            };
            read_body(&mut src, &header, vertex, face)
        }
        PlyFormat::BinaryLittleEndian | PlyFormat::BinaryBigEndian => {
            let mut src = BinarySource {
                bytes,
                pos: header.body,
                big_endian: header.format == PlyFormat::BinaryBigEndian,
            };
            read_body(&mut src, &header, vertex, face)
        }
    }
}

// ---------------------------------------------------------------------------------------------
// STL.

/// Bytes of a binary STL's header and triangle count.
const STL_HEADER_BYTES: u64 = 84;
/// Bytes of one binary STL triangle record.
const STL_RECORD_BYTES: u64 = 50;

/// Corners welded by the bits of their positions, numbered in order of first appearance.
#[derive(Default)]
struct Welder {
    ids: HashMap<[u32; 3], u32>,
    positions: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
}

impl Welder {
    fn with_capacity(triangles: usize) -> Welder {
        Welder {
            ids: HashMap::with_capacity(triangles.min(1 << 20)),
            positions: Vec::with_capacity(triangles.min(1 << 20)),
            triangles: Vec::with_capacity(triangles),
        }
    }

    fn vertex(&mut self, p: [f32; 3], at: Location) -> Result<u32, MeshError> {
        if let Some(&id) = self.ids.get(&p.map(f32::to_bits)) {
            return Ok(id);
        }
        if self.positions.len() >= MAX_VERTICES {
            return Err(MeshError::TooMany {
                at,
                what: "distinct vertex positions",
                count: self.positions.len() as u64 + 1,
                limit: MAX_VERTICES as u64,
            });
        }
        let id = self.positions.len() as u32;
        self.positions.push(p);
        self.ids.insert(p.map(f32::to_bits), id);
        Ok(id)
    }

    fn triangle(&mut self, t: [u32; 3], at: Location) -> Result<(), MeshError> {
        if self.triangles.len() >= MAX_TRIANGLES {
            return Err(MeshError::TooMany {
                at,
                what: "triangles",
                count: self.triangles.len() as u64 + 1,
                limit: MAX_TRIANGLES as u64,
            });
        }
        self.triangles.push(t);
        Ok(())
    }

    fn finish(self) -> Mesh {
        Mesh {
            positions: self.positions,
            triangles: self.triangles,
            ..Mesh::default()
        }
    }
}

/// Whether an STL file is binary (see the [module documentation](self)): its size matches the
/// count at byte 80, or it does not look like ASCII (`solid` first, no NUL byte).
pub fn stl_is_binary(bytes: &[u8]) -> bool {
    if let Some(n) = bytes.get(80..84).and_then(|b| b.first_chunk::<4>()) {
        let n = u64::from(u32::from_le_bytes(*n));
        if STL_HEADER_BYTES + STL_RECORD_BYTES * n == bytes.len() as u64 {
            return true;
        }
    }
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(bytes.len());
    let rest = bytes.get(start..).unwrap_or(&[]);
    let solid = rest
        .get(..5)
        .is_some_and(|k| k.eq_ignore_ascii_case(b"solid"))
        && rest.get(5).is_none_or(|b| b.is_ascii_whitespace());
    !solid || bytes.contains(&0)
}

fn stl_f32(bytes: &[u8], at: usize) -> f32 {
    let b = bytes
        .get(at..)
        .and_then(|r| r.first_chunk::<4>())
        .copied()
        .unwrap_or([0; 4]);
    f32::from_le_bytes(b)
}

fn parse_stl_binary(bytes: &[u8]) -> Result<Mesh, MeshError> {
    let Some(count) = bytes.get(80..84).and_then(|b| b.first_chunk::<4>()) else {
        return Err(MeshError::Truncated {
            at: Location::Byte(bytes.len()),
            what: "the end of the 84-byte binary STL header (80 bytes, then the triangle \
                   count; an ASCII STL starts with `solid`)"
                .into(),
        });
    };
    let count = u64::from(u32::from_le_bytes(*count));
    let expected = STL_HEADER_BYTES + STL_RECORD_BYTES * count;
    let actual = bytes.len() as u64;
    if actual < expected {
        let complete = (actual - STL_HEADER_BYTES) / STL_RECORD_BYTES;
        return Err(MeshError::Truncated {
            at: Location::Byte((STL_HEADER_BYTES + STL_RECORD_BYTES * complete) as usize),
            what: format!(
                "triangle {complete} of the {count} its header declares (that many take \
                 84 + 50 × {count} = {expected} bytes; the file has {actual})"
            ),
        });
    }
    if actual > expected {
        return Err(MeshError::StlSize {
            at: Location::Byte(80),
            count,
            expected,
            actual,
        });
    }
    let limit = (MAX_TRIANGLES as u64).min(ocellus_engine::limits::get().max_list_len);
    if count > limit {
        return Err(MeshError::TooMany {
            at: Location::Byte(80),
            what: "triangles",
            count,
            limit,
        });
    }
    // The size matched, so `count` records of 50 bytes follow.
    let mut welder = Welder::with_capacity(count as usize);
    for k in 0..count as usize {
        let record = STL_HEADER_BYTES as usize + STL_RECORD_BYTES as usize * k;
        // Bytes 0..12: the facet normal, ignored; 48..50: the attribute byte count, ignored.
        let mut triangle = [0u32; 3];
        for (c, slot) in triangle.iter_mut().enumerate() {
            let corner = record + 12 + 12 * c;
            let mut p = [0.0f32; 3];
            for (axis, (dst, name)) in p.iter_mut().zip(["x", "y", "z"]).enumerate() {
                let at = corner + 4 * axis;
                let v = stl_f32(bytes, at);
                if !v.is_finite() {
                    return Err(MeshError::NonFinite {
                        at: Location::Byte(at),
                        what: format!("{name} of corner {c} of triangle {k}"),
                        value: v.to_string(),
                    });
                }
                *dst = v;
            }
            *slot = welder.vertex(p, Location::Byte(corner))?;
        }
        welder.triangle(triangle, Location::Byte(record))?;
    }
    Ok(welder.finish())
}

/// The tokens of an ASCII STL, with their lines.
struct StlText<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> StlText<'a> {
    fn token(&mut self) -> Option<(&'a [u8], usize)> {
        let bytes: &'a [u8] = self.bytes;
        while let Some(&b) = bytes.get(self.pos) {
            if b == b'\n' {
                self.line += 1;
            } else if !b.is_ascii_whitespace() {
                break;
            }
            self.pos += 1;
        }
        let start = self.pos;
        while bytes
            .get(self.pos)
            .is_some_and(|b| !b.is_ascii_whitespace())
        {
            self.pos += 1;
        }
        bytes
            .get(start..self.pos)
            .filter(|t| !t.is_empty())
            .map(|t| (t, self.line))
    }

    /// Skips the rest of the line (a solid's name).
    fn skip_line(&mut self) {
        match self
            .bytes
            .get(self.pos..)
            .and_then(|r| r.iter().position(|&b| b == b'\n'))
        {
            Some(k) => {
                self.pos += k + 1;
                self.line += 1;
            }
            None => self.pos = self.bytes.len(),
        }
    }

    /// The next token, which must be `keyword` (any case).
    fn expect(&mut self, keyword: &str, facet: usize) -> Result<(), MeshError> {
        match self.token() {
            Some((t, _)) if t.eq_ignore_ascii_case(keyword.as_bytes()) => Ok(()),
            Some((t, line)) => {
                let hint = if keyword == "endloop" && t.eq_ignore_ascii_case(b"vertex") {
                    "; a facet has exactly 3 vertices"
                } else {
                    ""
                };
                Err(MeshError::Syntax {
                    at: Location::Line(line),
                    message: format!(
                        "expected `{keyword}` in facet {facet}, found `{}`{hint}",
                        String::from_utf8_lossy(t)
                    ),
                })
            }
            None => Err(MeshError::Truncated {
                at: Location::Line(self.line),
                what: format!("`{keyword}` in facet {facet}"),
            }),
        }
    }

    /// The next token as an `f32` (`finite`: NaN and infinities are errors).
    fn number(&mut self, what: &dyn Fn() -> String, finite: bool) -> Result<f32, MeshError> {
        let Some((t, line)) = self.token() else {
            return Err(MeshError::Truncated {
                at: Location::Line(self.line),
                what: what(),
            });
        };
        let at = Location::Line(line);
        let token = || String::from_utf8_lossy(t).into_owned();
        let v: f32 = std::str::from_utf8(t)
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| MeshError::BadNumber {
                at,
                what: what(),
                token: token(),
                expected: "number",
            })?;
        if finite && !v.is_finite() {
            return Err(MeshError::NonFinite {
                at,
                what: what(),
                value: token(),
            });
        }
        Ok(v)
    }
}

fn parse_stl_ascii(bytes: &[u8]) -> Result<Mesh, MeshError> {
    let mut text = StlText {
        bytes,
        pos: 0,
        line: 1,
    };
    let mut welder = Welder::default();
    let mut solids = 0usize;
    loop {
        match text.token() {
            None if solids > 0 => break,
            None => {
                return Err(MeshError::Truncated {
                    at: Location::Line(text.line),
                    what: "`solid`".into(),
                });
            }
            Some((t, _)) if t.eq_ignore_ascii_case(b"solid") => {}
            Some((t, line)) => {
                return Err(MeshError::Syntax {
                    at: Location::Line(line),
                    message: format!(
                        "expected `solid`, found `{}`; only another solid may follow `endsolid`",
                        String::from_utf8_lossy(t)
                    ),
                });
            }
        }
        text.skip_line();
        solids += 1;
        loop {
            let facet = welder.triangles.len();
            let (t, line) = text.token().ok_or_else(|| MeshError::Truncated {
                at: Location::Line(text.line),
                what: "`endsolid`".into(),
            })?;
            if t.eq_ignore_ascii_case(b"endsolid") {
                text.skip_line();
                break;
            }
            if !t.eq_ignore_ascii_case(b"facet") {
                return Err(MeshError::Syntax {
                    at: Location::Line(line),
                    message: format!(
                        "expected `facet` or `endsolid`, found `{}`",
                        String::from_utf8_lossy(t)
                    ),
                });
            }
            let at = Location::Line(line);
            text.expect("normal", facet)?;
            for axis in ["x", "y", "z"] {
                // Parsed, then ignored (see the module documentation).
                text.number(&|| format!("normal {axis} of facet {facet}"), false)?;
            }
            text.expect("outer", facet)?;
            text.expect("loop", facet)?;
            let mut triangle = [0u32; 3];
            for (c, slot) in triangle.iter_mut().enumerate() {
                text.expect("vertex", facet)?;
                let corner = Location::Line(text.line);
                let mut p = [0.0f32; 3];
                for (dst, axis) in p.iter_mut().zip(["x", "y", "z"]) {
                    *dst = text.number(&|| format!("vertex {c} {axis} of facet {facet}"), true)?;
                }
                *slot = welder.vertex(p, corner)?;
            }
            text.expect("endloop", facet)?;
            text.expect("endfacet", facet)?;
            welder.triangle(triangle, at)?;
        }
    }
    Ok(welder.finish())
}

/// Parses an STL file, binary or ASCII (see the [module documentation](self)), welding
/// bitwise-identical positions into an indexed mesh. Errors name the byte offset (binary) or
/// line (ASCII).
pub fn parse_stl(bytes: &[u8]) -> Result<Mesh, MeshError> {
    if stl_is_binary(bytes) {
        parse_stl_binary(bytes)
    } else {
        parse_stl_ascii(bytes)
    }
}

// ---------------------------------------------------------------------------------------------
// Files and the operator.

/// A mesh file format, chosen by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Wavefront OBJ (`.obj`).
    Obj,
    /// PLY, Turk, Stanford 1994 (`.ply`).
    Ply,
    /// STL, binary or ASCII (`.stl`).
    Stl,
}

impl MeshFormat {
    /// The format of `path` by its extension (`.obj`, `.ply`, `.stl`, any case).
    pub fn from_path(path: &Path) -> Result<MeshFormat, MeshError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("obj") => Ok(MeshFormat::Obj),
            Some("ply") => Ok(MeshFormat::Ply),
            Some("stl") => Ok(MeshFormat::Stl),
            _ => Err(MeshError::UnknownExtension {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Reads and parses a Wavefront OBJ, PLY or STL file, by extension. OBJ text that is not UTF-8 is
/// read lossily (only comments and names can hold other bytes).
pub fn read_mesh(path: &Path) -> Result<Mesh, OpError> {
    let format = MeshFormat::from_path(path).map_err(|e| OpError::failed(e.to_string()))?;
    let bytes = ocellus_engine::limits::read_file(path).map_err(|e| OpError::io(path, e))?;
    let mesh = match format {
        MeshFormat::Obj => parse_obj(&String::from_utf8_lossy(&bytes)),
        MeshFormat::Ply => parse_ply(&bytes),
        MeshFormat::Stl => parse_stl(&bytes),
    };
    mesh.map_err(|e| OpError::failed(format!("{}: {e}", path.display())))
}

ocellus_engine::params! {
    /// Parameters of [`ReadMesh`].
    pub struct ReadMeshParams {
        /// The mesh file, `.obj` (Wavefront OBJ), `.ply` (PLY) or `.stl` (STL, binary or
        /// ASCII); relative paths resolve against the graph file's folder.
        path: PathBuf = PathBuf::new(),
    }
}

/// `io.read_mesh`. See [`parse_obj`], [`parse_ply`] and [`parse_stl`].
pub struct ReadMesh {
    params: ReadMeshParams,
}

impl Op for ReadMesh {
    type Params = ReadMeshParams;
    const ID: &'static str = "io.read_mesh";
    const SUMMARY: &'static str = "Read a triangle mesh from a Wavefront OBJ, PLY or STL file.";
    const DOC: &'static str = r#"
Reads a triangle mesh; the extension picks the format (.obj, .ply or .stl, any case).

Wavefront OBJ: `v x y z` (optionally `r g b`, sRGB-encoded 0..1), `vt u v`, `vn x y z` and `f`
faces with corners `v`, `v/vt`, `v//vn` or `v/vt/vn`, 1-based or negative (relative) indices;
`#` comments; `o g s usemtl mtllib l p` are ignored. All face corners must name the same
attributes. Each distinct (v, vt, vn) corner becomes one vertex (a position with two uvs is
split), ordered by position; when nothing needs splitting, vertices and indices are the file's.

PLY (Turk, Stanford 1994): ascii, binary_little_endian or binary_big_endian 1.0, any scalar
types; vertex `x y z`, optional `nx ny nz`, `u v` (or `s t`, `texture_u texture_v`) and
`red green blue` and `tx ty tz tw` (tangents, w = ±1); face list `vertex_indices` (or
`vertex_index`). Other elements and properties are skipped.

STL, binary or ASCII: a file of exactly 84 + 50·n bytes (n the count at byte 80) is binary,
even if it starts with "solid"; otherwise a text file starting with `solid` is ASCII. Corners
with bitwise-identical positions are welded into one vertex (numbered by first appearance), so
the mesh comes out indexed; facet normals are ignored (the corner order gives the orientation;
use `mesh.normals`). A binary file whose size does not match its count is an error.

Polygons are fan-triangulated in their (counter-clockwise) order; normals are normalized.
Colors come out linear: OBJ colors and integer PLY colors are sRGB-decoded (as `--emit` writes
them), float PLY colors are taken as linear. Files written by `--emit` read back exactly.

Malformed files are errors naming the line (OBJ, PLY header and ascii body) or byte offset
(binary PLY and STL): bad numbers, NaN/Inf, indices out of range, zero normals, mixed
attributes, truncation. At most 10⁸ vertices, 10⁸ faces and 10⁸ triangles, lists of at most 1000 entries;
a PLY count larger than the file can hold is rejected before anything is allocated.

Example:
    "bunny": (op: "io.read_mesh", params: (path: "data/bunny.ply")),
"#;

    fn inputs() -> Vec<PortSpec> {
        Vec::new()
    }

    fn outputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "mesh",
            PortType::Mesh,
            "The triangle mesh, with the file's normals, uvs, colors and tangents when it has them.",
        )]
    }

    fn new(params: ReadMeshParams) -> Result<Self, String> {
        if params.path.as_os_str().is_empty() {
            return Err("`path` is required".into());
        }
        MeshFormat::from_path(&params.path).map_err(|e| e.to_string())?;
        Ok(ReadMesh { params })
    }
}

impl Operator for ReadMesh {
    fn run(&self, _ctx: &RunContext, _inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let mesh = read_mesh(&self.params.path)?;
        Ok(Outputs::new().with("mesh", Value::Mesh(Arc::new(mesh))))
    }

    /// The file's contents decide the result, so they are part of the cache key.
    fn fingerprint(&self) -> Result<Vec<u8>, OpError> {
        let bytes = ocellus_engine::limits::read_file(&self.params.path)
            .map_err(|e| OpError::io(&self.params.path, e))?;
        Ok(ocellus_engine::cache::content_hash(&bytes).to_vec())
    }
}

/// Names the command-line flag when the run's `--max-list-len` is the limit that was hit (the
/// readers' own maxima are fixed).
fn limit_flag(limit: u64) -> &'static str {
    if limit == ocellus_engine::limits::get().max_list_len {
        " (--max-list-len)"
    } else {
        ""
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Which error a case expects.
    type Kind = fn(&MeshError) -> bool;
    use ocellus_engine::emit::emit_value;
    use ocellus_engine::op::Registry;
    use ocellus_engine::{ParamMap, ParamValue};
    use proptest::prelude::*;

    /// A fresh folder under the system's temp dir, unique to this process and test.
    fn scratch(name: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("ocellus-read-mesh-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// What every successfully parsed mesh must satisfy.
    fn check_valid(mesh: &Mesh) {
        let n = mesh.positions.len();
        assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < n));
        assert!(mesh.positions.iter().flatten().all(|v| v.is_finite()));
        for len in [
            mesh.normals.as_ref().map(Vec::len),
            mesh.uvs.as_ref().map(Vec::len),
            mesh.colors.as_ref().map(Vec::len),
            mesh.tangents.as_ref().map(Vec::len),
        ]
        .into_iter()
        .flatten()
        {
            assert_eq!(len, n);
        }
        for t in mesh.tangents.iter().flatten() {
            let len = t[..3].iter().map(|c| c * c).sum::<f32>().sqrt();
            assert!((len - 1.0).abs() < 1e-5, "{t:?}");
            assert!(t[3] == 1.0 || t[3] == -1.0, "{t:?}");
        }
        for v in mesh.normals.iter().flatten() {
            let len = v.iter().map(|c| c * c).sum::<f32>().sqrt();
            assert!((len - 1.0).abs() < 1e-5, "{v:?}");
        }
        assert!(mesh.uvs.iter().flatten().flatten().all(|v| v.is_finite()));
        assert!(
            mesh.colors
                .iter()
                .flatten()
                .flatten()
                .all(|v| v.is_finite())
        );
    }

    /// Twice the signed area of a triangle's projection on the xy plane.
    fn area_z(mesh: &Mesh, t: [u32; 3]) -> f32 {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    }

    fn line(e: &MeshError) -> usize {
        match e.location() {
            Some(Location::Line(n)) => n,
            other => panic!("{e}: expected a line, got {other:?}"),
        }
    }

    fn byte(e: &MeshError) -> usize {
        match e.location() {
            Some(Location::Byte(n)) => n,
            other => panic!("{e}: expected a byte offset, got {other:?}"),
        }
    }

    // -----------------------------------------------------------------------------------------
    // OBJ.

    const SQUARE: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n";

    #[test]
    fn obj_quad_is_two_ccw_triangles() {
        let mesh = parse_obj(&format!("# a unit square\n{SQUARE}f 1 2 3 4\n")).unwrap();
        assert_eq!(
            mesh.positions,
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0]
            ]
        );
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        for &t in &mesh.triangles {
            assert_eq!(area_z(&mesh, t), 1.0);
        }
        assert_eq!((mesh.normals, mesh.uvs, mesh.colors), (None, None, None));
    }

    #[test]
    fn obj_pentagon_is_a_fan_covering_its_area() {
        let mut text = String::new();
        let mut ring = Vec::new();
        for k in 0..5 {
            let a = std::f32::consts::TAU * k as f32 / 5.0;
            ring.push([a.cos(), a.sin()]);
            text.push_str(&format!("v {} {} 0\n", a.cos(), a.sin()));
        }
        text.push_str("f 1 2 3 4 5\n");
        let mesh = parse_obj(&text).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 3, 4]]);
        let shoelace: f32 = (0..5)
            .map(|k| {
                let (p, q) = (ring[k], ring[(k + 1) % 5]);
                p[0] * q[1] - p[1] * q[0]
            })
            .sum();
        let fan: f32 = mesh.triangles.iter().map(|&t| area_z(&mesh, t)).sum();
        assert!(mesh.triangles.iter().all(|&t| area_z(&mesh, t) > 0.0));
        assert!((fan - shoelace).abs() < 1e-5, "{fan} vs {shoelace}");
    }

    #[test]
    fn obj_negative_indices_are_relative_to_the_elements_so_far() {
        let rel =
            parse_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 0 0\nv 5 1 0\nf -4 -2 -1\n")
                .unwrap();
        let abs =
            parse_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nv 5 0 0\nv 5 1 0\nf 2 4 5\n").unwrap();
        assert_eq!(rel, abs);
        assert_eq!(rel.triangles, vec![[0, 1, 2], [1, 3, 4]]);

        let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n\
                    f -3/-3/-1 -2/-2/-1 -1/-1/-1\n";
        let mesh = parse_obj(text).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
        assert_eq!(mesh.uvs, Some(vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]));
        assert_eq!(mesh.normals, Some(vec![[0.0, 0.0, 1.0]; 3]));
    }

    #[test]
    fn obj_splits_a_position_used_with_two_uvs() {
        // A square whose vertex 1 sits on a texture seam: face 1 gives it uv 1, face 2 uv 4.
        let text = format!(
            "{SQUARE}vt 0 0\nvt 0.5 0\nvt 0.5 0.5\nvt 1 0.5\nvt 1 1\nf 1/1 2/2 3/3\nf 1/4 3/3 4/5\n"
        );
        let mesh = parse_obj(&text).unwrap();
        // By position; position 1's two corners in order of appearance.
        assert_eq!(
            mesh.positions,
            vec![
                [0.0, 0.0, 0.0],
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0]
            ]
        );
        assert_eq!(
            mesh.uvs,
            Some(vec![
                [0.0, 0.0],
                [1.0, 0.5],
                [0.5, 0.0],
                [0.5, 0.5],
                [1.0, 1.0]
            ])
        );
        assert_eq!(mesh.triangles, vec![[0, 2, 3], [1, 3, 4]]);
        assert_eq!(mesh.normals, None);
        check_valid(&mesh);
        // The same corners again reuse the split vertices.
        let again = parse_obj(&format!("{text}f 1/4 3/3 4/5\n")).unwrap();
        assert_eq!(again.positions.len(), 5);
        assert_eq!(again.triangles[2], [1, 3, 4]);
    }

    #[test]
    fn obj_without_splits_keeps_the_vertex_order_and_takes_attributes_from_the_corners() {
        let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0.1 0.1\nvt 0.2 0.2\nvt 0.3 0.3\n\
                    f 3/1 1/2 2/3\n";
        let mesh = parse_obj(text).unwrap();
        assert_eq!(mesh.positions[2], [0.0, 1.0, 0.0]);
        assert_eq!(mesh.triangles, vec![[2, 0, 1]]);
        assert_eq!(mesh.uvs, Some(vec![[0.2, 0.2], [0.3, 0.3], [0.1, 0.1]]));
    }

    #[test]
    fn obj_unused_positions_are_kept_only_when_attributes_are_per_vertex() {
        // Four positions, three uvs: position 4 has no uv, so it is dropped.
        let dropped =
            parse_obj(&format!("{SQUARE}vt 0 0\nvt 1 0\nvt 1 1\nf 1/1 2/2 3/3\n")).unwrap();
        assert_eq!(dropped.positions.len(), 3);
        assert_eq!(dropped.triangles, vec![[0, 1, 2]]);
        // Four and four: kept, with uv 4.
        let kept = parse_obj(&format!(
            "{SQUARE}vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\n"
        ))
        .unwrap();
        assert_eq!(kept.positions.len(), 4);
        assert_eq!(kept.uvs.as_ref().map(|u| u[3]), Some([0.0, 1.0]));
        // Without attributes every position is kept.
        let plain = parse_obj(&format!("{SQUARE}f 1 2 3\n")).unwrap();
        assert_eq!(plain.positions.len(), 4);
    }

    #[test]
    fn obj_reads_every_corner_form_and_ignores_non_geometry() {
        let text = "mtllib scene.mtl\no thing\ng group1\ns 1\nusemtl red\n\
                    v 0 0 0 # a comment\nv 1 0 0\nv 0 1 0 1.0\n\
                    vt 0 0\nvt 1 0 0\nvt 0\n\
                    vn 0 0 2\nvn 3 0 0\n\
                    l 1 2\np 3\n\
                    f 1/1/1 2/2/1 3/3/2\n\
                    # done\n";
        let mesh = parse_obj(text).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
        assert_eq!(mesh.uvs, Some(vec![[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]));
        assert_eq!(
            mesh.normals,
            Some(vec![[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
        );
        let normals_only =
            parse_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 1 1\nf 1//1 2//1 3//1\n").unwrap();
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert_eq!(normals_only.normals, Some(vec![[0.0, h, h]; 3]));
        assert_eq!(normals_only.uvs, None);
        // Windows line ends.
        let crlf = parse_obj(&format!("{SQUARE}f 1 2 3 4\n").replace('\n', "\r\n")).unwrap();
        assert_eq!(crlf.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn obj_colors_are_srgb_decoded_to_linear() {
        let mesh =
            parse_obj("v 0 0 0 1 0.5 0\nv 1 0 0 0.02 0 0.2\nv 0 1 0 0 0 0\nf 1 2 3\n").unwrap();
        let decode = |s: f64| {
            if s <= 0.04045 {
                s / 12.92
            } else {
                ((s + 0.055) / 1.055).powf(2.4)
            }
        };
        let colors = mesh.colors.unwrap();
        assert_eq!(colors[0][0], 1.0);
        assert_eq!(colors[0][2], 0.0);
        assert!((colors[0][1] as f64 - decode(0.5)).abs() < 1e-7);
        assert!((colors[0][1] - 0.214_041_14).abs() < 1e-6);
        assert!((colors[1][0] as f64 - 0.02 / 12.92).abs() < 1e-9);
        assert!((colors[1][2] as f64 - decode(0.2)).abs() < 1e-7);
    }

    #[test]
    fn obj_empty_and_face_free_files() {
        assert_eq!(parse_obj("").unwrap(), Mesh::default());
        assert_eq!(parse_obj("# nothing\n\n   \n").unwrap(), Mesh::default());
        let points = parse_obj("v 1 2 3\nv 4 5 6\n").unwrap();
        assert_eq!(points.positions, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        assert!(points.triangles.is_empty());
        // Exactly one uv and normal per vertex: kept; other counts: not per-vertex data.
        let attributed = parse_obj("v 1 2 3\nvt 0.5 0.25\nvn 0 2 0\n").unwrap();
        assert_eq!(attributed.uvs, Some(vec![[0.5, 0.25]]));
        assert_eq!(attributed.normals, Some(vec![[0.0, 1.0, 0.0]]));
        let loose = parse_obj("v 1 2 3\nvt 0 0\nvt 1 1\n").unwrap();
        assert_eq!(loose.uvs, None);
        // A face may name vertices defined after it.
        let forward = parse_obj(&format!("f 1 2 3\n{SQUARE}")).unwrap();
        assert_eq!(forward.triangles, vec![[0, 1, 2]]);
    }

    #[test]
    fn obj_errors_name_the_kind_and_line() {
        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        let long_face = format!("{tri}f{}\n", " 1".repeat(MAX_LIST_LEN + 1));
        let cases: Vec<(String, usize, Kind)> = vec![
            ("v 0 0 0 1 1 1\nv 1 0 0\n".into(), 2, |e| {
                matches!(e, MeshError::MixedAttributes { .. })
            }),
            ("v 0 0 0\nv 1 0 0 1 1 1\n".into(), 2, |e| {
                matches!(e, MeshError::MixedAttributes { .. })
            }),
            (format!("{tri}vt 0 0\nf 1/1 2/1 3\n"), 5, |e| {
                matches!(e, MeshError::MixedAttributes { .. })
            }),
            (
                format!("{tri}vn 0 0 1\nf 1//1 2//1 3//1\nf 1 2 3\n"),
                6,
                |e| matches!(e, MeshError::MixedAttributes { .. }),
            ),
            ("vn 0 0 0\n".into(), 1, |e| {
                matches!(e, MeshError::ZeroNormal { .. })
            }),
            (format!("{tri}f 0 1 2\n"), 4, |e| {
                matches!(e, MeshError::IndexOutOfRange { index: 0, .. })
            }),
            (format!("{tri}f 1 2 4\n"), 4, |e| {
                matches!(
                    e,
                    MeshError::IndexOutOfRange {
                        index: 4,
                        count: 3,
                        ..
                    }
                )
            }),
            (format!("{tri}f -4 1 2\n"), 4, |e| {
                matches!(e, MeshError::IndexOutOfRange { index: -4, .. })
            }),
            (format!("{tri}vt 0 0\nf 1/2 2/1 3/1\n"), 5, |e| {
                matches!(e, MeshError::IndexOutOfRange { count: 1, .. })
            }),
            (format!("{tri}vn 0 0 1\nf 1//1 2//1 3//2\n"), 5, |e| {
                matches!(
                    e,
                    MeshError::IndexOutOfRange {
                        index: 2,
                        count: 1,
                        ..
                    }
                )
            }),
            (format!("{tri}f 1 2 999999999999\n"), 4, |e| {
                matches!(e, MeshError::IndexOutOfRange { .. })
            }),
            ("v 0 NaN 0\n".into(), 1, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            ("v 0 0 0\nv 0 inf 0\n".into(), 2, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            ("v 0 1e39 0\n".into(), 1, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            ("vn 0 nan 1\n".into(), 1, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            ("v 0 x 0\n".into(), 1, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (format!("{tri}f 1 2 x\n"), 4, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (format!("{tri}f 1 2 99999999999999999999\n"), 4, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (format!("{tri}f 1 2\n"), 4, |e| {
                matches!(e, MeshError::DegenerateFace { corners: 2, .. })
            }),
            (long_face, 4, |e| {
                matches!(e, MeshError::ListTooLong { len: 1001, .. })
            }),
            ("v 0 0 0\nfoo 1 2\n".into(), 2, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            ("curv 0 1 1 2\n".into(), 1, |e| {
                matches!(e, MeshError::Unsupported { .. })
            }),
            ("v 1 2\n".into(), 1, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            ("v 1 2 3 4 5\n".into(), 1, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            ("vt\n".into(), 1, |e| matches!(e, MeshError::Syntax { .. })),
            ("vn 1 2\n".into(), 1, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (format!("{tri}f 1/1/1/1 2 3\n"), 4, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (format!("{tri}f /1 2 3\n"), 4, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
        ];
        for (text, expected_line, is_kind) in cases {
            let err = parse_obj(&text).unwrap_err();
            assert!(is_kind(&err), "{text:?}: wrong kind {err:?}");
            assert_eq!(line(&err), expected_line, "{text:?}: {err}");
            assert!(
                err.to_string()
                    .starts_with(&format!("line {expected_line}: "))
            );
        }
    }

    // -----------------------------------------------------------------------------------------
    // PLY.

    /// A typed PLY value for hand-made files.
    #[derive(Debug, Clone, Copy)]
    enum V {
        I8(i8),
        U8(u8),
        I16(i16),
        U16(u16),
        I32(i32),
        U32(u32),
        F32(f32),
        F64(f64),
    }

    /// A PLY file: `header` holds the element and property lines.
    fn ply(format: &str, header: &str, records: &[Vec<V>]) -> Vec<u8> {
        let mut out =
            format!("ply\nformat {format} 1.0\ncomment made by hand\n{header}end_header\n")
                .into_bytes();
        let be = format == "binary_big_endian";
        for record in records {
            if format == "ascii" {
                let words: Vec<String> = record
                    .iter()
                    .map(|v| match *v {
                        V::I8(x) => x.to_string(),
                        V::U8(x) => x.to_string(),
                        V::I16(x) => x.to_string(),
                        V::U16(x) => x.to_string(),
                        V::I32(x) => x.to_string(),
                        V::U32(x) => x.to_string(),
                        V::F32(x) => x.to_string(),
                        V::F64(x) => x.to_string(),
                    })
                    .collect();
                out.extend_from_slice(words.join(" ").as_bytes());
                out.push(b'\n');
            } else {
                for v in record {
                    macro_rules! put {
                        ($x:expr) => {
                            if be {
                                out.extend_from_slice(&$x.to_be_bytes())
                            } else {
                                out.extend_from_slice(&$x.to_le_bytes())
                            }
                        };
                    }
                    match *v {
                        V::I8(x) => put!(x),
                        V::U8(x) => put!(x),
                        V::I16(x) => put!(x),
                        V::U16(x) => put!(x),
                        V::I32(x) => put!(x),
                        V::U32(x) => put!(x),
                        V::F32(x) => put!(x),
                        V::F64(x) => put!(x),
                    }
                }
            }
        }
        out
    }

    const FORMATS: [&str; 3] = ["ascii", "binary_little_endian", "binary_big_endian"];

    /// Header of the reference file: every scalar type, unknown scalar and list properties in
    /// the vertex and face elements, unknown elements before and after the faces.
    const RICH_HEADER: &str = "element vertex 4\nproperty float x\nproperty double y\n\
        property short z\nproperty float nx\nproperty float ny\nproperty float nz\n\
        property uint16 quality\nproperty float32 u\nproperty float32 v\n\
        property list uchar float extra\nproperty uchar red\nproperty uint8 green\n\
        property uchar blue\nproperty uchar alpha\n\
        element edge 2\nproperty int vertex1\nproperty int32 vertex2\n\
        property list ushort double weights\n\
        obj_info unknown elements are skipped\n\
        element face 2\nproperty uint flags\nproperty list uchar int vertex_indices\n\
        property list uint16 float64 texcoord\n\
        element material 1\nproperty list int char name\nproperty ushort id\n\
        property int8 a\nproperty uint b\nproperty float64 c\nproperty short d\n";

    fn rich_records() -> Vec<Vec<V>> {
        use V::*;
        // x y z, nx ny nz, quality, u v, extra list, red green blue alpha.
        let vertex =
            |xyz: (f32, f64, i16), n: [f32; 3], uv: [f32; 2], extra: &[f32], c: [u8; 4]| {
                let mut r = vec![F32(xyz.0), F64(xyz.1), I16(xyz.2)];
                r.extend(n.map(F32));
                r.push(U16(7));
                r.extend(uv.map(F32));
                r.push(U8(extra.len() as u8));
                r.extend(extra.iter().map(|&e| F32(e)));
                r.extend(c.map(U8));
                r
            };
        // flags, vertex_indices, texcoord list.
        let face = |flags: u32, corners: &[i32], texcoord: &[f64]| {
            let mut r = vec![U32(flags), U8(corners.len() as u8)];
            r.extend(corners.iter().map(|&i| I32(i)));
            r.push(U16(texcoord.len() as u16));
            r.extend(texcoord.iter().map(|&t| F64(t)));
            r
        };
        vec![
            vertex(
                (0.0, 0.0, 0),
                [0.0, 0.0, 2.0],
                [0.0, 0.0],
                &[1.5, 2.5],
                [255, 128, 0, 255],
            ),
            vertex(
                (1.0, 0.0, 0),
                [0.0, 0.0, 1.0],
                [1.0, 0.0],
                &[],
                [0, 0, 0, 9],
            ),
            vertex(
                (1.0, 1.5, -2),
                [0.0, 0.6, 0.8],
                [1.0, 1.0],
                &[3.25],
                [10, 20, 30, 40],
            ),
            vertex(
                (0.25, 1.0, 3),
                [0.0, -1.0, 0.0],
                [0.0, 1.0],
                &[],
                [1, 2, 3, 4],
            ),
            // edges
            vec![I32(0), I32(1), U16(1), F64(0.5)],
            vec![I32(2), I32(3), U16(0)],
            // faces: a quad and a triangle
            face(1, &[0, 1, 2, 3], &[0.0, 1.0]),
            face(2, &[0, 2, 3], &[]),
            // material, over two lines in ASCII (the body is a stream of values)
            vec![
                I32(3),
                I8(65),
                I8(66),
                I8(-3),
                U16(5),
                I8(-1),
                U32(4_000_000_000),
            ],
            vec![F64(-1e300), I16(-7)],
        ]
    }

    fn rich_mesh() -> Mesh {
        let c = |b: u8| srgb_to_linear(f64::from(b) / 255.0) as f32;
        Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.5, -2.0],
                [0.25, 1.0, 3.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3], [0, 2, 3]],
            normals: Some(vec![
                [0.0, 0.0, 1.0],
                [0.0, 0.0, 1.0],
                normalize([0.0, 0.6, 0.8]).unwrap(),
                [0.0, -1.0, 0.0],
            ]),
            uvs: Some(vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]),
            colors: Some(vec![
                [1.0, c(128), 0.0],
                [0.0, 0.0, 0.0],
                [c(10), c(20), c(30)],
                [c(1), c(2), c(3)],
            ]),
            tangents: None,
        }
    }

    #[test]
    fn ply_ascii_little_and_big_endian_give_the_same_mesh() {
        let expected = rich_mesh();
        for format in FORMATS {
            let bytes = ply(format, RICH_HEADER, &rich_records());
            let mesh = parse_ply(&bytes).unwrap_or_else(|e| panic!("{format}: {e}"));
            assert_eq!(mesh, expected, "{format}");
            check_valid(&mesh);
            for &t in &mesh.triangles[..2] {
                assert!(area_z(&mesh, t) > 0.0);
            }
        }
        // CRLF header lines.
        let text = String::from_utf8(ply("ascii", RICH_HEADER, &rich_records())).unwrap();
        let crlf = text.replace('\n', "\r\n");
        assert_eq!(parse_ply(crlf.as_bytes()).unwrap(), expected);
    }

    #[test]
    fn ply_alternative_names_types_and_float_colors() {
        let header = "element vertex 3\nproperty double x\nproperty double y\nproperty double z\n\
            property float texture_u\nproperty float texture_v\nproperty float red\n\
            property float green\nproperty float blue\n\
            element face 1\nproperty list int8 uint16 vertex_index\n";
        use V::*;
        let v = |x: f64, y: f64| {
            vec![
                F64(x),
                F64(y),
                F64(0.0),
                F32(0.5),
                F32(0.25),
                F32(0.5),
                F32(2.0),
                F32(0.0),
            ]
        };
        let records = vec![
            v(0.0, 0.0),
            v(1.0, 0.0),
            v(0.0, 1.0),
            vec![I8(3), U16(0), U16(1), U16(2)],
        ];
        for format in FORMATS {
            let mesh = parse_ply(&ply(format, header, &records)).unwrap();
            assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
            assert_eq!(mesh.uvs, Some(vec![[0.5, 0.25]; 3]));
            // Float colors are linear already.
            assert_eq!(mesh.colors, Some(vec![[0.5, 2.0, 0.0]; 3]));
            assert_eq!(mesh.normals, None);
        }
        // `s t` names, ushort colors, a point cloud without faces, and no vertex element.
        let header = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
            property float s\nproperty float t\nproperty ushort red\nproperty ushort green\n\
            property ushort blue\n";
        let records = vec![vec![
            F32(1.0),
            F32(2.0),
            F32(3.0),
            F32(0.75),
            F32(0.5),
            U16(65535),
            U16(0),
            U16(0),
        ]];
        let mesh = parse_ply(&ply("binary_little_endian", header, &records)).unwrap();
        assert_eq!(mesh.positions, vec![[1.0, 2.0, 3.0]]);
        assert_eq!(mesh.uvs, Some(vec![[0.75, 0.5]]));
        assert_eq!(mesh.colors, Some(vec![[1.0, 0.0, 0.0]]));
        assert!(mesh.triangles.is_empty());
        let empty = parse_ply(&ply(
            "ascii",
            "element face 0\nproperty list uchar int vertex_indices\n",
            &[],
        ))
        .unwrap();
        assert_eq!(empty, Mesh::default());
        // A huge element without properties costs nothing.
        let nothing = parse_ply(&ply(
            "binary_big_endian",
            "element nothing 100000000\n",
            &[],
        ));
        assert_eq!(nothing.unwrap(), Mesh::default());
    }

    /// Offset of the body of a [`ply`] file.
    fn body_offset(bytes: &[u8]) -> usize {
        let end = b"end_header\n";
        bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len()
    }

    const XYZ: &str = "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n";
    const FACES: &str = "element face 1\nproperty list uchar int vertex_indices\n";

    fn triangle_records(face: Vec<V>) -> Vec<Vec<V>> {
        use V::*;
        vec![
            vec![F32(0.0), F32(0.0), F32(0.0)],
            vec![F32(1.0), F32(0.0), F32(0.0)],
            vec![F32(0.0), F32(1.0), F32(0.0)],
            face,
        ]
    }

    #[test]
    fn ply_header_errors() {
        let le = "binary_little_endian";
        let cases: Vec<(Vec<u8>, usize, Kind)> = vec![
            (b"plx\nformat ascii 1.0\nend_header\n".to_vec(), 1, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (b"".to_vec(), 1, |e| {
                matches!(e, MeshError::Truncated { .. })
            }),
            (
                b"ply\nformat ascii 1.0\nelement vertex 0\n".to_vec(),
                4,
                |e| matches!(e, MeshError::Truncated { .. }),
            ),
            (
                b"ply\nformat binary_little_endian 2.0\nend_header\n".to_vec(),
                2,
                |e| matches!(e, MeshError::Unsupported { .. }),
            ),
            (b"ply\nformat xml 1.0\nend_header\n".to_vec(), 2, |e| {
                matches!(e, MeshError::Unsupported { .. })
            }),
            (b"ply\nelement vertex 0\nend_header\n".to_vec(), 3, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (
                ply(le, "element vertex 0\nproperty float128 x\n", &[]),
                5,
                |e| matches!(e, MeshError::Unsupported { .. }),
            ),
            (ply(le, "property float x\n", &[]), 4, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (
                ply(le, "element vertex 0\nelement vertex 0\n", &[]),
                5,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(
                    le,
                    "element vertex 0\nproperty float x\nproperty float x\n",
                    &[],
                ),
                6,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (ply(le, "element vertex -1\n", &[]), 4, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (ply(le, "element vertex 100000001\n", &[]), 4, |e| {
                matches!(
                    e,
                    MeshError::TooMany {
                        count: 100_000_001,
                        ..
                    }
                )
            }),
            (ply(le, "element face 100000001\n", &[]), 4, |e| {
                matches!(e, MeshError::TooMany { .. })
            }),
            (
                ply(le, "element other 18446744073709551615\n", &[]),
                4,
                |e| matches!(e, MeshError::TooMany { .. }),
            ),
            (ply(le, "banana\n", &[]), 4, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (
                ply(
                    le,
                    "element vertex 1\nproperty float y\nproperty float z\n",
                    &[],
                ),
                4,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(
                    le,
                    &format!("{XYZ}property float nx\nproperty float ny\n"),
                    &[],
                ),
                4,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(
                    le,
                    "element vertex 1\nproperty list uchar float x\nproperty float y\n\
                     property float z\n",
                    &[],
                ),
                5,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(
                    le,
                    "element face 1\nproperty list float int vertex_indices\n",
                    &[],
                ),
                5,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(
                    le,
                    "element face 1\nproperty list uchar float vertex_indices\n",
                    &[],
                ),
                5,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(le, "element face 1\nproperty int vertex_indices\n", &[]),
                5,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            (
                ply(le, "element face 1\nproperty list uchar int corners\n", &[]),
                4,
                |e| matches!(e, MeshError::Syntax { .. }),
            ),
            // Declared counts larger than the data, before anything is allocated.
            (
                ply(
                    le,
                    &format!("{}{FACES}", XYZ.replace(" 3", " 1000000")),
                    &[],
                ),
                4,
                |e| {
                    matches!(
                        e,
                        MeshError::CountExceedsData {
                            count: 1_000_000,
                            needed: 12_000_000,
                            available: 0,
                            ..
                        }
                    )
                },
            ),
            (
                ply(
                    le,
                    &format!("{XYZ}{}", FACES.replace(" 1", " 99999999")),
                    &triangle_records(vec![]),
                ),
                8,
                |e| {
                    matches!(
                        e,
                        MeshError::CountExceedsData {
                            needed: 100_000_035,
                            available: 36,
                            ..
                        }
                    )
                },
            ),
            (
                ply(
                    "ascii",
                    XYZ.replace(" 3", " 10").as_str(),
                    &triangle_records(vec![])[..1],
                ),
                4,
                |e| matches!(e, MeshError::CountExceedsData { needed: 59, .. }),
            ),
        ];
        for (bytes, expected_line, is_kind) in cases {
            let text = String::from_utf8_lossy(&bytes).into_owned();
            let err = parse_ply(&bytes).unwrap_err();
            assert!(is_kind(&err), "{text:?}: wrong kind {err:?}");
            assert_eq!(line(&err), expected_line, "{text:?}: {err}");
        }
    }

    #[test]
    fn ply_body_errors_name_the_byte_or_line() {
        use V::*;
        let le = "binary_little_endian";
        let header = format!("{XYZ}{FACES}");
        let good = ply(
            le,
            &header,
            &triangle_records(vec![U8(3), I32(0), I32(1), I32(2)]),
        );
        let body = body_offset(&good);
        assert_eq!(parse_ply(&good).unwrap().triangles, vec![[0, 1, 2]]);

        // Face index 3 of 3 vertices: its offset is after the vertices and the count byte.
        let bad = ply(
            le,
            &header,
            &triangle_records(vec![U8(3), I32(0), I32(1), I32(3)]),
        );
        let err = parse_ply(&bad).unwrap_err();
        assert!(
            matches!(
                err,
                MeshError::IndexOutOfRange {
                    index: 3,
                    count: 3,
                    ..
                }
            ),
            "{err}"
        );
        assert_eq!(byte(&err), body + 36 + 1 + 8);
        let bad = ply(
            le,
            &header,
            &triangle_records(vec![U8(3), I32(-1), I32(1), I32(2)]),
        );
        assert!(matches!(
            parse_ply(&bad),
            Err(MeshError::IndexOutOfRange { index: -1, .. })
        ));

        // NaN y of vertex 0.
        let mut nan = good.clone();
        nan[body + 4..body + 8].copy_from_slice(&f32::NAN.to_le_bytes());
        let err = parse_ply(&nan).unwrap_err();
        assert!(matches!(err, MeshError::NonFinite { .. }), "{err}");
        assert_eq!(byte(&err), body + 4);
        // Infinite z of vertex 2, big-endian.
        let mut inf = ply(
            "binary_big_endian",
            &header,
            &triangle_records(vec![U8(3), I32(0), I32(1), I32(2)]),
        );
        let b = body_offset(&inf);
        inf[b + 32..b + 36].copy_from_slice(&f32::INFINITY.to_be_bytes());
        assert_eq!(byte(&parse_ply(&inf).unwrap_err()), b + 32);
        // A double beyond the f32 range.
        let wide = ply(
            le,
            "element vertex 1\nproperty double x\nproperty double y\nproperty double z\n",
            &[vec![F64(0.0), F64(1e300), F64(0.0)]],
        );
        assert!(matches!(parse_ply(&wide), Err(MeshError::NonFinite { .. })));

        // Truncated anywhere in the body.
        for cut in [1, 5, 13] {
            let err = parse_ply(&good[..good.len() - cut]).unwrap_err();
            match err {
                MeshError::Truncated {
                    at: Location::Byte(at),
                    ..
                } => assert!(at >= body),
                // Cutting into the vertices leaves fewer bytes than the header promises.
                MeshError::CountExceedsData { .. } => assert_eq!(cut, 13),
                other => panic!("{other}"),
            }
        }
        assert!(matches!(
            parse_ply(&good[..good.len() - 2]),
            Err(MeshError::Truncated { at: Location::Byte(at), .. }) if at == body + 36 + 1 + 8
        ));

        // Lists: too long, negative, too short.
        let long_header = format!("{XYZ}element face 1\nproperty list ushort int vertex_indices\n");
        let mut face = vec![U16(1001)];
        face.extend((0..1001).map(|_| I32(0)));
        let err = parse_ply(&ply(le, &long_header, &triangle_records(face))).unwrap_err();
        assert!(
            matches!(err, MeshError::ListTooLong { len: 1001, .. }),
            "{err}"
        );
        assert_eq!(byte(&err), body_offset(&ply(le, &long_header, &[])) + 36);
        let neg_header = format!("{XYZ}element face 1\nproperty list char int vertex_indices\n");
        let err = parse_ply(&ply(le, &neg_header, &triangle_records(vec![I8(-1)]))).unwrap_err();
        assert!(
            matches!(
                err,
                MeshError::Syntax {
                    at: Location::Byte(_),
                    ..
                }
            ),
            "{err}"
        );
        let err = parse_ply(&ply(
            le,
            &header,
            &triangle_records(vec![U8(2), I32(0), I32(1)]),
        ));
        assert!(matches!(
            err,
            Err(MeshError::DegenerateFace { corners: 2, .. })
        ));
        // An unknown list that is too long is rejected too.
        let extra = format!("{XYZ}element junk 1\nproperty list uint float values\n");
        let mut records = triangle_records(vec![U32(5000)]);
        records[3].extend((0..5000).map(|_| F32(0.0)));
        let err = parse_ply(&ply(le, &extra, &records)).unwrap_err();
        assert!(
            matches!(err, MeshError::ListTooLong { len: 5000, .. }),
            "{err}"
        );

        // Zero normal.
        let normals = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
            property float nx\nproperty float ny\nproperty float nz\n";
        let zero = ply(le, normals, &[vec![F32(0.0); 6]]);
        let err = parse_ply(&zero).unwrap_err();
        assert!(matches!(err, MeshError::ZeroNormal { .. }), "{err}");
        assert_eq!(byte(&err), body_offset(&zero) + 12);

        // ASCII: truncation, trailing data, bad numbers, out-of-range integers.
        let ascii = |body: &str| {
            let mut bytes = ply("ascii", &header, &[]);
            bytes.extend_from_slice(body.as_bytes());
            parse_ply(&bytes)
        };
        let header_lines = 2 + 1 + XYZ.lines().count() + FACES.lines().count() + 1;
        assert!(ascii("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n\n\n").is_ok());
        let err = ascii("0 0 0\n1 0 0\n0 1 0\n3 0 1\n\n\n").unwrap_err();
        assert!(matches!(err, MeshError::Truncated { .. }), "{err}");
        let err = ascii("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n7\n").unwrap_err();
        assert!(matches!(err, MeshError::Syntax { .. }), "{err}");
        assert_eq!(line(&err), header_lines + 5);
        let err = ascii("0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert!(matches!(err, MeshError::BadNumber { .. }), "{err}");
        assert_eq!(line(&err), header_lines + 2);
        let err = ascii("0 0 0\n1 0 0\n0 1 0\n300 0 1 2\n").unwrap_err();
        assert!(matches!(err, MeshError::BadNumber { .. }), "{err}");
        let err = ascii("0 0 0\n1 0 0\n0 1 0\n3 0 1 2.5\n").unwrap_err();
        assert!(matches!(err, MeshError::BadNumber { .. }), "{err}");
        let err = ascii("0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n").unwrap_err();
        assert!(
            matches!(err, MeshError::IndexOutOfRange { index: 7, .. }),
            "{err}"
        );
        assert_eq!(line(&err), header_lines + 4);
        let err = ascii("0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert!(matches!(err, MeshError::NonFinite { .. }), "{err}");
        assert_eq!(line(&err), header_lines + 2);
    }

    // -----------------------------------------------------------------------------------------
    // PLY tangents.

    #[test]
    fn ply_tangents_are_read_when_all_four_properties_are_there() {
        let header = |props: &str| {
            format!(
                "ply\nformat ascii 1.0\n{XYZ}{props}element face 1\n\
                 property list uchar int vertex_indices\nend_header\n"
            )
        };
        let tw = "property float tx\nproperty float ty\nproperty float tz\nproperty float tw\n";
        let text = format!(
            "{}0 0 0 1 0 0 1\n1 0 0 0 2 0 -1\n0 1 0 0.6 0.8 0 -3\n3 0 1 2\n",
            header(tw)
        );
        let mesh = parse_ply(text.as_bytes()).unwrap();
        assert_eq!(
            mesh.tangents,
            Some(vec![
                [1.0, 0.0, 0.0, 1.0],
                [0.0, 1.0, 0.0, -1.0],
                [0.6, 0.8, 0.0, -1.0]
            ])
        );
        check_valid(&mesh);
        // Without `tw` the three are some other data: skipped, as before.
        let three = "property float tx\nproperty float ty\nproperty float tz\n";
        let text = format!(
            "{}0 0 0 1 0 0\n1 0 0 0 2 0\n0 1 0 5 5 5\n3 0 1 2\n",
            header(three)
        );
        let mesh = parse_ply(text.as_bytes()).unwrap();
        assert_eq!(mesh.tangents, None);
        assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
        // Zero tangents, zero handedness and NaN are errors naming the line.
        let header_lines = header(tw).lines().count();
        for (body, at, kind) in [
            (
                "0 0 0 1 0 0 1\n1 0 0 0 0 0 1\n0 1 0 1 0 0 1\n",
                2,
                (|e| matches!(e, MeshError::ZeroNormal { .. })) as Kind,
            ),
            ("0 0 0 1 0 0 1\n1 0 0 1 0 0 0\n0 1 0 1 0 0 1\n", 2, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            ("0 0 0 1 0 0 1\n1 0 0 1 0 0 1\n0 1 0 1 nan 0 1\n", 3, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
        ] {
            let text = format!("{}{body}3 0 1 2\n", header(tw));
            let err = parse_ply(text.as_bytes()).unwrap_err();
            assert!(kind(&err), "{err}");
            assert_eq!(line(&err), header_lines + at, "{err}");
        }
    }

    // -----------------------------------------------------------------------------------------
    // STL.

    type Soup = Vec<[[f32; 3]; 3]>;

    /// A tetrahedron as a triangle soup, outward and counter-clockwise.
    fn tetra_soup() -> Soup {
        let p = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
            .map(|t: [usize; 3]| t.map(|i| p[i]))
            .to_vec()
    }

    /// A binary STL of `soup` whose header starts with `start`, with facet normals (7, 7, 7)
    /// and attribute counts 0xcdab (both ignored).
    fn stl_binary(soup: &[[[f32; 3]; 3]], start: [u8; 5]) -> Vec<u8> {
        let mut b = vec![b' '; 80];
        b[..5].copy_from_slice(&start);
        b.extend_from_slice(&(soup.len() as u32).to_le_bytes());
        for t in soup {
            for v in [[7.0f32; 3], t[0], t[1], t[2]] {
                for c in v {
                    b.extend_from_slice(&c.to_le_bytes());
                }
            }
            b.extend_from_slice(&[0xab, 0xcd]);
        }
        b
    }

    /// An ASCII STL of `soup`: facet `k` starts on line `2 + 7k`, its vertex `c` is on line
    /// `4 + 7k + c`.
    fn stl_ascii(soup: &[[[f32; 3]; 3]]) -> String {
        let mut s = String::from("solid tetra\n");
        for t in soup {
            s.push_str("  facet normal 0 0 0\n    outer loop\n");
            for v in t {
                s.push_str(&format!("      vertex {} {} {}\n", v[0], v[1], v[2]));
            }
            s.push_str("    endloop\n  endfacet\n");
        }
        s.push_str("endsolid tetra\n");
        s
    }

    /// Each triangle's corner positions, by their bits.
    fn soup_bits(mesh: &Mesh) -> Vec<[[u32; 3]; 3]> {
        mesh.triangles
            .iter()
            .map(|t| t.map(|i| mesh.positions[i as usize].map(f32::to_bits)))
            .collect()
    }

    #[test]
    fn stl_binary_ascii_and_solid_headed_binary_give_the_same_welded_mesh() {
        let soup = tetra_soup();
        // Positions by first appearance: corner 0 of triangle 0, then its corners 2 and 1, …
        let expected = Mesh {
            positions: vec![
                [0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3], [0, 3, 1], [2, 1, 3]],
            ..Mesh::default()
        };
        let binary = stl_binary(&soup, *b"abcde");
        assert!(stl_is_binary(&binary));
        assert_eq!(parse_stl(&binary).unwrap(), expected);
        // A binary header starting with "solid": the size decides.
        let solid = stl_binary(&soup, *b"solid");
        assert!(stl_is_binary(&solid));
        assert_eq!(parse_stl(&solid).unwrap(), expected);
        let ascii = stl_ascii(&soup);
        assert!(!stl_is_binary(ascii.as_bytes()));
        assert_eq!(parse_stl(ascii.as_bytes()).unwrap(), expected);
        // Keyword case, CRLF, tabs and a nameless solid do not matter.
        let loose = ascii
            .replace("solid tetra", "SOLID")
            .replace("vertex", "VERTEX")
            .replace("  ", "\t")
            .replace('\n', "\r\n");
        assert_eq!(parse_stl(loose.as_bytes()).unwrap(), expected);
        // Each triangle keeps its corner positions and order (its orientation).
        let want: Vec<[[u32; 3]; 3]> = soup
            .iter()
            .map(|t| t.map(|p| p.map(f32::to_bits)))
            .collect();
        assert_eq!(soup_bits(&expected), want);
        // Solids that follow one another are appended, welded across.
        let twice = format!("{ascii}{ascii}");
        let both = parse_stl(twice.as_bytes()).unwrap();
        assert_eq!(both.positions, expected.positions);
        assert_eq!(both.triangles.len(), 8);
        assert_eq!(both.triangles[4..], expected.triangles[..]);
        // Empty files of both kinds.
        assert_eq!(
            parse_stl(&stl_binary(&[], *b"solid")).unwrap(),
            Mesh::default()
        );
        assert_eq!(
            parse_stl(b"solid empty\nendsolid empty\n").unwrap(),
            Mesh::default()
        );
        assert_eq!(parse_stl(b"  solid\nendsolid").unwrap(), Mesh::default());
    }

    #[test]
    fn stl_welds_only_bitwise_equal_positions() {
        let soup = vec![
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            [[-0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 1e-45]],
            [[0.0, 1.0, 1e-45], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        ];
        for bytes in [stl_binary(&soup, *b"xxxxx"), stl_ascii(&soup).into_bytes()] {
            let mesh = parse_stl(&bytes).unwrap();
            // -0.0 and the subnormal are vertices of their own; repeats reuse the first.
            assert_eq!(mesh.positions.len(), 5);
            assert_eq!(mesh.triangles, vec![[0, 1, 2], [3, 1, 4], [4, 1, 0]]);
            assert_eq!(mesh.positions[3][0].to_bits(), (-0.0f32).to_bits());
            check_valid(&mesh);
        }
    }

    #[test]
    fn stl_binary_errors_name_the_byte() {
        let good = stl_binary(&tetra_soup(), *b"solid");
        // Truncated mid-record: the first incomplete triangle's offset.
        let err = parse_stl(&good[..good.len() - 10]).unwrap_err();
        assert!(matches!(err, MeshError::Truncated { .. }), "{err}");
        assert_eq!(byte(&err), 84 + 3 * 50);
        assert!(err.to_string().contains("triangle 3 of the 4"), "{err}");
        // Shorter than the header (one that does not start with "solid"); empty.
        let plain = stl_binary(&tetra_soup(), *b"abcde");
        let err = parse_stl(&plain[..50]).unwrap_err();
        assert!(matches!(err, MeshError::Truncated { .. }), "{err}");
        assert_eq!(byte(&err), 50);
        assert_eq!(byte(&parse_stl(b"").unwrap_err()), 0);
        // A count too large for the file, and one too small.
        let mut more = good.clone();
        more[80..84].copy_from_slice(&5u32.to_le_bytes());
        let err = parse_stl(&more).unwrap_err();
        assert!(matches!(err, MeshError::Truncated { .. }), "{err}");
        assert_eq!(byte(&err), 84 + 4 * 50);
        let mut fewer = good.clone();
        fewer[80..84].copy_from_slice(&3u32.to_le_bytes());
        assert_eq!(
            parse_stl(&fewer).unwrap_err(),
            MeshError::StlSize {
                at: Location::Byte(80),
                count: 3,
                expected: 234,
                actual: 284
            }
        );
        // An absurd count fails before anything is allocated.
        let mut huge = good.clone();
        huge[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            parse_stl(&huge).unwrap_err(),
            MeshError::Truncated { .. }
        ));
        // NaN and infinite corners: the coordinate's offset.
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut b = good.clone();
            let at = 84 + 2 * 50 + 12 + 12 + 4; // triangle 2, corner 1, y
            b[at..at + 4].copy_from_slice(&bad.to_le_bytes());
            let err = parse_stl(&b).unwrap_err();
            assert!(matches!(err, MeshError::NonFinite { .. }), "{err}");
            assert_eq!(byte(&err), at);
            assert!(
                err.to_string().contains("y of corner 1 of triangle 2"),
                "{err}"
            );
        }
        // Facet normals are ignored, NaN included.
        let mut b = good.clone();
        b[84..88].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(parse_stl(&b).unwrap(), parse_stl(&good).unwrap());
    }

    #[test]
    fn stl_ascii_errors_name_the_line() {
        let good = stl_ascii(&tetra_soup());
        let edit = |from: &str, to: &str| good.replacen(from, to, 1);
        // Facet 0's vertices are on lines 4, 5, 6; facet 1 starts on line 9.
        let cases: Vec<(String, usize, Kind)> = vec![
            (edit("vertex 0 1 0", "vertex 0 nan 0"), 5, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            (edit("vertex 0 1 0", "vertex 0 1e39 0"), 5, |e| {
                matches!(e, MeshError::NonFinite { .. })
            }),
            (edit("vertex 0 1 0", "vertex 0 one 0"), 5, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (edit("facet normal 0 0 0", "facet normal 0 x 0"), 2, |e| {
                matches!(e, MeshError::BadNumber { .. })
            }),
            (
                edit("    endloop", "      vertex 1 1 1\n    endloop"),
                7,
                |e| matches!(e, MeshError::Syntax { message, .. } if message.contains("exactly 3")),
            ),
            (edit("outer loop", "outer ring"), 3, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (edit("  facet", "  facade"), 2, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (format!("{good}junk\n"), 31, |e| {
                matches!(e, MeshError::Syntax { .. })
            }),
            (good.replace("endsolid tetra\n", ""), 30, |e| {
                matches!(e, MeshError::Truncated { .. })
            }),
            (good[..good.find("endloop").unwrap()].to_string(), 7, |e| {
                matches!(e, MeshError::Truncated { .. })
            }),
        ];
        for (text, at, kind) in cases {
            let err = parse_stl(text.as_bytes()).unwrap_err();
            assert!(kind(&err), "{err}");
            assert_eq!(line(&err), at, "{err}\n{text}");
        }
        // "solid" alone is not enough to make a file with NUL bytes ASCII.
        let mut nul = good.clone().into_bytes();
        nul[20] = 0;
        assert!(stl_is_binary(&nul));
        assert!(matches!(
            parse_stl(&nul).unwrap_err(),
            MeshError::StlSize { .. } | MeshError::Truncated { .. }
        ));
    }

    // -----------------------------------------------------------------------------------------
    // Round trips through the engine's emitter.

    struct Lcg(u64);

    impl Lcg {
        fn unit(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn sample_mesh(
        n: usize,
        faces: usize,
        seed: u64,
        (normals, uvs, colors): (bool, bool, bool),
        unused: usize,
    ) -> Mesh {
        let mut rng = Lcg(seed);
        let mut positions: Vec<[f32; 3]> = (0..n)
            .map(|_| [0; 3].map(|_| 20.0 * rng.unit() - 10.0))
            .collect();
        if let Some(p) = positions.first_mut() {
            *p = [1e-40, -0.0, 3.0e38];
        }
        if let Some(p) = positions.get_mut(1) {
            *p = [-1.0e-7, 123_456.79, f32::MIN_POSITIVE];
        }
        let used = n - unused;
        let triangles = (0..faces)
            .map(|_| [0; 3].map(|_| ((rng.unit() * used as f32) as u32).min(used as u32 - 1)))
            .collect();
        let normals = normals.then(|| {
            (0..n)
                .map(|_| normalize([0; 3].map(|_| rng.unit() - 0.5)).unwrap_or([0.0, 0.0, 1.0]))
                .collect()
        });
        let uvs = uvs.then(|| {
            (0..n)
                .map(|_| [rng.unit(), 2.0 * rng.unit() - 0.5])
                .collect()
        });
        let colors = colors.then(|| {
            (0..n)
                .map(|i| match i {
                    0 => [0.0, 1.0, 0.001],
                    1 => [0.003, 0.5, 0.999],
                    _ => [rng.unit(), rng.unit(), rng.unit()],
                })
                .collect()
        });
        Mesh {
            positions,
            triangles,
            normals,
            uvs,
            colors,
            tangents: None,
        }
    }

    fn emit(dir: &Path, name: &str, mesh: &Mesh) -> (PathBuf, PathBuf) {
        let files = emit_value(dir, name, &Value::Mesh(Arc::new(mesh.clone()))).unwrap();
        assert_eq!(files.len(), 2);
        (files[0].clone(), files[1].clone())
    }

    fn assert_close(label: &str, a: &[[f32; 3]], b: &[[f32; 3]], tol: f32) {
        assert_eq!(a.len(), b.len(), "{label}");
        for (x, y) in a.iter().zip(b) {
            for (p, q) in x.iter().zip(y) {
                assert!((p - q).abs() <= tol, "{label}: {x:?} vs {y:?}");
            }
        }
    }

    fn assert_round_trip(label: &str, original: &Mesh, back: &Mesh, color_tol: f32) {
        check_valid(back);
        let bits = |m: &Mesh| -> Vec<[u32; 3]> {
            m.positions.iter().map(|p| p.map(f32::to_bits)).collect()
        };
        assert_eq!(bits(back), bits(original), "{label}: positions");
        assert_eq!(back.triangles, original.triangles, "{label}: triangles");
        assert_eq!(back.uvs, original.uvs, "{label}: uvs");
        assert_eq!(
            back.normals.is_some(),
            original.normals.is_some(),
            "{label}"
        );
        if let (Some(a), Some(b)) = (&back.normals, &original.normals) {
            assert_close(label, a, b, 1e-6);
        }
        assert_eq!(back.colors.is_some(), original.colors.is_some(), "{label}");
        if let (Some(a), Some(b)) = (&back.colors, &original.colors) {
            assert_close(label, a, b, color_tol);
        }
    }

    /// PLY stores colors as sRGB bytes: half a step, through the steepest part of the curve.
    const BYTE_TOL: f32 = 0.5 / 255.0 * 2.4 / 1.055 + 1e-6;

    #[test]
    fn emitted_meshes_read_back_exactly() {
        let dir = scratch("round-trip");
        let all = (true, true, true);
        let cases = [
            ("plain", sample_mesh(30, 40, 1, (false, false, false), 0)),
            ("normals", sample_mesh(30, 40, 2, (true, false, false), 0)),
            ("uvs", sample_mesh(30, 40, 3, (false, true, false), 0)),
            ("colors", sample_mesh(30, 40, 4, (false, false, true), 0)),
            ("all", sample_mesh(500, 900, 5, all, 0)),
            ("all_unused", sample_mesh(40, 30, 6, all, 3)),
            (
                "uvs_normals_unused",
                sample_mesh(40, 30, 7, (true, true, false), 2),
            ),
            (
                "plain_unused",
                sample_mesh(10, 5, 8, (false, false, false), 4),
            ),
            ("no_faces", sample_mesh(12, 0, 9, all, 0)),
            ("empty", Mesh::default()),
        ];
        for (name, mesh) in &cases {
            let (obj, ply) = emit(&dir, name, mesh);
            let from_obj = parse_obj(&std::fs::read_to_string(&obj).unwrap())
                .unwrap_or_else(|e| panic!("{name}.obj: {e}"));
            assert_round_trip(&format!("{name}.obj"), mesh, &from_obj, 1e-6);
            let bytes = std::fs::read(&ply).unwrap();
            let from_ply = parse_ply(&bytes).unwrap_or_else(|e| panic!("{name}.ply: {e}"));
            assert_round_trip(&format!("{name}.ply"), mesh, &from_ply, BYTE_TOL);
            // What was read writes the same bytes again (colors re-quantize to the same bytes).
            let (_, ply2) = emit(&dir, &format!("{name}_again"), &from_ply);
            let again = parse_ply(&std::fs::read(&ply2).unwrap()).unwrap();
            assert_eq!(again.colors, from_ply.colors, "{name}");
            if mesh.normals.is_none() {
                assert_eq!(std::fs::read(&ply2).unwrap(), bytes, "{name}");
            }
            // And the OBJ reader agrees with the PLY reader on everything but color precision.
            assert_round_trip(
                &format!("{name} obj vs ply"),
                &from_ply,
                &from_obj,
                BYTE_TOL,
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    // -----------------------------------------------------------------------------------------
    // Hostile input.

    /// `cases` from a fixed seed (`PROPTEST_CASES`, `PROPTEST_RNG_SEED` override).
    fn config(cases: u32) -> ProptestConfig {
        let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse().ok());
        ProptestConfig {
            cases: env("PROPTEST_CASES").map_or(cases, |c: u64| c as u32),
            rng_seed: proptest::test_runner::RngSeed::Fixed(
                env("PROPTEST_RNG_SEED").unwrap_or(20_260_517),
            ),
            ..ProptestConfig::default()
        }
    }

    fn seeds() -> Vec<Vec<u8>> {
        let mut out: Vec<Vec<u8>> = FORMATS
            .iter()
            .map(|f| ply(f, RICH_HEADER, &rich_records()))
            .collect();
        let header = format!("{XYZ}{FACES}");
        out.push(ply(
            "binary_little_endian",
            &header,
            &triangle_records(vec![V::U8(3), V::I32(0), V::I32(1), V::I32(2)]),
        ));
        out.push(ply(
            "ascii",
            &header,
            &triangle_records(vec![V::U8(3), V::I32(0), V::I32(1), V::I32(2)]),
        ));
        out.push(
            format!(
                "{SQUARE}vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nf 1/1/1 2/2/1 3/3/1 4/4/1\n\
                 f -4/-1/-1 -2/-2/-1 -1/-3/-1\n"
            )
            .into_bytes(),
        );
        out.push(format!("{SQUARE}f 1 2 3\nf 1 3 4\n").into_bytes());
        out.push(b"v 0 0 0 1 0 0\nv 1 0 0 0 1 0\nv 0 1 0 0 0 1\nf 1 2 3\n".to_vec());
        out.push(stl_binary(&tetra_soup(), *b"abcde"));
        out.push(stl_binary(&tetra_soup(), *b"solid"));
        out.push(stl_ascii(&tetra_soup()).into_bytes());
        out
    }

    fn check_parsers(bytes: &[u8]) {
        if let Ok(mesh) = parse_ply(bytes) {
            check_valid(&mesh);
        }
        if let Ok(mesh) = parse_stl(bytes) {
            check_valid(&mesh);
        }
        if let Ok(mesh) = parse_obj(&String::from_utf8_lossy(bytes)) {
            check_valid(&mesh);
        }
    }

    fn mutation_byte() -> impl Strategy<Value = u8> {
        prop_oneof![
            1 => any::<u8>(),
            3 => prop::sample::select(b"0123456789 -./\ne".to_vec()),
        ]
    }

    /// `(where, byte, kind)` edits.
    fn edits() -> impl Strategy<Value = Vec<(prop::sample::Index, u8, u8)>> {
        prop::collection::vec(
            (any::<prop::sample::Index>(), mutation_byte(), 0u8..11),
            1..4,
        )
    }

    /// Applies edits: mostly byte replacements (half of them a digit for a digit, which keeps a
    /// file plausible), some insertions, removals and truncations.
    fn mutate(bytes: &mut Vec<u8>, edits: &[(prop::sample::Index, u8, u8)]) {
        for (at, b, kind) in edits {
            if bytes.is_empty() {
                bytes.push(*b);
                continue;
            }
            let i = at.index(bytes.len());
            match kind {
                0..=4 => bytes[i] = *b,
                5..=7 => {
                    if let Some(d) = bytes[i..].iter_mut().find(|d| d.is_ascii_digit()) {
                        *d = b'0' + b % 10;
                    }
                }
                8 => bytes.insert(i, *b),
                9 => {
                    bytes.remove(i);
                }
                _ => bytes.truncate(i),
            }
        }
    }

    /// A random mesh: up to 12 vertices (some unused), 16 triangles, any attributes.
    fn mesh_strategy() -> impl Strategy<Value = Mesh> {
        (
            0usize..12,
            any::<[bool; 3]>(),
            any::<u64>(),
            0usize..16,
            any::<usize>(),
        )
            .prop_map(|(n, [normals, uvs, colors], seed, faces, unused)| {
                if n == 0 {
                    Mesh::default()
                } else {
                    sample_mesh(n, faces, seed, (normals, uvs, colors), unused % n)
                }
            })
    }

    proptest! {
        #![proptest_config(config(256))]

        #[test]
        fn random_bytes_never_panic(
            bytes in prop::collection::vec(any::<u8>(), 0..400),
            prefix in 0usize..5,
        ) {
            let mut input = match prefix {
                0 => Vec::new(),
                1 => ply("binary_little_endian", &format!("{XYZ}{FACES}"), &[]),
                2 => ply("ascii", &format!("{XYZ}{FACES}"), &[]),
                3 => b"solid random\n  facet normal 0 0 1\n".to_vec(),
                _ => {
                    // A binary STL header whose count matches 0..=7 random records.
                    let mut h = vec![0u8; 80];
                    h.extend_from_slice(&((bytes.len() / 50) as u32).to_le_bytes());
                    h
                }
            };
            input.extend_from_slice(&bytes);
            check_parsers(&input);
        }

        #[test]
        fn mutated_files_never_panic(which in any::<prop::sample::Index>(), edits in edits()) {
            let seeds = seeds();
            let mut bytes = seeds[which.index(seeds.len())].clone();
            mutate(&mut bytes, &edits);
            check_parsers(&bytes);
        }

        #[test]
        fn random_emitted_meshes_read_back_and_survive_mutation(
            mesh in mesh_strategy(),
            edits in edits(),
        ) {
            let dir = std::env::temp_dir()
                .join(format!("ocellus-read-mesh-{}-property", std::process::id()));
            let (obj, ply) = emit(&dir, "mesh", &mesh);
            let mut obj = std::fs::read(obj).unwrap();
            let mut ply = std::fs::read(ply).unwrap();
            std::fs::remove_dir_all(&dir).unwrap();
            let from_obj = parse_obj(&String::from_utf8_lossy(&obj)).unwrap();
            assert_round_trip("obj", &mesh, &from_obj, 1e-6);
            let from_ply = parse_ply(&ply).unwrap();
            assert_round_trip("ply", &mesh, &from_ply, BYTE_TOL);
            mutate(&mut obj, &edits);
            mutate(&mut ply, &edits);
            check_parsers(&obj);
            check_parsers(&ply);
        }
    }

    #[test]
    fn seeds_are_valid() {
        for (k, s) in seeds().iter().enumerate() {
            let ok = parse_ply(s).is_ok()
                || parse_obj(&String::from_utf8_lossy(s)).is_ok()
                || parse_stl(s).is_ok();
            assert!(ok, "seed {k}");
        }
    }

    // -----------------------------------------------------------------------------------------
    // The operator.

    #[test]
    fn operator_through_the_registry() {
        let mut registry = Registry::new();
        crate::register_builtins(&mut registry).unwrap();
        let factory = registry.get("io.read_mesh").unwrap();
        assert_eq!(factory.info().outputs[0].ty, PortType::Mesh);
        assert!(factory.info().inputs.is_empty());
        let build = |path: &Path| {
            let mut params = ParamMap::new();
            params.insert(
                "path".into(),
                ParamValue::Str(path.to_string_lossy().into_owned()),
            );
            factory.build(&params)
        };
        let ctx = RunContext {
            node: "mesh".into(),
            threads: 1,
            element: None,
        };
        let run = |op: &Arc<dyn Operator>| {
            op.run(&ctx, &Inputs::new(&[], &[]))
                .map(|mut out| out.take("mesh"))
        };
        let dir = scratch("operator");

        let err = build(&dir.join("mesh.off")).err().unwrap();
        assert!(
            err.contains(".obj") && err.contains(".ply") && err.contains(".stl"),
            "{err}"
        );
        assert!(build(&dir.join("mesh")).is_err());
        assert!(build(Path::new("")).is_err());

        let missing = build(&dir.join("missing.ply")).unwrap();
        assert!(matches!(run(&missing), Err(OpError::Io { .. })));
        assert!(missing.fingerprint().is_err());

        let obj = dir.join("square.OBJ");
        std::fs::write(&obj, format!("{SQUARE}f 1 2 3 4\n")).unwrap();
        let op = build(&obj).unwrap();
        let expected = parse_obj(&format!("{SQUARE}f 1 2 3 4\n")).unwrap();
        assert_eq!(
            run(&op).unwrap(),
            Some(Value::Mesh(Arc::new(expected.clone())))
        );
        assert!(op.fingerprint().is_ok());

        let (_, ply) = emit(&dir, "square", &expected);
        assert_eq!(
            run(&build(&ply).unwrap()).unwrap(),
            Some(Value::Mesh(Arc::new(expected)))
        );

        let bad = dir.join("bad.ply");
        std::fs::write(&bad, "ply\nformat ascii 1.0\nbanana\nend_header\n").unwrap();
        let err = run(&build(&bad).unwrap()).unwrap_err().to_string();
        assert!(err.contains("bad.ply") && err.contains("line 3"), "{err}");

        assert_eq!(
            MeshFormat::from_path(Path::new("a/b.Ply")),
            Ok(MeshFormat::Ply)
        );
        assert_eq!(
            MeshFormat::from_path(Path::new("a.obj")),
            Ok(MeshFormat::Obj)
        );
        assert_eq!(
            MeshFormat::from_path(Path::new("a.STL")),
            Ok(MeshFormat::Stl)
        );
        assert!(matches!(
            MeshFormat::from_path(Path::new("a.obj.gz")),
            Err(MeshError::UnknownExtension { .. })
        ));
        // An STL through the operator: welded, with the file's triangles.
        let stl = dir.join("tetra.stl");
        std::fs::write(&stl, stl_binary(&tetra_soup(), *b"solid")).unwrap();
        let Some(Value::Mesh(m)) = run(&build(&stl).unwrap()).unwrap() else {
            panic!("no mesh")
        };
        assert_eq!(m.positions.len(), 4);
        assert_eq!(m.triangles.len(), 4);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
