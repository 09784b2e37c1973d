//! Replays every input the fuzzers kept (`fuzz/corpus/<target>/`) and every crash they found
//! (`fuzz/regressions/<target>/`) through the same checks the fuzz targets run
//! (`ocellus_nodes::fuzz`), so the suite guards them on a stable toolchain without libFuzzer.
//!
//! `cargo test --test fuzz_corpus -- --ignored write_seed_corpora` regenerates the seeds (files
//! named `seed-*`): small files of every format, written by this project's own encoders.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use ocellus_engine::image_io::{ImageFormat, encode_image};
use ocellus_engine::value::Mesh;
use ocellus_engine::{Channels, Image, PixelData};
use ocellus_nodes::fuzz::TARGETS;

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let Ok(read) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut out: Vec<PathBuf> = read
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    out.sort();
    out
}

#[test]
fn every_corpus_and_regression_input_passes_its_target_check() {
    let mut failures = Vec::new();
    for (target, check) in TARGETS {
        let corpus = files(&fuzz_dir().join("corpus").join(target));
        let seeds = corpus
            .iter()
            .filter(|p| {
                p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with("seed-"))
            })
            .count();
        assert!(seeds >= 2, "fuzz/corpus/{target} has {seeds} seeds");
        let regressions = files(&fuzz_dir().join("regressions").join(target));
        for path in corpus.iter().chain(&regressions) {
            let bytes = std::fs::read(path).unwrap();
            if let Err(payload) = catch_unwind(AssertUnwindSafe(|| check(&bytes))) {
                let message = payload
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                failures.push(format!("{target}: {}: {message}", path.display()));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The descriptor the plugin seed `seed-valid` spells is accepted, so the fuzz target reaches
/// the registration path and not only the early refusals.
#[test]
fn the_valid_plugin_seed_registers_one_operator() {
    let mut registry = ocellus_engine::Registry::new();
    let info =
        ocellus_engine::plugin::register_descriptor_bytes(&valid_descriptor(), &mut registry)
            .unwrap();
    assert_eq!(info.ops, ["fz.op"]);
    let factory = registry.get("fz.op").unwrap();
    assert_eq!(factory.info().inputs.len(), 1);
    assert_eq!(factory.info().params.len(), 1);
    // A wrong ABI version is refused before anything else is read.
    let mut stale = valid_descriptor();
    stale[0] = 0x0F;
    stale.insert(1, 99);
    let err = ocellus_engine::plugin::register_descriptor_bytes(&stale, &mut registry).unwrap_err();
    assert!(err.to_string().contains("ABI version 99"), "{err}");
}

/// Bytes the plugin target reads as a valid one-operator descriptor (see
/// `register_descriptor_bytes`): one input, one output, one integer parameter in `[0, 10]`.
fn valid_descriptor() -> Vec<u8> {
    let mut d = vec![
        0x00, // header: current ABI, host fingerprint, init succeeds
        0x01, // name: "fuzzed"
        0x01, // SDK version: the host's
        0x01, // one operator
        0x01, // id "fz.op"
        0x01, // version 1
        0x01, 0x01, // summary, doc
        0x00, // no side effects
        0x01, 0x01, 0x01, 0x01, 0x00, // one input: "a", the first port type, doc, required
        0x01, 0x05, 0x05, 0x01, 0x00, // one output: "b", the second port type, doc, required
        0x01, // one parameter
        0x02, 0x00, 0x00, // int, default of the same kind, boolean false
    ];
    d.extend_from_slice(&3i64.to_le_bytes()); // default 3
    d.extend_from_slice(&0f64.to_bits().to_le_bytes());
    d.push(0x01); // default text "x"
    d.push(0x00); // no choices
    d.push(0x03); // has min and max
    d.push(0x01); // name "p"
    d.extend_from_slice(&0f64.to_bits().to_le_bytes());
    d.extend_from_slice(&10f64.to_bits().to_le_bytes());
    d.push(0x01); // unit "px"
    d.push(0x01); // doc
    d
}

fn write_seed(target: &str, name: &str, bytes: &[u8]) {
    let dir = fuzz_dir().join("corpus").join(target);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(format!("seed-{name}")), bytes).unwrap();
}

fn test_image(width: usize, height: usize, channels: Channels, depth: u8) -> Image {
    let n = width * height * channels.count();
    let data = match depth {
        8 => PixelData::U8((0..n).map(|i| (i * 37 % 251) as u8).collect()),
        16 => PixelData::U16((0..n).map(|i| (i * 4099 % 65521) as u16).collect()),
        _ => PixelData::F32((0..n).map(|i| i as f32 * 0.25 - 1.0).collect()),
    };
    Image::new(width, height, channels, data).unwrap()
}

fn tetrahedron() -> Mesh {
    Mesh {
        positions: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        normals: Some(vec![
            [0.0, 0.0, -1.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ]),
        uvs: Some(vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
        colors: Some(vec![
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.5, 0.5, 0.5],
        ]),
        tangents: None,
    }
}

#[test]
#[ignore = "regenerates fuzz/corpus/*/seed-*; run by hand"]
fn write_seed_corpora() {
    // Graphs: the example jobs and the broken graphs the diagnostics tests use.
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for dir in ["graphs", "tests/broken"] {
        for path in files(&root.join(dir)) {
            if path.extension().is_some_and(|e| e == "ron") {
                let name = path.file_name().unwrap().to_string_lossy().into_owned();
                let prefix = dir.replace('/', "-");
                write_seed(
                    "graph",
                    &format!("{prefix}-{name}"),
                    &std::fs::read(&path).unwrap(),
                );
            }
        }
    }

    // Images: every format and sample type the reader decodes.
    let cases: [(&str, ImageFormat, Channels, u8); 14] = [
        ("gray8.png", ImageFormat::Png, Channels::Gray, 8),
        ("rgba8.png", ImageFormat::Png, Channels::Rgba, 8),
        ("rgb16.png", ImageFormat::Png, Channels::Rgb, 16),
        (
            "rgb.jpg",
            ImageFormat::Jpeg { quality: 90 },
            Channels::Rgb,
            8,
        ),
        (
            "gray.jpg",
            ImageFormat::Jpeg { quality: 50 },
            Channels::Gray,
            8,
        ),
        ("gray8.pgm", ImageFormat::Pnm, Channels::Gray, 8),
        ("rgb16.ppm", ImageFormat::Pnm, Channels::Rgb, 16),
        ("rgba8.pam", ImageFormat::Pnm, Channels::Rgba, 8),
        ("rgb8.tif", ImageFormat::Tiff, Channels::Rgb, 8),
        ("rgbaf.tif", ImageFormat::Tiff, Channels::Rgba, 32),
        ("gray.pfm", ImageFormat::Pfm, Channels::Gray, 32),
        ("rgb.pfm", ImageFormat::Pfm, Channels::Rgb, 32),
        ("gray.exr", ImageFormat::Exr, Channels::Gray, 32),
        ("rgba.exr", ImageFormat::Exr, Channels::Rgba, 32),
    ];
    for (name, format, channels, depth) in cases {
        let bytes = encode_image(&test_image(7, 5, channels, depth), format).unwrap();
        write_seed("image", name, &bytes);
    }

    // Meshes: selector byte (0 PLY, 1 OBJ, 2 STL), then the file.
    let mesh = tetrahedron();
    let with = |selector: u8, name: &str, write: &dyn Fn(&mut Vec<u8>)| {
        let mut bytes = vec![selector];
        write(&mut bytes);
        write_seed("mesh", name, &bytes);
    };
    use ocellus_engine::mesh_write::{write_obj, write_ply, write_stl};
    with(0, "ascii.ply", &|b| write_ply(b, &mesh, false).unwrap());
    with(0, "binary.ply", &|b| write_ply(b, &mesh, true).unwrap());
    with(1, "tetra.obj", &|b| write_obj(b, &mesh).unwrap());
    with(2, "ascii.stl", &|b| write_stl(b, &mesh, false).unwrap());
    with(2, "binary.stl", &|b| write_stl(b, &mesh, true).unwrap());

    // BAL: two cameras, three points, four observations.
    let bal = "2 3 4\n0 0 -1.5 2.0\n1 0 1.0 -0.5\n0 1 3.25 1e-3\n1 2 -2 7\n\
        0.01 -0.02 0.03 0.1 0.2 -5 500 -1e-7 2e-13\n\
        0 0 0 0 0 -4 600 0 0\n\
        1 2 3\n-1 0.5 2\n0 0 1\n";
    write_seed("bal", "two-cameras.txt", bal.as_bytes());
    write_seed("bal", "empty-header.txt", b"0 0 0\n");

    // COLMAP text: cameras.txt NUL images.txt NUL points3D.txt.
    let cameras = "# Camera list\n1 PINHOLE 640 480 500 510 320 240\n\
        2 SIMPLE_RADIAL 800 600 700 400 300 -0.01\n3 OPENCV 64 48 50 50 32 24 0.1 -0.01 0.001 0.002\n";
    let images = "# Image list\n\
        1 1 0 0 0 0 0 0 1 a.png\n100 200 1 300 400 -1 10 20 -1\n\
        2 0.7071068 0 0.7071068 0 1 0 0 2 b.png\n110 210 1 5 6 -1\n";
    let points = "# 3D points\n1 0.5 0.25 4 255 128 0 0.3 1 0 2 0\n";
    write_seed(
        "colmap",
        "two-images.txt",
        format!("{cameras}\0{images}\0{points}").as_bytes(),
    );
    write_seed(
        "colmap",
        "cameras-only.txt",
        format!("{cameras}\0\0").as_bytes(),
    );

    // Plugin descriptors: a valid one and a stale one.
    write_seed("plugin_descriptor", "valid", &valid_descriptor());
    let mut stale = valid_descriptor();
    stale[0] = 0x0F;
    stale.insert(1, 2);
    write_seed("plugin_descriptor", "stale-abi", &stale);
}
