//! Binary encoding of values for the on-disk result cache.
//!
//! # Format (version 3)
//! Little-endian throughout. A file is
//!
//! ```text
//! "OCVL"  u32 version  u64 count  value × count
//! ```
//!
//! and a value is a `u8` tag followed by its payload. Lengths are `u64` element counts; strings
//! are a length then UTF-8 bytes; `[f32; 3]` and similar arrays are their elements in order.
//!
//! | tag | value | payload |
//! |----:|-------|---------|
//! | 0 | Image | `u64 width, u64 height, u8 channels (0 gray, 1 rgb, 2 rgba), u8 depth (0 u8, 1 u16, 2 f32)`, then the samples in bulk |
//! | 1 | Keypoints | `u64 n`, n × (`f32 x, y, size, angle, response, i32 octave`) |
//! | 2 | Descriptors | `u8 kind (0 float, 1 binary), u64 dim or bytes, u64 n`, n samples (f32 or u8) |
//! | 3 | Matches | `u64 n`, n × (`u32 query, u32 train, f32 distance`) |
//! | 4 | Matrix | `u64 rows, u64 cols`, rows × cols f64 |
//! | 5 | Camera | camera (below) |
//! | 6 | Pose | pose: `f64 × 4` rotation, `f64 × 3` translation |
//! | 7 | Points2D | `u64 n`, n × `f64 × 2` |
//! | 8 | PointCloud | `u64 n`, n × `f32 × 3`, `u8 flags (1 colors, 2 normals)`, then each present attribute as `u64 n` + items |
//! | 9 | Tracks | `u64 tracks`, each `u64 n`, n × (`u32 image, u32 keypoint`) |
//! | 10 | Reconstruction | cameras (`u64 n`, n × (`u32 id`, camera)), images (`u64 n`, n × (`u32 id, u32 camera_id`, string name, pose, `u64 n`, n × (`f64 x, f64 y, u8 has_point, u64 point_id`))), points (`u64 n`, n × (`u64 id, f64 × 3, u8 × 3, f64 error, u64 n`, n × `u32 image, u32 index`)) |
//! | 11 | Mesh | mesh: positions (`u64 n`, `f32 × 3` each), triangles (`u64 n`, `u32 × 3` each), `u8 flags (1 normals, 2 uvs, 4 colors, 8 tangents)`, then each present attribute as `u64 n` + items (tangents `f32 × 4`) |
//! | 12 | Scene | materials (`u64 n`, n × (string name, `f32 × 3` albedo, texture albedo, texture normal, `f32` roughness, texture, `f32` metalness, texture, `f32 × 3` emission, texture, `f32 × 5` specular shininess transmission ior opacity, `u8` shading)), objects (`u64 n`, n × (string name, shape, pose, `f64` scale, `u32` material)), lights (`u64 n`, n × (`u8 kind`, then 0 point `f64 × 3, f32 × 3`; 1 directional `f64 × 3, f32 × 3`; 2 area `f64 × 9, f32 × 3`; 3 environment `f32 × 3`, texture)), cameras (`u64 n`, n × (camera, pose, `f64` aperture radius, `f64` focus distance)); a texture is `u8 present`, then image (as tag 0 without the tag), `u8 wrap, u8 filter, f32 × 4 border, u32 max anisotropy, f32 × 2 uv scale`; a shape is `u8 kind`, then 0 mesh; 1 sphere `f64 × 4`; 2 plane `f64 × 7`; 3 quadric `f64 × 16` |
//! | 13 | Animation | `f64 duration, u64 n`, n × (string target, `u64 n` times f64, `u64 width`, `u64 n` values f64) |
//! | 14 | Scalar | `f64` |
//! | 15 | Integer | `i64` |
//! | 16 | Bool | `u8` 0 or 1 |
//! | 17 | Text | string |
//! | 18 | Metrics | `u64 n`, n × (string name, `f64`), names strictly increasing |
//! | 19 | List | element type, `u64 n`, n values |
//! | 20 | Bvh | nodes (`u64 n`, n × (`f32 × 3` min, `u32` offset, `f32 × 3` max, `u32` count)), primitives (`u64 n`, `u32` each), corners (`u64 n`, `f32 × 9` each), mesh |
//!
//! A camera is `u8 model (0 SIMPLE_PINHOLE, 1 PINHOLE, 2 SIMPLE_RADIAL, 3 RADIAL, 4 OPENCV,
//! 5 radial–tangential with skew, 6 fisheye with skew), u32
//! width, u32 height, u64 n`, n f64 params. An element type is a `u8`: the value tag of the type
//! above (0..=18 and 20, the non-list types in the order of [`SCALAR_PORT_TYPES`] with 19 left
//! out), 19 = `List` followed by its element type.
//!
//! Floats are stored by their bits, so NaN payloads and `-0.0` survive a round trip.
//!
//! # Hostile input
//! [`decode_values`] never panics and never allocates more than a small multiple of the input
//! size: every length is checked against the bytes left before anything is allocated,
//! containers of values are grown as items actually decode, nesting (lists and list types) is
//! limited to [`MAX_DEPTH`] lists inside one another, and unknown tags, versions and trailing
//! bytes are errors. Values nested deeper than that still encode, but do not decode; callers
//! using this as a cache treat that as a miss.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::types::{PortType, SCALAR_PORT_TYPES};
use crate::value::{
    Animation, AnimationChannel, Bvh, BvhNode, Camera, CameraModel, Channels, Depth, Descriptors,
    Image, Keypoint, Light, Match, Material, Matrix, Mesh, Metrics, PixelData, PointCloud, Pose,
    ReconImage, ReconPoint, Reconstruction, Scene, SceneCamera, SceneObject, Shading, Shape,
    Texture, TextureFilter, TextureWrap, TrackElement, Tracks, Value, ValueList,
};

/// First four bytes of every encoding.
pub const MAGIC: [u8; 4] = *b"OCVL";

/// The format version written, and the only one read. Version 3 added mesh tangents (mesh
/// flag 8). Version 2 files would still decode, but `io.read_mesh` results cached by a version 2
/// build lack the tangents a PLY file may carry (and the STL support), so they are rejected as
/// [`CodecError::UnsupportedVersion`] and recomputed, like any other cache miss.
pub const FORMAT_VERSION: u32 = 3;

/// Most lists nested inside one another (and so most `List<…>` levels in an element type) that
/// decode.
pub const MAX_DEPTH: usize = 32;

/// Containers of non-fixed-size items start with at most this capacity and grow as items decode.
const PREALLOC_MAX: usize = 1024;

/// Errors decoding values.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// The bytes do not start with [`MAGIC`].
    #[error("not an Ocellus value encoding (missing `OCVL` magic)")]
    BadMagic,
    /// The encoding is of a version this build does not read.
    #[error(
        "value encoding version {found} is not supported (this build reads version {supported})"
    )]
    UnsupportedVersion {
        /// Version in the data.
        found: u32,
        /// Version this build reads.
        supported: u32,
    },
    /// The data ends, or a length points past its end.
    #[error("truncated at byte {offset}: {what} needs {needed} bytes, {remaining} left")]
    Truncated {
        /// Where the item starts.
        offset: usize,
        /// What was being read.
        what: &'static str,
        /// Bytes it needs (saturated at `u64::MAX`).
        needed: u64,
        /// Bytes left.
        remaining: usize,
    },
    /// A tag byte names nothing known.
    #[error("unknown {what} tag {tag} at byte {offset}")]
    UnknownTag {
        /// Where the tag is.
        offset: usize,
        /// What kind of tag.
        what: &'static str,
        /// The tag.
        tag: u8,
    },
    /// A field holds an impossible value.
    #[error("invalid {what} at byte {offset}: {reason}")]
    Invalid {
        /// Where the field is.
        offset: usize,
        /// The field.
        what: &'static str,
        /// Why it is invalid.
        reason: String,
    },
    /// Values or types are nested deeper than [`MAX_DEPTH`].
    #[error("values nested deeper than {limit} levels")]
    TooDeep {
        /// The limit.
        limit: usize,
    },
    /// Bytes remain after the declared number of values.
    #[error("{count} unexpected bytes after the last value (at byte {offset})")]
    TrailingBytes {
        /// Where they start.
        offset: usize,
        /// How many.
        count: usize,
    },
}

mod tag {
    pub const IMAGE: u8 = 0;
    pub const KEYPOINTS: u8 = 1;
    pub const DESCRIPTORS: u8 = 2;
    pub const MATCHES: u8 = 3;
    pub const MATRIX: u8 = 4;
    pub const CAMERA: u8 = 5;
    pub const POSE: u8 = 6;
    pub const POINTS2D: u8 = 7;
    pub const POINT_CLOUD: u8 = 8;
    pub const TRACKS: u8 = 9;
    pub const RECONSTRUCTION: u8 = 10;
    pub const MESH: u8 = 11;
    pub const SCENE: u8 = 12;
    pub const ANIMATION: u8 = 13;
    pub const SCALAR: u8 = 14;
    pub const INTEGER: u8 = 15;
    pub const BOOL: u8 = 16;
    pub const TEXT: u8 = 17;
    pub const METRICS: u8 = 18;
    pub const LIST: u8 = 19;
    pub const BVH: u8 = 20;
}

/// Port type tag of `List`; the non-list types are their index in [`SCALAR_PORT_TYPES`], plus
/// one from `List`'s index on (types added after `List` keep the tags of their values).
const LIST_TYPE_TAG: u8 = 19;

/// The element-type tag of the non-list type at `index` of [`SCALAR_PORT_TYPES`].
fn scalar_type_tag(index: usize) -> u8 {
    let tag = index as u8;
    if tag >= LIST_TYPE_TAG { tag + 1 } else { tag }
}

/// The index in [`SCALAR_PORT_TYPES`] of the element-type tag `tag` (not `List`'s).
fn scalar_type_index(tag: u8) -> usize {
    usize::from(if tag > LIST_TYPE_TAG { tag - 1 } else { tag })
}

/// Encoded sizes of fixed-size items, used to bound lengths before allocating.
mod size {
    pub const KEYPOINT: usize = 24;
    pub const MATCH: usize = 12;
    pub const TRACK_ELEMENT: usize = 8;
    pub const POINT2D: usize = 16;
    pub const RGB8: usize = 3;
    pub const OBSERVATION: usize = 25;
    pub const POSE: usize = 56;
    /// Smallest encodings of variable-size items.
    pub const MIN_VALUE: usize = 2;
    pub const MIN_CAMERA: usize = 17;
    pub const MIN_RECON_CAMERA: usize = 4 + MIN_CAMERA;
    pub const MIN_RECON_IMAGE: usize = 4 + 4 + 8 + POSE + 8;
    pub const MIN_RECON_POINT: usize = 8 + 24 + 3 + 8 + 8;
    pub const MIN_MESH: usize = 8 + 8 + 1;
    pub const MIN_MATERIAL: usize = 8 + 12 + 5 + 4 + 4 + 12 + 20 + 1;
    pub const MIN_SCENE_OBJECT: usize = 8 + 1 + MIN_MESH + POSE + 8 + 4;
    pub const MIN_LIGHT: usize = 1 + 12 + 1;
    pub const MIN_SCENE_CAMERA: usize = MIN_CAMERA + POSE + 16;
    pub const MIN_CHANNEL: usize = 8 + 8 + 8 + 8;
    pub const MIN_METRIC: usize = 8 + 8;
    pub const MIN_TRACK: usize = 8;
}

/// Encodes values (see the [module docs](self) for the format).
pub fn encode_values(values: &[Value]) -> Vec<u8> {
    let mut e = Encoder {
        out: Vec::with_capacity(16 + values.iter().map(Value::byte_size).sum::<usize>()),
    };
    e.out.extend_from_slice(&MAGIC);
    e.u32(FORMAT_VERSION);
    e.len(values.len());
    for value in values {
        e.value(value);
    }
    e.out
}

struct Encoder {
    out: Vec<u8>,
}

/// Appends `values` as little-endian `N`-byte items in one resize, so the loop compiles to a
/// bulk copy.
fn put_bulk<T: Copy, const N: usize>(
    out: &mut Vec<u8>,
    values: &[T],
    to_le: impl Fn(T) -> [u8; N],
) {
    let start = out.len();
    out.resize(start + values.len() * N, 0);
    for (dst, v) in out[start..].as_chunks_mut::<N>().0.iter_mut().zip(values) {
        *dst = to_le(*v);
    }
}

impl Encoder {
    fn u8(&mut self, v: u8) {
        self.out.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    fn len(&mut self, n: usize) {
        self.u64(n as u64);
    }
    fn f32(&mut self, v: f32) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    fn str(&mut self, s: &str) {
        self.len(s.len());
        self.out.extend_from_slice(s.as_bytes());
    }
    fn f32s(&mut self, v: &[f32]) {
        put_bulk(&mut self.out, v, f32::to_le_bytes);
    }
    fn f64s(&mut self, v: &[f64]) {
        put_bulk(&mut self.out, v, f64::to_le_bytes);
    }
    fn u32s(&mut self, v: &[u32]) {
        put_bulk(&mut self.out, v, u32::to_le_bytes);
    }
    fn f64_vec(&mut self, v: &[f64]) {
        self.len(v.len());
        self.f64s(v);
    }
    fn pose(&mut self, p: &Pose) {
        self.f64s(&p.rotation);
        self.f64s(&p.translation);
    }
    fn camera(&mut self, c: &Camera) {
        self.u8(camera_model_tag(c.model));
        self.u32(c.width);
        self.u32(c.height);
        self.f64_vec(&c.params);
    }
    fn port_type(&mut self, t: &PortType) {
        match t {
            PortType::List(inner) => {
                self.u8(LIST_TYPE_TAG);
                self.port_type(inner);
            }
            other => {
                let index = SCALAR_PORT_TYPES
                    .iter()
                    .position(|s| s == other)
                    .unwrap_or_default();
                self.u8(scalar_type_tag(index));
            }
        }
    }
    fn mesh(&mut self, m: &Mesh) {
        self.len(m.positions.len());
        self.f32s(m.positions.as_flattened());
        self.len(m.triangles.len());
        self.u32s(m.triangles.as_flattened());
        let flags = u8::from(m.normals.is_some())
            | u8::from(m.uvs.is_some()) << 1
            | u8::from(m.colors.is_some()) << 2
            | u8::from(m.tangents.is_some()) << 3;
        self.u8(flags);
        if let Some(n) = &m.normals {
            self.len(n.len());
            self.f32s(n.as_flattened());
        }
        if let Some(uv) = &m.uvs {
            self.len(uv.len());
            self.f32s(uv.as_flattened());
        }
        if let Some(c) = &m.colors {
            self.len(c.len());
            self.f32s(c.as_flattened());
        }
        if let Some(t) = &m.tangents {
            self.len(t.len());
            self.f32s(t.as_flattened());
        }
    }

    fn image(&mut self, image: &Image) {
        self.len(image.width());
        self.len(image.height());
        self.u8(match image.channels() {
            Channels::Gray => 0,
            Channels::Rgb => 1,
            Channels::Rgba => 2,
        });
        self.u8(match image.depth() {
            Depth::U8 => 0,
            Depth::U16 => 1,
            Depth::F32 => 2,
        });
        match image.data() {
            PixelData::U8(v) => self.out.extend_from_slice(v),
            PixelData::U16(v) => put_bulk(&mut self.out, v, u16::to_le_bytes),
            PixelData::F32(v) => self.f32s(v),
        }
    }

    fn texture(&mut self, t: Option<&Texture>) {
        let Some(t) = t else {
            self.u8(0);
            return;
        };
        self.u8(1);
        self.image(&t.image);
        self.u8(t.wrap as u8);
        self.u8(t.filter as u8);
        self.f32s(&t.border);
        self.u32(t.max_anisotropy);
        self.f32s(&t.uv_scale);
    }

    fn value(&mut self, value: &Value) {
        match value {
            Value::Image(image) => {
                self.u8(tag::IMAGE);
                self.image(image);
            }
            Value::Keypoints(k) => {
                self.u8(tag::KEYPOINTS);
                self.len(k.len());
                self.out.reserve(k.len() * size::KEYPOINT);
                for kp in k.iter() {
                    self.f32s(&[kp.x, kp.y, kp.size, kp.angle, kp.response]);
                    self.out.extend_from_slice(&kp.octave.to_le_bytes());
                }
            }
            Value::Descriptors(d) => {
                self.u8(tag::DESCRIPTORS);
                match d.as_ref() {
                    Descriptors::Float { dim, data } => {
                        self.u8(0);
                        self.len(*dim);
                        self.len(data.len());
                        self.f32s(data);
                    }
                    Descriptors::Binary { bytes, data } => {
                        self.u8(1);
                        self.len(*bytes);
                        self.len(data.len());
                        self.out.extend_from_slice(data);
                    }
                }
            }
            Value::Matches(m) => {
                self.u8(tag::MATCHES);
                self.len(m.len());
                self.out.reserve(m.len() * size::MATCH);
                for mt in m.iter() {
                    self.u32(mt.query);
                    self.u32(mt.train);
                    self.f32(mt.distance);
                }
            }
            Value::Matrix(m) => {
                self.u8(tag::MATRIX);
                self.len(m.rows);
                self.len(m.cols);
                self.f64s(&m.data);
            }
            Value::Camera(c) => {
                self.u8(tag::CAMERA);
                self.camera(c);
            }
            Value::Pose(p) => {
                self.u8(tag::POSE);
                self.pose(p);
            }
            Value::Points2D(p) => {
                self.u8(tag::POINTS2D);
                self.len(p.len());
                self.f64s(p.as_flattened());
            }
            Value::PointCloud(p) => {
                self.u8(tag::POINT_CLOUD);
                self.len(p.positions.len());
                self.f32s(p.positions.as_flattened());
                self.u8(u8::from(p.colors.is_some()) | u8::from(p.normals.is_some()) << 1);
                if let Some(c) = &p.colors {
                    self.len(c.len());
                    self.out.extend_from_slice(c.as_flattened());
                }
                if let Some(n) = &p.normals {
                    self.len(n.len());
                    self.f32s(n.as_flattened());
                }
            }
            Value::Tracks(t) => {
                self.u8(tag::TRACKS);
                self.len(t.tracks.len());
                for track in &t.tracks {
                    self.len(track.len());
                    for el in track {
                        self.u32(el.image);
                        self.u32(el.keypoint);
                    }
                }
            }
            Value::Reconstruction(r) => {
                self.u8(tag::RECONSTRUCTION);
                self.len(r.cameras.len());
                for (id, camera) in &r.cameras {
                    self.u32(*id);
                    self.camera(camera);
                }
                self.len(r.images.len());
                for image in &r.images {
                    self.u32(image.id);
                    self.u32(image.camera_id);
                    self.str(&image.name);
                    self.pose(&image.camera_from_world);
                    self.len(image.points2d.len());
                    for ([x, y], point) in &image.points2d {
                        self.f64(*x);
                        self.f64(*y);
                        self.u8(u8::from(point.is_some()));
                        self.u64(point.unwrap_or(0));
                    }
                }
                self.len(r.points.len());
                for p in &r.points {
                    self.u64(p.id);
                    self.f64s(&p.position);
                    self.out.extend_from_slice(&p.color);
                    self.f64(p.error_px);
                    self.len(p.track.len());
                    for (image, index) in &p.track {
                        self.u32(*image);
                        self.u32(*index);
                    }
                }
            }
            Value::Mesh(m) => {
                self.u8(tag::MESH);
                self.mesh(m);
            }
            Value::Bvh(b) => {
                self.u8(tag::BVH);
                self.len(b.nodes.len());
                for n in &b.nodes {
                    self.f32s(&n.min);
                    self.u32(n.offset);
                    self.f32s(&n.max);
                    self.u32(n.count);
                }
                self.len(b.primitives.len());
                self.u32s(&b.primitives);
                self.len(b.corners.len());
                self.f32s(b.corners.as_flattened().as_flattened());
                self.mesh(&b.mesh);
            }
            Value::Scene(s) => {
                self.u8(tag::SCENE);
                self.len(s.materials.len());
                for m in &s.materials {
                    self.str(&m.name);
                    self.f32s(&m.albedo);
                    self.texture(m.albedo_texture.as_ref());
                    self.texture(m.normal_texture.as_ref());
                    self.f32(m.roughness);
                    self.texture(m.roughness_texture.as_ref());
                    self.f32(m.metalness);
                    self.texture(m.metalness_texture.as_ref());
                    self.f32s(&m.emission);
                    self.texture(m.emission_texture.as_ref());
                    self.f32s(&[m.specular, m.shininess, m.transmission, m.ior, m.opacity]);
                    self.u8(m.shading as u8);
                }
                self.len(s.objects.len());
                for o in &s.objects {
                    self.str(&o.name);
                    match &o.shape {
                        Shape::Mesh(m) => {
                            self.u8(0);
                            self.mesh(m);
                        }
                        Shape::Sphere { center, radius } => {
                            self.u8(1);
                            self.f64s(center);
                            self.f64(*radius);
                        }
                        Shape::Plane {
                            point,
                            normal,
                            half_extent,
                        } => {
                            self.u8(2);
                            self.f64s(point);
                            self.f64s(normal);
                            self.f64(*half_extent);
                        }
                        Shape::Quadric {
                            coefficients,
                            min,
                            max,
                        } => {
                            self.u8(3);
                            self.f64s(coefficients);
                            self.f64s(min);
                            self.f64s(max);
                        }
                    }
                    self.pose(&o.world_from_object);
                    self.f64(o.scale);
                    self.u32(o.material);
                }
                self.len(s.lights.len());
                for light in &s.lights {
                    match light {
                        Light::Point {
                            position,
                            intensity,
                        } => {
                            self.u8(0);
                            self.f64s(position);
                            self.f32s(intensity);
                        }
                        Light::Directional {
                            direction,
                            irradiance,
                        } => {
                            self.u8(1);
                            self.f64s(direction);
                            self.f32s(irradiance);
                        }
                        Light::Area {
                            corner,
                            edge_u,
                            edge_v,
                            radiance,
                        } => {
                            self.u8(2);
                            self.f64s(corner);
                            self.f64s(edge_u);
                            self.f64s(edge_v);
                            self.f32s(radiance);
                        }
                        Light::Environment { radiance, map } => {
                            self.u8(3);
                            self.f32s(radiance);
                            self.texture(map.as_ref());
                        }
                    }
                }
                self.len(s.cameras.len());
                for c in &s.cameras {
                    self.camera(&c.camera);
                    self.pose(&c.camera_from_world);
                    self.f64(c.aperture_radius);
                    self.f64(c.focus_distance);
                }
            }
            Value::Animation(a) => {
                self.u8(tag::ANIMATION);
                self.f64(a.duration);
                self.len(a.channels.len());
                for c in &a.channels {
                    self.str(&c.target);
                    self.f64_vec(&c.times);
                    self.len(c.width);
                    self.f64_vec(&c.values);
                }
            }
            Value::Scalar(x) => {
                self.u8(tag::SCALAR);
                self.f64(*x);
            }
            Value::Integer(i) => {
                self.u8(tag::INTEGER);
                self.out.extend_from_slice(&i.to_le_bytes());
            }
            Value::Bool(b) => {
                self.u8(tag::BOOL);
                self.u8(u8::from(*b));
            }
            Value::Text(t) => {
                self.u8(tag::TEXT);
                self.str(t);
            }
            Value::Metrics(m) => {
                self.u8(tag::METRICS);
                self.len(m.len());
                for (name, v) in m.iter() {
                    self.str(name);
                    self.f64(*v);
                }
            }
            Value::List(list) => {
                self.u8(tag::LIST);
                self.port_type(&list.element);
                self.len(list.items.len());
                for item in &list.items {
                    self.value(item);
                }
            }
        }
    }
}

fn camera_model_tag(model: CameraModel) -> u8 {
    match model {
        CameraModel::SimplePinhole => 0,
        CameraModel::Pinhole => 1,
        CameraModel::SimpleRadial => 2,
        CameraModel::Radial => 3,
        CameraModel::OpenCv => 4,
        CameraModel::RadialTangential => 5,
        CameraModel::Fisheye => 6,
    }
}

/// Decodes what [`encode_values`] wrote. Never panics; see the [module docs](self) for the
/// guarantees on hostile input.
pub fn decode_values(bytes: &[u8]) -> Result<Vec<Value>, CodecError> {
    if !bytes.starts_with(&MAGIC) {
        return Err(CodecError::BadMagic);
    }
    let mut d = Decoder {
        bytes,
        pos: MAGIC.len(),
    };
    let version = d.u32("version")?;
    if version != FORMAT_VERSION {
        return Err(CodecError::UnsupportedVersion {
            found: version,
            supported: FORMAT_VERSION,
        });
    }
    let count = d.len(size::MIN_VALUE, "value count")?;
    let mut values = Vec::with_capacity(count.min(PREALLOC_MAX));
    for _ in 0..count {
        values.push(d.value(0)?);
    }
    if d.pos != bytes.len() {
        return Err(CodecError::TrailingBytes {
            offset: d.pos,
            count: bytes.len() - d.pos,
        });
    }
    Ok(values)
}

struct Decoder<'a> {
    bytes: &'a [u8],
    pos: usize,
}

fn f32x3(b: &[u8; 12]) -> [f32; 3] {
    std::array::from_fn(|i| {
        f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    })
}

fn f32x4(b: &[u8; 16]) -> [f32; 4] {
    std::array::from_fn(|i| {
        f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    })
}

fn f32x2(b: &[u8; 8]) -> [f32; 2] {
    std::array::from_fn(|i| {
        f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    })
}

fn u32x3(b: &[u8; 12]) -> [u32; 3] {
    std::array::from_fn(|i| {
        u32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    })
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    if let Some(s) = b.get(at..at + 4) {
        a.copy_from_slice(s);
    }
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    if let Some(s) = b.get(at..at + 8) {
        a.copy_from_slice(s);
    }
    u64::from_le_bytes(a)
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_bits(u64_at(b, at))
}

impl<'a> Decoder<'a> {
    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn truncated(&self, what: &'static str, needed: u64) -> CodecError {
        CodecError::Truncated {
            offset: self.pos,
            what,
            needed,
            remaining: self.remaining(),
        }
    }

    fn invalid(&self, offset: usize, what: &'static str, reason: impl Into<String>) -> CodecError {
        CodecError::Invalid {
            offset,
            what,
            reason: reason.into(),
        }
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], CodecError> {
        let slice = self
            .bytes
            .get(self.pos..)
            .and_then(|rest| rest.get(..n))
            .ok_or_else(|| self.truncated(what, n as u64))?;
        self.pos += n;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CodecError> {
        let s = self.take(N, what)?;
        s.first_chunk::<N>()
            .copied()
            .ok_or_else(|| self.truncated(what, N as u64))
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, CodecError> {
        Ok(self.array::<1>(what)?[0])
    }
    fn u32(&mut self, what: &'static str) -> Result<u32, CodecError> {
        self.array(what).map(u32::from_le_bytes)
    }
    fn u64(&mut self, what: &'static str) -> Result<u64, CodecError> {
        self.array(what).map(u64::from_le_bytes)
    }
    fn f64(&mut self, what: &'static str) -> Result<f64, CodecError> {
        self.array(what).map(f64::from_le_bytes)
    }

    /// A `u64` that is a size but not a count of following items (a width, a descriptor size).
    fn usize(&mut self, what: &'static str) -> Result<usize, CodecError> {
        let at = self.pos;
        let v = self.u64(what)?;
        usize::try_from(v).map_err(|_| self.invalid(at, what, format!("{v} is too large")))
    }

    /// A count of following items each taking at least `min_item_bytes`, checked against the
    /// bytes left so that nothing is allocated for data that is not there.
    fn len(&mut self, min_item_bytes: usize, what: &'static str) -> Result<usize, CodecError> {
        let at = self.pos;
        let n = self.u64(what)?;
        let needed = n.saturating_mul(min_item_bytes as u64);
        if needed > self.remaining() as u64 {
            return Err(CodecError::Truncated {
                offset: at,
                what,
                needed,
                remaining: self.remaining(),
            });
        }
        // `needed` fits in the remaining byte count, hence in usize.
        Ok(n as usize)
    }

    /// `n` fixed-size items of `N` bytes each, converted by `f`.
    fn items<T, const N: usize>(
        &mut self,
        n: usize,
        what: &'static str,
        f: impl Fn(&[u8; N]) -> T,
    ) -> Result<Vec<T>, CodecError> {
        let bytes = n
            .checked_mul(N)
            .ok_or_else(|| self.truncated(what, u64::MAX))?;
        let raw = self.take(bytes, what)?;
        Ok(raw.as_chunks::<N>().0.iter().map(f).collect())
    }

    /// A length followed by that many `N`-byte items.
    fn counted<T, const N: usize>(
        &mut self,
        what: &'static str,
        f: impl Fn(&[u8; N]) -> T,
    ) -> Result<Vec<T>, CodecError> {
        let n = self.len(N, what)?;
        self.items(n, what, f)
    }

    fn f64_vec(&mut self, what: &'static str) -> Result<Vec<f64>, CodecError> {
        self.counted(what, |b: &[u8; 8]| f64::from_le_bytes(*b))
    }

    fn string(&mut self, what: &'static str) -> Result<String, CodecError> {
        let n = self.len(1, what)?;
        let at = self.pos;
        let raw = self.take(n, what)?;
        String::from_utf8(raw.to_vec()).map_err(|_| self.invalid(at, what, "not UTF-8"))
    }

    fn bool_flag(&mut self, what: &'static str) -> Result<bool, CodecError> {
        let at = self.pos;
        match self.u8(what)? {
            0 => Ok(false),
            1 => Ok(true),
            other => Err(self.invalid(at, what, format!("{other} is neither 0 nor 1"))),
        }
    }

    fn flags(&mut self, allowed: u8, what: &'static str) -> Result<u8, CodecError> {
        let at = self.pos;
        let flags = self.u8(what)?;
        if flags & !allowed != 0 {
            return Err(self.invalid(at, what, format!("unknown flag bits {flags:#04x}")));
        }
        Ok(flags)
    }

    fn pose(&mut self) -> Result<Pose, CodecError> {
        let b = self.array::<{ size::POSE }>("pose")?;
        Ok(Pose {
            rotation: std::array::from_fn(|i| f64_at(&b, 8 * i)),
            translation: std::array::from_fn(|i| f64_at(&b, 32 + 8 * i)),
        })
    }

    fn camera(&mut self) -> Result<Camera, CodecError> {
        let at = self.pos;
        let model = match self.u8("camera model")? {
            0 => CameraModel::SimplePinhole,
            1 => CameraModel::Pinhole,
            2 => CameraModel::SimpleRadial,
            3 => CameraModel::Radial,
            4 => CameraModel::OpenCv,
            5 => CameraModel::RadialTangential,
            6 => CameraModel::Fisheye,
            tag => {
                return Err(CodecError::UnknownTag {
                    offset: at,
                    what: "camera model",
                    tag,
                });
            }
        };
        Ok(Camera {
            model,
            width: self.u32("camera width")?,
            height: self.u32("camera height")?,
            params: self.f64_vec("camera params")?,
        })
    }

    fn port_type(&mut self, depth: usize) -> Result<PortType, CodecError> {
        if depth > MAX_DEPTH {
            return Err(CodecError::TooDeep { limit: MAX_DEPTH });
        }
        let at = self.pos;
        let t = self.u8("element type")?;
        if t == LIST_TYPE_TAG {
            return Ok(self.port_type(depth + 1)?.list_of());
        }
        SCALAR_PORT_TYPES
            .get(scalar_type_index(t))
            .cloned()
            .ok_or(CodecError::UnknownTag {
                offset: at,
                what: "element type",
                tag: t,
            })
    }

    fn mesh(&mut self) -> Result<Mesh, CodecError> {
        let positions = self.counted("mesh positions", f32x3)?;
        let triangles = self.counted("mesh triangles", u32x3)?;
        let flags = self.flags(0b1111, "mesh flags")?;
        let normals = if flags & 1 != 0 {
            Some(self.counted("mesh normals", f32x3)?)
        } else {
            None
        };
        let uvs = if flags & 2 != 0 {
            Some(self.counted("mesh uvs", f32x2)?)
        } else {
            None
        };
        let colors = if flags & 4 != 0 {
            Some(self.counted("mesh colors", f32x3)?)
        } else {
            None
        };
        let tangents = if flags & 8 != 0 {
            Some(self.counted("mesh tangents", f32x4)?)
        } else {
            None
        };
        Ok(Mesh {
            positions,
            triangles,
            normals,
            uvs,
            colors,
            tangents,
        })
    }

    fn image(&mut self) -> Result<Image, CodecError> {
        let at = self.pos;
        let width = self.usize("image width")?;
        let height = self.usize("image height")?;
        let channels = match self.u8("image channels")? {
            0 => Channels::Gray,
            1 => Channels::Rgb,
            2 => Channels::Rgba,
            tag => {
                return Err(CodecError::UnknownTag {
                    offset: at + 16,
                    what: "image channels",
                    tag,
                });
            }
        };
        let depth_at = self.pos;
        let depth = self.u8("image depth")?;
        let n = Image::sample_count(width, height, channels)
            .map_err(|e| self.invalid(at, "image size", e.to_string()))?;
        let data = match depth {
            0 => PixelData::U8(self.take(n, "image samples")?.to_vec()),
            1 => PixelData::U16(
                self.items(n, "image samples", |b: &[u8; 2]| u16::from_le_bytes(*b))?,
            ),
            2 => PixelData::F32(
                self.items(n, "image samples", |b: &[u8; 4]| f32::from_le_bytes(*b))?,
            ),
            tag => {
                return Err(CodecError::UnknownTag {
                    offset: depth_at,
                    what: "image depth",
                    tag,
                });
            }
        };
        Image::new(width, height, channels, data)
            .map_err(|e| self.invalid(at, "image", e.to_string()))
    }

    fn value(&mut self, depth: usize) -> Result<Value, CodecError> {
        if depth > MAX_DEPTH {
            return Err(CodecError::TooDeep { limit: MAX_DEPTH });
        }
        let at = self.pos;
        let t = self.u8("value tag")?;
        Ok(match t {
            tag::IMAGE => Value::image(self.image()?),
            tag::KEYPOINTS => {
                let k = self.counted("keypoints", |b: &[u8; size::KEYPOINT]| Keypoint {
                    x: f32::from_bits(u32_at(b, 0)),
                    y: f32::from_bits(u32_at(b, 4)),
                    size: f32::from_bits(u32_at(b, 8)),
                    angle: f32::from_bits(u32_at(b, 12)),
                    response: f32::from_bits(u32_at(b, 16)),
                    octave: u32_at(b, 20) as i32,
                })?;
                Value::Keypoints(Arc::new(k))
            }
            tag::DESCRIPTORS => {
                let kind_at = self.pos;
                let kind = self.u8("descriptor kind")?;
                let per_row = self.usize("descriptor size")?;
                let d = match kind {
                    0 => Descriptors::Float {
                        dim: per_row,
                        data: self
                            .counted("descriptor data", |b: &[u8; 4]| f32::from_le_bytes(*b))?,
                    },
                    1 => {
                        let n = self.len(1, "descriptor data")?;
                        Descriptors::Binary {
                            bytes: per_row,
                            data: self.take(n, "descriptor data")?.to_vec(),
                        }
                    }
                    tag => {
                        return Err(CodecError::UnknownTag {
                            offset: kind_at,
                            what: "descriptor kind",
                            tag,
                        });
                    }
                };
                Value::Descriptors(Arc::new(d))
            }
            tag::MATCHES => {
                let m = self.counted("matches", |b: &[u8; size::MATCH]| Match {
                    query: u32_at(b, 0),
                    train: u32_at(b, 4),
                    distance: f32::from_bits(u32_at(b, 8)),
                })?;
                Value::Matches(Arc::new(m))
            }
            tag::MATRIX => {
                let rows = self.usize("matrix rows")?;
                let cols = self.usize("matrix cols")?;
                let n = rows
                    .checked_mul(cols)
                    .ok_or_else(|| self.invalid(at, "matrix", "rows × cols overflows"))?;
                let data = self.items(n, "matrix data", |b: &[u8; 8]| f64::from_le_bytes(*b))?;
                Value::Matrix(Arc::new(Matrix { rows, cols, data }))
            }
            tag::CAMERA => Value::Camera(Arc::new(self.camera()?)),
            tag::POSE => Value::Pose(self.pose()?),
            tag::POINTS2D => {
                let p = self.counted("points", |b: &[u8; size::POINT2D]| {
                    [f64_at(b, 0), f64_at(b, 8)]
                })?;
                Value::Points2D(Arc::new(p))
            }
            tag::POINT_CLOUD => {
                let positions = self.counted("cloud positions", f32x3)?;
                let flags = self.flags(0b11, "cloud flags")?;
                let colors = if flags & 1 != 0 {
                    Some(self.counted("cloud colors", |b: &[u8; size::RGB8]| *b)?)
                } else {
                    None
                };
                let normals = if flags & 2 != 0 {
                    Some(self.counted("cloud normals", f32x3)?)
                } else {
                    None
                };
                Value::PointCloud(Arc::new(PointCloud {
                    positions,
                    colors,
                    normals,
                }))
            }
            tag::TRACKS => {
                let n = self.len(size::MIN_TRACK, "tracks")?;
                let mut tracks = Vec::with_capacity(n.min(PREALLOC_MAX));
                for _ in 0..n {
                    tracks.push(self.counted("track", |b: &[u8; size::TRACK_ELEMENT]| {
                        TrackElement {
                            image: u32_at(b, 0),
                            keypoint: u32_at(b, 4),
                        }
                    })?);
                }
                Value::Tracks(Arc::new(Tracks { tracks }))
            }
            tag::RECONSTRUCTION => Value::Reconstruction(Arc::new(self.reconstruction()?)),
            tag::MESH => Value::Mesh(Arc::new(self.mesh()?)),
            tag::BVH => {
                let nodes = self.counted("bvh nodes", |b: &[u8; 32]| BvhNode {
                    min: std::array::from_fn(|i| f32::from_bits(u32_at(b, 4 * i))),
                    offset: u32_at(b, 12),
                    max: std::array::from_fn(|i| f32::from_bits(u32_at(b, 16 + 4 * i))),
                    count: u32_at(b, 28),
                })?;
                let primitives = self.counted("bvh primitives", |b: &[u8; 4]| u32_at(b, 0))?;
                let corners = self.counted("bvh corners", |b: &[u8; 36]| {
                    std::array::from_fn(|v| {
                        std::array::from_fn(|i| f32::from_bits(u32_at(b, 12 * v + 4 * i)))
                    })
                })?;
                let mesh = Arc::new(self.mesh()?);
                Value::Bvh(Arc::new(Bvh {
                    nodes,
                    primitives,
                    corners,
                    mesh,
                }))
            }
            tag::SCENE => Value::Scene(Arc::new(self.scene()?)),
            tag::ANIMATION => {
                let duration = self.f64("animation duration")?;
                let n = self.len(size::MIN_CHANNEL, "animation channels")?;
                let mut channels = Vec::with_capacity(n.min(PREALLOC_MAX));
                for _ in 0..n {
                    channels.push(AnimationChannel {
                        target: self.string("channel target")?,
                        times: self.f64_vec("channel times")?,
                        width: self.usize("channel width")?,
                        values: self.f64_vec("channel values")?,
                    });
                }
                Value::Animation(Arc::new(Animation { duration, channels }))
            }
            tag::SCALAR => Value::Scalar(self.f64("scalar")?),
            tag::INTEGER => Value::Integer(i64::from_le_bytes(self.array("integer")?)),
            tag::BOOL => Value::Bool(self.bool_flag("bool")?),
            tag::TEXT => Value::Text(self.string("text")?.into()),
            tag::METRICS => {
                let n = self.len(size::MIN_METRIC, "metrics")?;
                let mut metrics = Metrics::new();
                for _ in 0..n {
                    let key_at = self.pos;
                    let key = self.string("metric name")?;
                    let v = self.f64("metric value")?;
                    if metrics
                        .last_key_value()
                        .is_some_and(|(last, _)| *last >= key)
                    {
                        return Err(self.invalid(
                            key_at,
                            "metric name",
                            format!("{key:?} is out of order or repeated"),
                        ));
                    }
                    metrics.insert(key, v);
                }
                Value::metrics(metrics)
            }
            tag::LIST => {
                let element = self.port_type(depth + 1)?;
                let n = self.len(size::MIN_VALUE, "list")?;
                let mut items = Vec::with_capacity(n.min(PREALLOC_MAX));
                for _ in 0..n {
                    items.push(self.value(depth + 1)?);
                }
                Value::List(Arc::new(ValueList { element, items }))
            }
            other => {
                return Err(CodecError::UnknownTag {
                    offset: at,
                    what: "value",
                    tag: other,
                });
            }
        })
    }

    fn reconstruction(&mut self) -> Result<Reconstruction, CodecError> {
        let n = self.len(size::MIN_RECON_CAMERA, "cameras")?;
        let mut cameras = BTreeMap::new();
        for _ in 0..n {
            let at = self.pos;
            let id = self.u32("camera id")?;
            let camera = self.camera()?;
            if cameras.insert(id, camera).is_some() {
                return Err(self.invalid(at, "camera id", format!("{id} is repeated")));
            }
        }
        let n = self.len(size::MIN_RECON_IMAGE, "images")?;
        let mut images = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let id = self.u32("image id")?;
            let camera_id = self.u32("image camera id")?;
            let name = self.string("image name")?;
            let camera_from_world = self.pose()?;
            let count = self.len(size::OBSERVATION, "image points")?;
            let raw = self.take(count * size::OBSERVATION, "image points")?;
            let mut points2d = Vec::with_capacity(count);
            for (i, b) in raw
                .as_chunks::<{ size::OBSERVATION }>()
                .0
                .iter()
                .enumerate()
            {
                let point = match b[16] {
                    0 => None,
                    1 => Some(u64_at(b, 17)),
                    other => {
                        let offset = self.pos - raw.len() + i * size::OBSERVATION + 16;
                        return Err(self.invalid(
                            offset,
                            "observation flag",
                            format!("{other} is neither 0 nor 1"),
                        ));
                    }
                };
                points2d.push(([f64_at(b, 0), f64_at(b, 8)], point));
            }
            images.push(ReconImage {
                id,
                camera_id,
                name,
                camera_from_world,
                points2d,
            });
        }
        let n = self.len(size::MIN_RECON_POINT, "points")?;
        let mut points = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let id = self.u64("point id")?;
            let b = self.array::<24>("point position")?;
            let position = std::array::from_fn(|i| f64_at(&b, 8 * i));
            let color = self.array::<3>("point color")?;
            let error_px = self.f64("point error")?;
            let track = self.counted("point track", |b: &[u8; 8]| (u32_at(b, 0), u32_at(b, 4)))?;
            points.push(ReconPoint {
                id,
                position,
                color,
                error_px,
                track,
            });
        }
        Ok(Reconstruction {
            cameras,
            images,
            points,
        })
    }

    fn f32(&mut self, what: &'static str) -> Result<f32, CodecError> {
        Ok(f32::from_le_bytes(self.array::<4>(what)?))
    }

    fn f32x3(&mut self, what: &'static str) -> Result<[f32; 3], CodecError> {
        Ok(f32x3(&self.array::<12>(what)?))
    }

    fn f64s<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N], CodecError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }

    fn unknown(&self, offset: usize, what: &'static str, tag: u8) -> CodecError {
        CodecError::UnknownTag { offset, what, tag }
    }

    fn texture(&mut self) -> Result<Option<Texture>, CodecError> {
        if !self.bool_flag("texture present")? {
            return Ok(None);
        }
        let image = Arc::new(self.image()?);
        let at = self.pos;
        let wrap = match self.u8("texture wrap")? {
            0 => TextureWrap::Repeat,
            1 => TextureWrap::MirroredRepeat,
            2 => TextureWrap::ClampToEdge,
            3 => TextureWrap::ClampToBorder,
            tag => return Err(self.unknown(at, "texture wrap", tag)),
        };
        let at = self.pos;
        let filter = match self.u8("texture filter")? {
            0 => TextureFilter::Nearest,
            1 => TextureFilter::Bilinear,
            2 => TextureFilter::Trilinear,
            3 => TextureFilter::Anisotropic,
            tag => return Err(self.unknown(at, "texture filter", tag)),
        };
        let border = std::array::from_fn::<_, 4, _>(|_| 0.0);
        let mut border: [f32; 4] = border;
        for v in &mut border {
            *v = self.f32("texture border")?;
        }
        let max_anisotropy = self.u32("texture anisotropy")?;
        let uv_scale = [self.f32("texture uv scale")?, self.f32("texture uv scale")?];
        Ok(Some(Texture {
            image,
            wrap,
            filter,
            border,
            max_anisotropy,
            uv_scale,
        }))
    }

    fn scene(&mut self) -> Result<Scene, CodecError> {
        let n = self.len(size::MIN_MATERIAL, "scene materials")?;
        let mut materials = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let name = self.string("material name")?;
            let albedo = self.f32x3("material albedo")?;
            let albedo_texture = self.texture()?;
            let normal_texture = self.texture()?;
            let roughness = self.f32("material roughness")?;
            let roughness_texture = self.texture()?;
            let metalness = self.f32("material metalness")?;
            let metalness_texture = self.texture()?;
            let emission = self.f32x3("material emission")?;
            let emission_texture = self.texture()?;
            let specular = self.f32("material specular")?;
            let shininess = self.f32("material shininess")?;
            let transmission = self.f32("material transmission")?;
            let ior = self.f32("material ior")?;
            let opacity = self.f32("material opacity")?;
            let at = self.pos;
            let shading = match self.u8("material shading")? {
                0 => Shading::Unlit,
                1 => Shading::Flat,
                2 => Shading::Gouraud,
                3 => Shading::Lambert,
                4 => Shading::Phong,
                5 => Shading::BlinnPhong,
                6 => Shading::Pbr,
                tag => return Err(self.unknown(at, "material shading", tag)),
            };
            materials.push(Material {
                name,
                albedo,
                albedo_texture,
                normal_texture,
                roughness,
                roughness_texture,
                metalness,
                metalness_texture,
                emission,
                emission_texture,
                specular,
                shininess,
                transmission,
                ior,
                opacity,
                shading,
            });
        }
        let n = self.len(size::MIN_SCENE_OBJECT, "scene objects")?;
        let mut objects = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let name = self.string("object name")?;
            let at = self.pos;
            let shape = match self.u8("shape kind")? {
                0 => Shape::Mesh(Arc::new(self.mesh()?)),
                1 => Shape::Sphere {
                    center: self.f64s("sphere centre")?,
                    radius: self.f64("sphere radius")?,
                },
                2 => Shape::Plane {
                    point: self.f64s("plane point")?,
                    normal: self.f64s("plane normal")?,
                    half_extent: self.f64("plane extent")?,
                },
                3 => Shape::Quadric {
                    coefficients: self.f64s("quadric coefficients")?,
                    min: self.f64s("quadric box")?,
                    max: self.f64s("quadric box")?,
                },
                tag => return Err(self.unknown(at, "shape kind", tag)),
            };
            let world_from_object = self.pose()?;
            let scale = self.f64("object scale")?;
            let material = self.u32("object material")?;
            objects.push(SceneObject {
                name,
                shape,
                world_from_object,
                scale,
                material,
            });
        }
        let n = self.len(size::MIN_LIGHT, "scene lights")?;
        let mut lights = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let at = self.pos;
            lights.push(match self.u8("light kind")? {
                0 => Light::Point {
                    position: self.f64s("light position")?,
                    intensity: self.f32x3("light intensity")?,
                },
                1 => Light::Directional {
                    direction: self.f64s("light direction")?,
                    irradiance: self.f32x3("light irradiance")?,
                },
                2 => Light::Area {
                    corner: self.f64s("light corner")?,
                    edge_u: self.f64s("light edge")?,
                    edge_v: self.f64s("light edge")?,
                    radiance: self.f32x3("light radiance")?,
                },
                3 => Light::Environment {
                    radiance: self.f32x3("light radiance")?,
                    map: self.texture()?,
                },
                tag => return Err(self.unknown(at, "light kind", tag)),
            });
        }
        let n = self.len(size::MIN_SCENE_CAMERA, "scene cameras")?;
        let mut cameras = Vec::with_capacity(n.min(PREALLOC_MAX));
        for _ in 0..n {
            let camera = self.camera()?;
            let camera_from_world = self.pose()?;
            let aperture_radius = self.f64("camera aperture")?;
            let focus_distance = self.f64("camera focus distance")?;
            cameras.push(SceneCamera {
                camera,
                camera_from_world,
                aperture_radius,
                focus_distance,
            });
        }
        Ok(Scene {
            materials,
            objects,
            lights,
            cameras,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh() -> Mesh {
        Mesh {
            positions: vec![[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, -8.0]],
            triangles: vec![[0, 1, 2]],
            normals: Some(vec![[0.0, 0.0, 1.0]; 3]),
            uvs: None,
            colors: Some(vec![[0.25, 0.5, 1.0]; 3]),
            tangents: None,
        }
    }

    /// Every attribute, tangents included, with bit patterns worth keeping.
    fn full_mesh() -> Mesh {
        Mesh {
            uvs: Some(vec![[0.0, 1.0], [-0.0, 0.5], [f32::MAX, 1e-45]]),
            tangents: Some(vec![
                [1.0, 0.0, 0.0, 1.0],
                [0.0, -1.0, 0.0, -1.0],
                [f32::from_bits(0x7fc0_0001), -0.0, f32::MIN_POSITIVE, -1.0],
            ]),
            ..mesh()
        }
    }

    fn camera() -> Camera {
        Camera {
            model: CameraModel::OpenCv,
            width: 640,
            height: 480,
            params: vec![500.0, 501.0, 320.0, 240.0, 0.1, -0.01, 0.001, 0.0],
        }
    }

    /// One value of every variant, with awkward contents.
    fn samples() -> Vec<Value> {
        let nan_payload = f32::from_bits(0x7FC0_1234);
        let mut cameras = BTreeMap::new();
        cameras.insert(3, camera());
        let mut metrics = Metrics::new();
        metrics.insert("a".into(), 1.5);
        metrics.insert("b.c".into(), f64::NAN);
        vec![
            Value::image(Image::from_u8(3, 2, Channels::Rgb, (0..18).collect()).unwrap()),
            Value::image(Image::from_u16(2, 2, Channels::Gray, vec![0, 1, 65535, 258]).unwrap()),
            Value::image(
                Image::from_f32(
                    1,
                    2,
                    Channels::Rgba,
                    vec![nan_payload, -0.0, 1.0, f32::INFINITY, 0.5, -2.0, 1e-40, 3.0],
                )
                .unwrap(),
            ),
            Value::image(Image::from_u8(0, 5, Channels::Gray, vec![]).unwrap()),
            Value::image(Image::from_f32(4, 0, Channels::Rgb, vec![]).unwrap()),
            Value::Keypoints(Arc::new(vec![Keypoint {
                x: 1.0,
                y: 2.0,
                size: 3.0,
                angle: -1.0,
                response: nan_payload,
                octave: -2,
            }])),
            Value::Descriptors(Arc::new(Descriptors::Float {
                dim: 2,
                data: vec![0.5, 1.5, 2.5, 3.5],
            })),
            Value::Descriptors(Arc::new(Descriptors::Binary {
                bytes: 3,
                data: vec![1, 2, 3, 255, 254, 253],
            })),
            Value::Matches(Arc::new(vec![Match {
                query: 7,
                train: u32::MAX,
                distance: 0.25,
            }])),
            Value::Matrix(Arc::new(
                Matrix::new(2, 3, vec![1.0, 2.0, 3.0, 4.0, 5.0, f64::NAN]).unwrap(),
            )),
            Value::Matrix(Arc::new(Matrix::new(0, 7, vec![]).unwrap())),
            Value::Camera(Arc::new(camera())),
            Value::Pose(Pose {
                rotation: [0.5, 0.5, 0.5, 0.5],
                translation: [1.0, -2.0, 3.0],
            }),
            Value::Points2D(Arc::new(vec![[1.0, 2.0], [-3.5, 1e300]])),
            Value::PointCloud(Arc::new(PointCloud {
                positions: vec![[1.0, 2.0, 3.0]; 2],
                colors: Some(vec![[1, 2, 3], [4, 5, 6]]),
                normals: None,
            })),
            Value::PointCloud(Arc::new(PointCloud::default())),
            Value::Tracks(Arc::new(Tracks {
                tracks: vec![
                    vec![
                        TrackElement {
                            image: 0,
                            keypoint: 1,
                        },
                        TrackElement {
                            image: 2,
                            keypoint: 3,
                        },
                    ],
                    vec![],
                ],
            })),
            Value::Reconstruction(Arc::new(Reconstruction {
                cameras,
                images: vec![ReconImage {
                    id: 1,
                    camera_id: 3,
                    name: "img_ü.jpg".into(),
                    camera_from_world: Pose::IDENTITY,
                    points2d: vec![([1.0, 2.0], Some(42)), ([3.0, 4.0], None)],
                }],
                points: vec![ReconPoint {
                    id: 42,
                    position: [1.0, 2.0, 3.0],
                    color: [9, 8, 7],
                    error_px: 0.5,
                    track: vec![(1, 0)],
                }],
            })),
            Value::Mesh(Arc::new(mesh())),
            Value::Mesh(Arc::new(full_mesh())),
            Value::Mesh(Arc::new(Mesh::default())),
            Value::Scene(Arc::new(Scene {
                materials: vec![
                    Material::default(),
                    Material {
                        name: "checker".into(),
                        albedo_texture: Some(Texture {
                            image: Arc::new(
                                Image::new(
                                    2,
                                    1,
                                    Channels::Rgb,
                                    PixelData::U8(vec![1, 2, 3, 4, 5, 6]),
                                )
                                .expect("image"),
                            ),
                            wrap: TextureWrap::MirroredRepeat,
                            filter: TextureFilter::Anisotropic,
                            border: [0.1, 0.2, 0.3, 0.4],
                            max_anisotropy: 8,
                            uv_scale: [2.0, 3.0],
                        }),
                        shading: Shading::Pbr,
                        ior: 1.33,
                        ..Material::default()
                    },
                ],
                objects: vec![
                    SceneObject {
                        name: "tri".into(),
                        shape: Shape::Mesh(Arc::new(mesh())),
                        world_from_object: Pose::IDENTITY,
                        scale: 2.0,
                        material: 1,
                    },
                    SceneObject {
                        name: "ball".into(),
                        shape: Shape::Sphere {
                            center: [1.0, 2.0, 3.0],
                            radius: 0.5,
                        },
                        world_from_object: Pose::IDENTITY,
                        scale: 1.0,
                        material: 0,
                    },
                    SceneObject {
                        name: "floor".into(),
                        shape: Shape::Plane {
                            point: [0.0; 3],
                            normal: [0.0, 1.0, 0.0],
                            half_extent: f64::INFINITY,
                        },
                        world_from_object: Pose::IDENTITY,
                        scale: 1.0,
                        material: 0,
                    },
                    SceneObject {
                        name: "egg".into(),
                        shape: Shape::Quadric {
                            coefficients: [1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 3.0, 0.0, -1.0],
                            min: [-1.0; 3],
                            max: [1.0; 3],
                        },
                        world_from_object: Pose::IDENTITY,
                        scale: 1.0,
                        material: 0,
                    },
                ],
                lights: vec![
                    Light::Point {
                        position: [0.0, 1.0, 0.0],
                        intensity: [1.0, 1.0, 1.0],
                    },
                    Light::Directional {
                        direction: [0.0, -1.0, 0.0],
                        irradiance: [2.0, 2.0, 2.0],
                    },
                    Light::Area {
                        corner: [0.0, 2.0, 0.0],
                        edge_u: [1.0, 0.0, 0.0],
                        edge_v: [0.0, 0.0, 1.0],
                        radiance: [5.0, 5.0, 5.0],
                    },
                    Light::Environment {
                        radiance: [0.5, 0.5, 0.5],
                        map: None,
                    },
                ],
                cameras: vec![SceneCamera {
                    camera: camera(),
                    camera_from_world: Pose::IDENTITY,
                    aperture_radius: 0.01,
                    focus_distance: 2.5,
                }],
            })),
            Value::Animation(Arc::new(Animation {
                duration: 1.5,
                channels: vec![AnimationChannel {
                    target: "joint3.rotation".into(),
                    times: vec![0.0, 1.5],
                    width: 4,
                    values: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                }],
            })),
            Value::Scalar(-0.0),
            Value::Scalar(f64::from_bits(0x7FF8_0000_0000_ABCD)),
            Value::Integer(i64::MIN),
            Value::Bool(true),
            Value::Text("héllo\n\"world\"".into()),
            Value::Text("".into()),
            Value::metrics(metrics),
            Value::list(PortType::Image, vec![]),
            Value::Bvh(Arc::new(Bvh {
                nodes: vec![
                    BvhNode {
                        min: [0.0, -1.0, 0.5],
                        offset: 1,
                        max: [1.0, 1.0, 2.0],
                        count: 0,
                    },
                    BvhNode {
                        min: [0.0, -1.0, 0.5],
                        offset: 0,
                        max: [0.5, 1.0, 2.0],
                        count: 1,
                    },
                    BvhNode {
                        min: [0.5, -1.0, 0.5],
                        offset: 1,
                        max: [1.0, 1.0, f32::INFINITY],
                        count: 1,
                    },
                ],
                primitives: vec![1, 0],
                corners: vec![
                    [[0.0, 0.0, 1.0], [0.5, 1.0, 2.0], [0.0, -1.0, 0.5]],
                    [[1.0, 0.0, 1.0], [0.5, 1.0, 2.0], [0.5, -1.0, -0.0]],
                ],
                mesh: Arc::new(mesh()),
            })),
            Value::list(PortType::Bvh, vec![Value::Bvh(Arc::new(Bvh::default()))]),
            Value::list(
                PortType::Scalar.list_of(),
                vec![
                    Value::list(
                        PortType::Scalar,
                        vec![Value::Scalar(1.0), Value::Scalar(2.0)],
                    ),
                    Value::list(PortType::Scalar, vec![]),
                ],
            ),
        ]
    }

    /// Bit-exact equality (NaN payloads, -0.0) by comparing re-encodings.
    fn assert_same(a: &[Value], b: &[Value]) {
        assert_eq!(a.len(), b.len());
        assert_eq!(encode_values(a), encode_values(b));
    }

    #[test]
    fn round_trips_every_variant() {
        let values = samples();
        let bytes = encode_values(&values);
        let decoded = decode_values(&bytes).unwrap();
        assert_same(&values, &decoded);
        // Structural equality too, wherever NaN (never equal to itself) is absent; the
        // byte-for-byte comparison above covers the rest.
        for (a, b) in values.iter().zip(&decoded) {
            if !format!("{a:?}").contains("NaN") {
                assert_eq!(a, b);
            }
        }
        // Every variant is covered.
        let mut tags: Vec<u8> = values
            .iter()
            .map(|v| encode_values(std::slice::from_ref(v))[16])
            .collect();
        tags.sort();
        tags.dedup();
        assert_eq!(tags, (0..=20).collect::<Vec<u8>>());
        assert_eq!(decode_values(&encode_values(&[])).unwrap(), vec![]);
    }

    #[test]
    fn nan_payloads_survive() {
        let bits = 0x7FA0_0001u32; // a signalling NaN with a payload
        let image = Image::from_f32(1, 1, Channels::Gray, vec![f32::from_bits(bits)]).unwrap();
        let decoded = decode_values(&encode_values(&[Value::image(image)])).unwrap();
        let Value::Image(image) = &decoded[0] else {
            panic!("not an image")
        };
        assert_eq!(image.as_f32().unwrap()[0].to_bits(), bits);
        let scalar = f64::from_bits(0xFFF0_0000_0000_0F0F);
        let decoded = decode_values(&encode_values(&[Value::Scalar(scalar)])).unwrap();
        let Value::Scalar(x) = decoded[0] else {
            panic!("not a scalar")
        };
        assert_eq!(x.to_bits(), scalar.to_bits());
    }

    #[test]
    fn image_samples_are_little_endian_bulk() {
        let image = Image::from_u16(2, 1, Channels::Gray, vec![0x0102, 0x0304]).unwrap();
        let bytes = encode_values(&[Value::image(image)]);
        let mut expected = b"OCVL".to_vec();
        expected.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        expected.extend_from_slice(&1u64.to_le_bytes());
        expected.push(0);
        expected.extend_from_slice(&2u64.to_le_bytes());
        expected.extend_from_slice(&1u64.to_le_bytes());
        expected.extend_from_slice(&[0, 1, 0x02, 0x01, 0x04, 0x03]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn truncation_at_every_offset_fails_cleanly() {
        let bytes = encode_values(&samples());
        for cut in 0..bytes.len() {
            assert!(decode_values(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(
            decode_values(&longer),
            Err(CodecError::TrailingBytes { count: 1, .. })
        ));
    }

    #[test]
    fn corrupted_bytes_never_panic() {
        let bytes = encode_values(&samples());
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..3000 {
            let mut corrupt = bytes.clone();
            for _ in 0..1 + next() % 4 {
                let i = (next() as usize) % corrupt.len();
                corrupt[i] = next() as u8;
            }
            let _ = decode_values(&corrupt);
        }
        for round in 0..500 {
            let len = (next() % 200) as usize;
            let mut random: Vec<u8> = (0..len).map(|_| next() as u8).collect();
            if round % 2 == 0 {
                let mut with_header = b"OCVL\x01\0\0\0".to_vec();
                with_header.append(&mut random);
                random = with_header;
            }
            let _ = decode_values(&random);
        }
    }

    fn header(count: u64) -> Vec<u8> {
        let mut b = b"OCVL".to_vec();
        b.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        b.extend_from_slice(&count.to_le_bytes());
        b
    }

    #[test]
    fn huge_lengths_are_rejected_without_allocating() {
        assert!(matches!(
            decode_values(&header(u64::MAX)),
            Err(CodecError::Truncated { .. })
        ));
        for t in [
            tag::KEYPOINTS,
            tag::MATCHES,
            tag::POINTS2D,
            tag::TEXT,
            tag::METRICS,
            tag::TRACKS,
        ] {
            let mut b = header(1);
            b.push(t);
            b.extend_from_slice(&u64::MAX.to_le_bytes());
            assert!(
                matches!(decode_values(&b), Err(CodecError::Truncated { .. })),
                "tag {t}"
            );
        }
        // An image claiming u64::MAX × u64::MAX pixels.
        let mut b = header(1);
        b.push(tag::IMAGE);
        b.extend_from_slice(&u64::MAX.to_le_bytes());
        b.extend_from_slice(&u64::MAX.to_le_bytes());
        b.extend_from_slice(&[0, 0]);
        assert!(decode_values(&b).is_err());
        // A plausible image size with too few samples.
        let mut b = header(1);
        b.push(tag::IMAGE);
        b.extend_from_slice(&100_000u64.to_le_bytes());
        b.extend_from_slice(&100_000u64.to_le_bytes());
        b.extend_from_slice(&[2, 2, 0, 0, 0, 0]);
        assert!(matches!(
            decode_values(&b),
            Err(CodecError::Truncated { .. })
        ));
        // A matrix whose rows × cols overflows.
        let mut b = header(1);
        b.push(tag::MATRIX);
        b.extend_from_slice(&u64::MAX.to_le_bytes());
        b.extend_from_slice(&3u64.to_le_bytes());
        assert!(decode_values(&b).is_err());
    }

    #[test]
    fn rejects_bad_headers_tags_and_nesting() {
        assert_eq!(decode_values(b""), Err(CodecError::BadMagic));
        assert_eq!(decode_values(b"OCVX\x01\0\0\0"), Err(CodecError::BadMagic));
        let mut b = b"OCVL".to_vec();
        b.extend_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        b.extend_from_slice(&0u64.to_le_bytes());
        assert_eq!(
            decode_values(&b),
            Err(CodecError::UnsupportedVersion {
                found: FORMAT_VERSION + 1,
                supported: FORMAT_VERSION
            })
        );
        let mut b = header(1);
        b.extend_from_slice(&[200, 0]);
        assert!(matches!(
            decode_values(&b),
            Err(CodecError::UnknownTag { tag: 200, .. })
        ));
        let mut b = header(1);
        b.extend_from_slice(&[tag::BOOL, 2]);
        assert!(matches!(decode_values(&b), Err(CodecError::Invalid { .. })));

        // 40 nested lists: too deep.
        let mut deep = Value::list(PortType::Bool, vec![Value::Bool(true)]);
        let mut element = PortType::Bool;
        for _ in 0..40 {
            element = element.list_of();
            deep = Value::list(element.clone(), vec![deep]);
        }
        let bytes = encode_values(&[deep]);
        assert_eq!(
            decode_values(&bytes),
            Err(CodecError::TooDeep { limit: MAX_DEPTH })
        );
        // Exactly MAX_DEPTH lists inside one another decode; one more does not.
        let mut ok = Value::list(PortType::Bool, vec![Value::Bool(false)]);
        let mut element = PortType::Bool;
        for _ in 1..MAX_DEPTH {
            element = element.list_of();
            ok = Value::list(element.clone(), vec![ok]);
        }
        let decoded = decode_values(&encode_values(std::slice::from_ref(&ok))).unwrap();
        assert_eq!(decoded, [ok.clone()]);
        let too_deep = Value::list(element.list_of(), vec![ok]);
        assert_eq!(
            decode_values(&encode_values(&[too_deep])),
            Err(CodecError::TooDeep { limit: MAX_DEPTH })
        );
        // A list type nested far too deep, with no values at all.
        let mut b = header(1);
        b.push(tag::LIST);
        b.extend(std::iter::repeat_n(LIST_TYPE_TAG, 10_000));
        assert_eq!(
            decode_values(&b),
            Err(CodecError::TooDeep { limit: MAX_DEPTH })
        );

        // Metrics must be strictly ordered.
        let mut b = header(1);
        b.push(tag::METRICS);
        b.extend_from_slice(&2u64.to_le_bytes());
        for key in ["b", "a"] {
            b.extend_from_slice(&1u64.to_le_bytes());
            b.extend_from_slice(key.as_bytes());
            b.extend_from_slice(&1.0f64.to_le_bytes());
        }
        assert!(matches!(decode_values(&b), Err(CodecError::Invalid { .. })));
    }

    #[test]
    fn mesh_tangents_use_flag_8_and_keep_their_bits() {
        let mesh = full_mesh();
        let bytes = encode_values(&[Value::Mesh(Arc::new(mesh.clone()))]);
        // Header (16 bytes), tag, 3 positions, 1 triangle: the flags byte follows.
        let flags_at = 16 + 1 + 8 + 36 + 8 + 12;
        assert_eq!(bytes[flags_at], 1 | 2 | 4 | 8);
        let back = decode_values(&bytes).unwrap();
        let Value::Mesh(m) = &back[0] else {
            panic!("not a mesh: {back:?}")
        };
        let bits = |t: &Option<Vec<[f32; 4]>>| -> Vec<[u32; 4]> {
            t.iter().flatten().map(|v| v.map(f32::to_bits)).collect()
        };
        assert_eq!(bits(&m.tangents), bits(&mesh.tangents));
        assert_eq!(m.tangents.as_ref().map(Vec::len), Some(3));
        // Without tangents the flag is clear and the payload is exactly 4 × 4 × n bytes shorter.
        let plain = Mesh {
            tangents: None,
            ..mesh.clone()
        };
        let short = encode_values(&[Value::Mesh(Arc::new(plain))]);
        assert_eq!(short[flags_at], 1 | 2 | 4);
        assert_eq!(bytes.len() - short.len(), 8 + 3 * 16);
        // An unknown flag bit is an error, not a silently dropped attribute.
        let mut bad = bytes.clone();
        bad[flags_at] |= 16;
        assert!(matches!(
            decode_values(&bad),
            Err(CodecError::Invalid { .. })
        ));
        // Fewer tangents than the length says: truncated.
        assert!(matches!(
            decode_values(&bytes[..bytes.len() - 1]),
            Err(CodecError::Truncated { .. })
        ));
        // A version 2 file (before tangents) is refused cleanly, so a cache recomputes it.
        let mut old = short.clone();
        old[4..8].copy_from_slice(&2u32.to_le_bytes());
        assert_eq!(
            decode_values(&old),
            Err(CodecError::UnsupportedVersion {
                found: 2,
                supported: FORMAT_VERSION
            })
        );
    }
}
