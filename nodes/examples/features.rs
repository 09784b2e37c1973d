//! SIFT or ORB on one image, or on a pair with a known homography (such as the Oxford "graf"
//! pair and its `H1to3p` file).
//!
//! One image: prints the keypoint count and the detect+describe time, and optionally writes
//! keypoints and descriptors:
//!
//! `cargo run --release -p ocellus-nodes --example features -- sift|orb IMAGE [MAX_FEATURES] [OUT]`
//!
//! OUT holds a u32 count, then per keypoint x, y, size, angle, response, octave (as f32) and the
//! descriptor (SIFT: 128 f32; ORB: 32 bytes).
//!
//! A pair: for every feature count, detects and describes both images, matches the first
//! against the second (brute force, k = 2, Lowe's ratio 0.8) and counts the matches whose
//! second keypoint lies within 3 px of H · first keypoint; the time is the best of 5 detect +
//! describe runs on the first image (`FEATURES_REPEATS` sets the count):
//!
//! `cargo run --release -p ocellus-nodes --example features -- sift|orb --pair IMAGE1 IMAGE2 H [COUNTS]`
//!
//! H is an OpenCV storage file (the nine numbers in its `<data>` element, row-major) or a plain
//! file of nine numbers; COUNTS is a comma-separated list (default `500,1000,2000`). Run with
//! `RAYON_NUM_THREADS=1` to compare with single-threaded OpenCV.

use std::io::Write;
use std::process::exit;
use std::time::Instant;

use ocellus_engine::op::OpError;
use ocellus_engine::value::{Channels, Descriptors, Image, Keypoint};
use ocellus_nodes::analyze::match_accuracy::match_accuracy;
use ocellus_nodes::describe::orb::{
    OrbParams, PatternTraining, learn_pattern_with, orb_detect_and_compute, orb_with_pattern,
};
use ocellus_nodes::describe::sift::{SiftParams, sift_detect_and_compute};
use ocellus_nodes::detect::gray::gray_u8;
use ocellus_nodes::matching::brute_force::{MatchOptions, brute_force_match};
use ocellus_nodes::matching::{Norm, prepare};

type Features = (Vec<Keypoint>, Descriptors);

fn fail(message: impl std::fmt::Display) -> ! {
    eprintln!("{message}");
    exit(1);
}

/// The image at `path` as gray u8; colour files are converted with BT.601 weights in OpenCV's
/// fixed point (as `cv2.cvtColor(..., COLOR_BGR2GRAY)`), not the `image` crate's Rec. 709
/// luma, so that both libraries see nearly the same pixels. (`cv2.imread(path,
/// IMREAD_GRAYSCALE)` converts inside libpng and differs from both by up to one level: for an
/// exact comparison, give both programs the same gray file.)
fn load(path: &str) -> Image {
    let img = image::open(path).unwrap_or_else(|e| fail(format!("{path}: {e}")));
    let (w, h) = (img.width() as usize, img.height() as usize);
    let image = if img.color().has_color() {
        Image::from_u8(w, h, Channels::Rgb, img.to_rgb8().into_raw())
    } else {
        Image::from_u8(w, h, Channels::Gray, img.to_luma8().into_raw())
    }
    .unwrap_or_else(|e| fail(e));
    let gray = gray_u8(&image).into_owned();
    Image::from_u8(w, h, Channels::Gray, gray).unwrap_or_else(|e| fail(e))
}

fn detect(method: &str, image: &Image, max_features: u32) -> Result<Features, OpError> {
    if method == "orb" {
        let params = OrbParams {
            max_features: max_features.max(1),
            ..OrbParams::default()
        };
        if let Some(pattern) = trained_pattern() {
            return orb_with_pattern(image, &params, pattern);
        }
        orb_detect_and_compute(image, &params)
    } else {
        let params = SiftParams {
            max_features,
            ..SiftParams::default()
        };
        sift_detect_and_compute(image, &params)
    }
}

/// Experiments: `ORB_TRAINING="candidates=4096 sigma=0 images=4 shapes=400 keypoints=1500
/// threshold=0.2 seed=1"` learns the ORB pattern with those settings (see `PatternTraining`).
fn trained_pattern() -> Option<&'static [(i32, i32)]> {
    static PATTERN: std::sync::OnceLock<Option<Vec<(i32, i32)>>> = std::sync::OnceLock::new();
    PATTERN
        .get_or_init(|| {
            let spec = std::env::var("ORB_TRAINING").ok()?;
            let mut t = PatternTraining::default();
            for item in spec.split_whitespace() {
                let (k, v) = item.split_once('=').unwrap_or_else(|| fail(item));
                let f: f64 = v.parse().unwrap_or_else(|e| fail(format!("{item}: {e}")));
                match k {
                    "candidates" => t.candidates = f as usize,
                    "sigma" => t.sigma_ratio = f,
                    "images" => t.images = f as usize,
                    "shapes" => t.shapes = f as usize,
                    "keypoints" => t.keypoints = f as usize,
                    "threshold" => t.threshold = f,
                    "seed" => t.seed = f as u64,
                    "model" => t.model = f as u32,
                    "noise" => t.noise = f,
                    _ => fail(format!("unknown training setting {k}")),
                }
            }
            Some(learn_pattern_with(31, &t))
        })
        .as_deref()
}

/// Best of `FEATURES_REPEATS` (default 5) runs, seconds, and the last result.
fn timed(method: &str, image: &Image, max_features: u32) -> (f64, Features) {
    let repeats: usize = std::env::var("FEATURES_REPEATS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(5);
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let r = detect(method, image, max_features);
        best = best.min(t.elapsed().as_secs_f64());
        result = Some(r);
    }
    match result {
        Some(Ok(r)) => (best, r),
        Some(Err(e)) => fail(e),
        None => fail("no run"),
    }
}

/// The nine numbers of an OpenCV storage matrix (inside `<data>`) or of a plain text file.
fn read_homography(path: &str) -> [f64; 9] {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| fail(format!("{path}: {e}")));
    let body = match (text.find("<data>"), text.find("</data>")) {
        (Some(a), Some(b)) if a < b => &text[a + 6..b],
        _ => text.as_str(),
    };
    let values: Vec<f64> = body
        .split_whitespace()
        .map(|s| {
            s.parse()
                .unwrap_or_else(|e| fail(format!("{path}: {s}: {e}")))
        })
        .collect();
    values
        .try_into()
        .unwrap_or_else(|v: Vec<f64>| fail(format!("{path}: {} numbers, expected 9", v.len())))
}

fn pair(method: &str, args: &[String]) {
    let [first, second, h_path, rest @ ..] = args else {
        fail("usage: features sift|orb --pair IMAGE1 IMAGE2 H [COUNTS]");
    };
    let counts: Vec<u32> = rest
        .first()
        .map_or("500,1000,2000", String::as_str)
        .split(',')
        .map(|s| s.parse().unwrap_or_else(|e| fail(format!("{s}: {e}"))))
        .collect();
    let (a, b) = (load(first), load(second));
    let h = read_homography(h_path);
    println!("method  features  keypoints  matches  correct  ratio   time_ms");
    for n in counts {
        let (seconds, left) = timed(method, &a, n);
        let right = detect(method, &b, n).unwrap_or_else(|e| fail(e));
        let (metric, query, train) =
            prepare(&left.1, &right.1, Norm::Auto).unwrap_or_else(|e| fail(e));
        let options = MatchOptions {
            ratio: 0.8,
            ..MatchOptions::default()
        };
        let matches = brute_force_match(&query, &train, metric, &options, None);
        let m = match_accuracy(&left.0, &right.0, &matches, &h, 3.0).unwrap_or_else(|e| fail(e));
        let get = |k: &str| m.get(k).copied().unwrap_or(0.0);
        println!(
            "{method:<7} {n:>8}  {:>4}/{:<4}  {:>7}  {:>7}  {:.3}  {:>8.1}",
            left.0.len(),
            right.0.len(),
            get("matches"),
            get("correct"),
            get("correct_ratio"),
            seconds * 1e3
        );
    }
}

fn main() {
    // The CLI's allocator settings (freed blocks reused across calls).
    ocellus_engine::buffer::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let method = match args.get(1).map(String::as_str) {
        Some(m @ ("sift" | "orb")) => m,
        _ => {
            eprintln!(
                "usage: features sift|orb IMAGE [MAX_FEATURES] [OUT]\n       \
                 features sift|orb --pair IMAGE1 IMAGE2 H [COUNTS]"
            );
            exit(2);
        }
    };
    if args.get(2).map(String::as_str) == Some("--pair") {
        pair(method, &args[3..]);
        return;
    }
    let Some(path) = args.get(2) else {
        fail("usage: features sift|orb IMAGE [MAX_FEATURES] [OUT]");
    };
    let max_features: u32 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(0);
    let image = load(path);
    let (best, (keypoints, descriptors)) = timed(method, &image, max_features);
    println!(
        "{path}: {} keypoints, best run: {:.1} ms",
        keypoints.len(),
        best * 1e3
    );
    let Some(out) = args.get(4) else { return };
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&(keypoints.len() as u32).to_le_bytes());
    for (i, k) in keypoints.iter().enumerate() {
        for v in [k.x, k.y, k.size, k.angle, k.response, k.octave as f32] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        match &descriptors {
            Descriptors::Float { dim, data } => {
                for v in &data[i * dim..(i + 1) * dim] {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
            Descriptors::Binary { bytes: n, data } => {
                bytes.extend_from_slice(&data[i * n..(i + 1) * n]);
            }
        }
    }
    if let Err(e) = std::fs::File::create(out).and_then(|mut f| f.write_all(&bytes)) {
        fail(format!("{out}: {e}"));
    }
}
