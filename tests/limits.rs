//! Hostile inputs through the CLI, as a user would meet them: a PNG whose header claims
//! 20,000 × 20,000 pixels, a JPEG cut off half-way, and a PLY claiming 10⁹ vertices. Each must
//! end the run with a clear error naming the node and the file — not a panic, an out-of-memory
//! kill or a partial output file — and must not allocate what the header claims (the children's
//! peak resident memory is checked to stay under 100 MB).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test
#![allow(unsafe_code)] // getrusage, to read the children's peak memory

mod common;

use std::path::Path;

use common::{ocellus, stderr, temp_dir};
use ocellus_engine::value::{Channels, Image};

/// CRC-32 (IEEE 802.3, reflected, as PNG uses it), bit by bit.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xedb8_8320 & mask);
        }
    }
    !crc
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// A well-formed PNG header for a `width × height` RGB image, with a few bytes of data.
fn png_claiming(width: u32, height: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    png_chunk(&mut out, b"IHDR", &ihdr);
    png_chunk(
        &mut out,
        b"IDAT",
        &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
    );
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// A real 640 × 480 JPEG of a gradient, cut to its first half.
fn truncated_jpeg(dir: &Path) -> Vec<u8> {
    let (w, h) = (640, 480);
    let pixels: Vec<u8> = (0..w * h * 3)
        .map(|i| (((i % (w * 3)) * 255 / (w * 3)) ^ ((i / (w * 3)) % 256)) as u8)
        .collect();
    let image = Image::from_u8(w, h, Channels::Rgb, pixels).unwrap();
    let full = dir.join("full.jpg");
    ocellus_engine::image_io::write_image(&full, &image).unwrap();
    let bytes = std::fs::read(&full).unwrap();
    assert!(bytes.len() > 2000, "{} bytes", bytes.len());
    bytes[..bytes.len() / 2].to_vec()
}

/// A binary PLY header claiming 10⁹ vertices, followed by one vertex.
fn ply_claiming_a_billion_vertices() -> Vec<u8> {
    let mut out = b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n\
property float x\nproperty float y\nproperty float z\nelement face 1\n\
property list uchar int vertex_indices\nend_header\n"
        .to_vec();
    out.extend_from_slice(&[0u8; 12]);
    out
}

/// Peak resident set size of the waited-for children, bytes.
fn children_peak_rss() -> u64 {
    // SAFETY: getrusage only writes into the struct we pass.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    let rc = unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) };
    assert_eq!(rc, 0);
    // Linux reports kilobytes.
    u64::try_from(usage.ru_maxrss).unwrap() * 1024
}

/// Runs a one-node graph reading `file` with `op`, emitting to a fresh folder; returns stderr
/// and the emitted files.
fn run_reader(dir: &Path, op: &str, file: &Path) -> (String, Vec<std::path::PathBuf>) {
    let graph = dir.join(format!("{}.ron", op.replace('.', "_")));
    let port = if op == "io.read_image" {
        "read.image"
    } else {
        "read.mesh"
    };
    std::fs::write(
        &graph,
        format!(
            "Graph(nodes: {{ \"read\": (op: \"{op}\", params: (path: {:?})) }}, \
             outputs: {{ \"out\": \"{port}\" }})",
            file.display().to_string()
        ),
    )
    .unwrap();
    let out_dir = dir.join(format!("out_{}", op.replace('.', "_")));
    let out = ocellus(&[
        "run",
        graph.to_str().unwrap(),
        "--emit",
        out_dir.to_str().unwrap(),
    ]);
    assert!(
        !out.status.success(),
        "{op} on {} succeeded",
        file.display()
    );
    // A clean error exit, not a signal (a panic abort or an out-of-memory kill).
    assert!(out.status.code().is_some(), "{op}: killed by a signal");
    let emitted = std::fs::read_dir(&out_dir)
        .map(|entries| entries.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    (stderr(&out), emitted)
}

#[test]
fn hostile_headers_are_clear_errors_without_allocating_what_they_claim() {
    let dir = temp_dir("limits");
    let png = dir.join("huge.png");
    std::fs::write(&png, png_claiming(20_000, 20_000)).unwrap();
    let jpeg = dir.join("cut.jpg");
    std::fs::write(&jpeg, truncated_jpeg(&dir)).unwrap();
    let ply = dir.join("billion.ply");
    std::fs::write(&ply, ply_claiming_a_billion_vertices()).unwrap();

    let cases = [
        ("io.read_image", &png, "20000"),
        ("io.read_image", &jpeg, "cut.jpg"),
        ("io.read_mesh", &ply, "1000000000"),
    ];
    for (op, file, mention) in cases {
        let (err, emitted) = run_reader(&dir, op, file);
        // The node and the file (or the claimed size) are named.
        assert!(err.contains("read"), "{op}: {err}");
        assert!(err.contains(mention), "{op} on {}: {err}", file.display());
        assert!(!err.contains("panicked"), "{op}: {err}");
        // No output file, partial or not.
        assert!(emitted.is_empty(), "{op}: wrote {emitted:?}");
    }
    let peak = children_peak_rss();
    assert!(peak < 100 << 20, "peak resident memory {} MB", peak >> 20);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs `ocellus run GRAPH ARGS` on a one-node graph; returns (success, stderr).
fn run_graph(dir: &Path, name: &str, graph_text: &str, args: &[&str]) -> (bool, String) {
    let graph = dir.join(format!("{name}.ron"));
    std::fs::write(&graph, graph_text).unwrap();
    let out_dir = dir.join(format!("out_{name}"));
    let mut all = vec![
        "run",
        graph.to_str().unwrap(),
        "--emit",
        out_dir.to_str().unwrap(),
    ];
    all.extend_from_slice(args);
    let out = ocellus(&all);
    assert!(out.status.code().is_some(), "{name}: killed by a signal");
    let err = stderr(&out);
    assert!(!err.contains("panicked"), "{name}: {err}");
    if !out.status.success() {
        let emitted = std::fs::read_dir(&out_dir).map(|d| d.count()).unwrap_or(0);
        assert_eq!(emitted, 0, "{name}: a failed run wrote files");
    }
    (out.status.success(), err)
}

fn reader_graph(op: &str, file: &Path, port: &str) -> String {
    format!(
        "Graph(nodes: {{ \"read\": (op: \"{op}\", params: (path: {:?})) }}, \
         outputs: {{ \"out\": \"read.{port}\" }})",
        file.display().to_string()
    )
}

#[test]
fn limits_are_set_from_the_command_line_and_name_their_flag() {
    let dir = temp_dir("limit-flags");
    let png = dir.join("card.png");
    let image = Image::from_u8(64, 64, Channels::Gray, vec![128; 64 * 64]).unwrap();
    ocellus_engine::image_io::write_image(&png, &image).unwrap();
    let ply = dir.join("tetra.ply");
    std::fs::write(
        &ply,
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
         property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n\
         0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
    )
    .unwrap();
    let image_graph = reader_graph("io.read_image", &png, "image");
    let mesh_graph = reader_graph("io.read_mesh", &ply, "mesh");

    // Pixels: 64 × 64 = 4096.
    let (ok, err) = run_graph(
        &dir,
        "pixels_low",
        &image_graph,
        &["--max-image-pixels", "4095"],
    );
    assert!(
        !ok && err.contains("64×64") && err.contains("4095 pixels (--max-image-pixels)"),
        "{err}"
    );
    let (ok, err) = run_graph(
        &dir,
        "pixels_ok",
        &image_graph,
        &["--max-image-pixels", "4096"],
    );
    assert!(ok, "{err}");

    // Bytes: the file itself is over the limit.
    let (ok, err) = run_graph(&dir, "bytes_low", &mesh_graph, &["--max-alloc-bytes", "64"]);
    assert!(
        !ok && err.contains("--max-alloc-bytes") && err.contains("tetra.ply"),
        "{err}"
    );
    let (ok, err) = run_graph(&dir, "bytes_ok", &mesh_graph, &["--max-alloc-bytes", "1K"]);
    assert!(ok, "{err}");

    // A device that never ends and reports no size stops at the limit.
    let zero_ply = dir.join("zero.ply");
    std::os::unix::fs::symlink("/dev/zero", &zero_ply).unwrap();
    let zero = reader_graph("io.read_mesh", &zero_ply, "mesh");
    let (ok, err) = run_graph(&dir, "zero", &zero, &["--max-alloc-bytes", "1M"]);
    assert!(!ok && err.contains("over the limit of 1048576"), "{err}");

    // Elements a file declares.
    let (ok, err) = run_graph(&dir, "list_low", &mesh_graph, &["--max-list-len", "3"]);
    assert!(
        !ok && err.contains("4 vertices") && err.contains("--max-list-len"),
        "{err}"
    );
    let (ok, err) = run_graph(&dir, "list_ok", &mesh_graph, &["--max-list-len", "4"]);
    assert!(ok, "{err}");

    // Elements a node outputs in one list.
    let clip = "Graph(nodes: { \"clip\": (op: \"capture.moving_shapes\", \
        params: (width: 16, height: 12, frames: 6, size_px: 4)) }, \
        outputs: { \"frames\": \"clip.frames\" })";
    let (ok, err) = run_graph(&dir, "clip_low", clip, &["--batch", "--max-list-len", "5"]);
    assert!(
        !ok && err.contains("clip") && err.contains("--max-list-len"),
        "{err}"
    );
    let (ok, err) = run_graph(&dir, "clip_ok", clip, &["--batch", "--max-list-len", "6"]);
    assert!(ok, "{err}");

    // Bad values are usage errors.
    let (ok, err) = run_graph(&dir, "bad_unit", &mesh_graph, &["--max-alloc-bytes", "3X"]);
    assert!(!ok && err.contains("unknown unit"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
