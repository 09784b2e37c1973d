//! Entry points shared by the coverage-guided fuzz targets in `fuzz/` and the corpus replay test
//! (`tests/fuzz_corpus.rs`), so that every input the fuzzer ever kept — and every crash it ever
//! found — is re-checked by `cargo test` on a stable toolchain.
//!
//! Each function takes arbitrary bytes and returns normally when the reader under test behaved:
//! it either returned a typed error or a value that satisfies the format's invariants (indices in
//! range, attribute lengths matching, a lossless image surviving a re-encode). Anything else —
//! a panic, an out-of-range index, an invariant broken — panics here, which the fuzzer reports as
//! a crash and the replay test as a failure.

use std::path::Path;
use std::sync::OnceLock;

use ocellus_engine::diag::SourceFile;
use ocellus_engine::diag::{Diagnostic, Diagnostics};
use ocellus_engine::image_io::{DecodeLimits, ImageFormat, decode_image, encode_image};
use ocellus_engine::value::{Depth, Mesh};
use ocellus_engine::{PixelData, Registry};

/// Decode limits for fuzzing: small enough that a hostile header is refused quickly, large
/// enough for every seed.
const FUZZ_LIMITS: DecodeLimits = DecodeLimits {
    max_pixels: 1 << 22,
    max_alloc_bytes: 1 << 26,
};

/// The built-in registry, built once per process.
fn registry() -> &'static Registry {
    static REGISTRY: OnceLock<Registry> = OnceLock::new();
    REGISTRY.get_or_init(|| match crate::builtin_registry() {
        Ok(r) => r,
        Err(e) => panic!("the built-in registry does not build: {e}"),
    })
}

/// The graph loader and validator on one graph text (`inputs` of a subgraph, includes,
/// overrides and all): either a resolved graph or diagnostics whose spans lie inside their
/// source on character boundaries and that render.
pub fn graph(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    let source = SourceFile::new("fuzz.ron", None, text.into_owned());
    // A resolved graph needs no further check here: resolution is the validator.
    if let Err(diagnostics) = ocellus_engine::resolve::load_source(registry(), &source, &[]) {
        check_diagnostics(&diagnostics);
    }
}

fn check_diagnostics(diagnostics: &Diagnostics) {
    assert!(
        !diagnostics.0.is_empty(),
        "a failed load carries no diagnostic"
    );
    for d in &diagnostics.0 {
        check_span(d);
        assert!(!d.message.is_empty(), "a diagnostic without a message");
    }
    let rendered = diagnostics.to_string();
    assert!(!rendered.is_empty());
}

fn check_span(d: &Diagnostic) {
    let (Some(source), Some(span)) = (&d.source, d.span) else {
        return;
    };
    let text = &source.text;
    assert!(
        span.start <= span.end && span.end <= text.len(),
        "span {}..{} outside a {}-byte source: {}",
        span.start,
        span.end,
        text.len(),
        d.message
    );
    assert!(
        text.is_char_boundary(span.start) && text.is_char_boundary(span.end),
        "span {}..{} splits a character: {}",
        span.start,
        span.end,
        d.message
    );
    for related in &d.related {
        assert!(related.span.start <= related.span.end && related.span.end <= text.len());
    }
}

/// Image decoding as `io.read_image` does it (content sniffing, all formats), under small
/// limits. A decoded image stays within the limits, and a lossless re-encode decodes to the
/// same image.
pub fn image(data: &[u8]) {
    let Ok(image) = decode_image(data, Path::new("fuzz.bin"), &FUZZ_LIMITS) else {
        return;
    };
    let pixels = (image.width() as u64) * (image.height() as u64);
    assert!(
        pixels <= FUZZ_LIMITS.max_pixels,
        "decoded over the pixel limit"
    );
    let format = match image.data().depth() {
        Depth::U8 | Depth::U16 => ImageFormat::Png,
        Depth::F32 => ImageFormat::Exr,
    };
    if image.width() == 0 || image.height() == 0 {
        return;
    }
    if let Ok(bytes) = encode_image(&image, format) {
        let back = match decode_image(&bytes, Path::new("fuzz.bin"), &DecodeLimits::default()) {
            Ok(back) => back,
            Err(e) => panic!("our own {format:?} encoding does not decode: {e}"),
        };
        // NaN compares unequal to itself, so an image holding one is not compared.
        let comparable = match image.data() {
            PixelData::F32(v) => !v.iter().any(|x| x.is_nan()),
            _ => true,
        };
        if comparable {
            assert_eq!(back, image, "{format:?} round trip changed the image");
        }
    }
}

/// The mesh readers. The first byte picks the format (PLY, OBJ, STL); the rest is the file.
pub fn mesh(data: &[u8]) {
    let Some((&selector, file)) = data.split_first() else {
        return;
    };
    let parsed = match selector % 3 {
        0 => crate::io::read_mesh::parse_ply(file),
        1 => crate::io::read_mesh::parse_obj(&String::from_utf8_lossy(file)),
        _ => crate::io::read_mesh::parse_stl(file),
    };
    if let Ok(mesh) = parsed {
        check_mesh(&mesh);
    }
}

fn check_mesh(mesh: &Mesh) {
    if let Err(e) = ocellus_engine::mesh_write::check_mesh(mesh) {
        panic!("a parsed mesh breaks the mesh invariants: {e}");
    }
    if let Err(e) = ocellus_engine::mesh_write::check_finite(mesh) {
        panic!("a parsed mesh holds a non-finite value: {e}");
    }
}

/// The BAL reader: observations refer to cameras and points that exist.
pub fn bal(data: &[u8]) {
    let Ok(file) = crate::io::read_bal::parse_bal(&String::from_utf8_lossy(data)) else {
        return;
    };
    for &(camera, point, _) in &file.observations {
        assert!((camera as usize) < file.cameras.len());
        assert!((point as usize) < file.points.len());
    }
}

/// The COLMAP text reader: `cameras.txt`, `images.txt` and `points3D.txt` separated by NUL
/// bytes. Every image names a camera that exists, every track entry an image and a 2-D point
/// that exist.
pub fn colmap(data: &[u8]) {
    use crate::io::read_colmap::{parse_cameras, parse_images, parse_points};
    let mut parts = data.splitn(3, |&b| b == 0);
    let cameras_text = String::from_utf8_lossy(parts.next().unwrap_or_default());
    let images_text = String::from_utf8_lossy(parts.next().unwrap_or_default());
    let points_text = String::from_utf8_lossy(parts.next().unwrap_or_default());
    let Ok(cameras) = parse_cameras(&cameras_text, "cameras.txt") else {
        return;
    };
    for camera in cameras.values() {
        assert_eq!(camera.params.len(), camera.model.param_count());
    }
    let Ok(images) = parse_images(&images_text, "images.txt", &cameras) else {
        return;
    };
    for image in &images {
        assert!(cameras.contains_key(&image.camera_id));
    }
    let Ok(points) = parse_points(&points_text, "points3D.txt", &images) else {
        return;
    };
    for point in &points {
        for &(image_id, index) in &point.track {
            let image = images.iter().find(|i| i.id == image_id);
            let Some(image) = image else {
                panic!("track names image {image_id}, which does not exist");
            };
            assert!((index as usize) < image.points2d.len());
        }
    }
}

/// The plugin descriptor reader, on a descriptor built from the bytes (strings, counts, port
/// types, parameter schemas; see [`ocellus_engine::plugin::register_descriptor_bytes`]). It is
/// either registered — every operator then in the registry — or refused with a message.
pub fn plugin_descriptor(data: &[u8]) {
    let mut registry = Registry::new();
    match ocellus_engine::plugin::register_descriptor_bytes(data, &mut registry) {
        Ok(info) => {
            for id in &info.ops {
                assert!(
                    registry.get(id).is_some(),
                    "`{id}` reported but not registered"
                );
            }
        }
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

/// A fuzz target's check: returns when the reader behaved, panics otherwise.
pub type Check = fn(&[u8]);

/// Every fuzz target by name, for the corpus replay test.
pub const TARGETS: &[(&str, Check)] = &[
    ("graph", graph),
    ("image", image),
    ("mesh", mesh),
    ("bal", bal),
    ("colmap", colmap),
    ("plugin_descriptor", plugin_descriptor),
];
