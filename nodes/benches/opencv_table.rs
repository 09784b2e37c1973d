//! The filter issue's OpenCV comparison table: each operation of `../shared/anchors/bench_image.py`
//! that Ocellus has, on the same inputs, timed the way the anchors time OpenCV (one warm-up call,
//! then repeats until at least 7 calls and 1.5 s, at most 50; the median is reported).
//!
//! ```text
//! # OpenCV, once per thread count (writes the inputs too):
//! THREADS=1 OMP_NUM_THREADS=1 python bench_image.py --out /tmp/cv.jsonl --dump /tmp/inputs
//! THREADS=2 OMP_NUM_THREADS=2 python bench_image.py --out /tmp/cv.jsonl
//! # Ocellus, same inputs, the ratio column filled from OpenCV's JSON lines:
//! OCELLUS_BENCH_INPUTS=/tmp/inputs OCELLUS_OPENCV_JSONL=/tmp/cv.jsonl \
//!     cargo bench -p ocellus-nodes --bench opencv_table
//! ```
//!
//! Without `OCELLUS_BENCH_INPUTS` the inputs are generated test cards of the same sizes; without
//! `OCELLUS_OPENCV_JSONL` only our times are printed. `OCELLUS_BENCH_THREADS` (default `1,2`)
//! lists the thread counts and `OCELLUS_BENCH_ONLY` filters operations by substring. Output is
//! one Markdown table row per (operation, input, threads).

use std::collections::HashMap;
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use ocellus_engine::image_io::{DecodeLimits, read_image};
use ocellus_engine::value::{Channels, Depth, Image, PixelFormat};
use ocellus_nodes::capture::pattern::{Drawing, render};
use ocellus_nodes::detect::canny::canny;
use ocellus_nodes::filter::bilateral::{bilateral_filter, radius_for};
use ocellus_nodes::filter::border::BorderMode;
use ocellus_nodes::filter::box_filter::box_filter;
use ocellus_nodes::filter::color::{Conversion, convert_color};
use ocellus_nodes::filter::convert::convert_type;
use ocellus_nodes::filter::gaussian::gaussian_blur;
use ocellus_nodes::filter::grayscale::{LumaStandard, grayscale};
use ocellus_nodes::filter::integral::integral;
use ocellus_nodes::filter::median::median_blur;
use ocellus_nodes::filter::morphology::{
    MorphBorder, Operation, Shape, StructuringElement, morphology,
};
use ocellus_nodes::filter::pyramid::pyr_down;
use ocellus_nodes::filter::resize::{Interpolation, Target, resize};
use ocellus_nodes::filter::sobel::sobel;
use ocellus_nodes::filter::threshold::{ThresholdMethod, ThresholdMode, threshold};
use ocellus_nodes::segment::components::connected_components;

const MIN_REPEATS: usize = 7;
const MAX_REPEATS: usize = 50;
const TARGET: Duration = Duration::from_millis(1500);

type Case = (&'static str, &'static str, Box<dyn Fn(&Image) + Sync>);

fn main() {
    // The allocator settings of the CLI (freed blocks are reused, not
    // faulted in again); `OCELLUS_BENCH_ALLOCATOR=default` measures with glibc's defaults.
    if std::env::var("OCELLUS_BENCH_ALLOCATOR").as_deref() != Ok("default") {
        ocellus_engine::buffer::keep_freed_memory();
    }
    let inputs_dir = std::env::var("OCELLUS_BENCH_INPUTS").ok();
    let opencv = std::env::var("OCELLUS_OPENCV_JSONL")
        .ok()
        .map(|p| load_opencv(Path::new(&p)))
        .unwrap_or_default();
    let only = std::env::var("OCELLUS_BENCH_ONLY").ok();
    let threads: Vec<usize> = std::env::var("OCELLUS_BENCH_THREADS")
        .unwrap_or_else(|_| "1,2".into())
        .split(',')
        .filter_map(|t| t.trim().parse().ok())
        .collect();

    println!("| operation | input | threads | Ocellus ms | OpenCV ms | ratio |");
    println!("|---|---|---:|---:|---:|---:|");
    for (tag, w, h) in [("1080p", 1920, 1080), ("2160p", 3840, 2160)] {
        let load = |channels: Channels, name: &str| -> Image {
            if let Some(dir) = &inputs_dir {
                let path = Path::new(dir).join(format!("synth_{tag}_{name}.png"));
                match read_image(&path, &DecodeLimits::default()) {
                    Ok(image) => return image,
                    Err(e) => panic!("{}: {e}", path.display()),
                }
            }
            let format = PixelFormat {
                channels,
                depth: Depth::U8,
            };
            match render(Drawing::TestCard { square: 32 }, w, h, format) {
                Ok(image) => image,
                Err(e) => panic!("rendering the input: {e}"),
            }
        };
        let rgb = load(Channels::Rgb, "rgb");
        let gray = load(Channels::Gray, "gray");
        let gray_f32 = match convert_type(&gray, Depth::F32, Some(1.0 / 255.0), 0.0) {
            Ok(image) => image,
            Err(e) => panic!("{e}"),
        };
        // The anchors' connected-components input: the gray image binarized by Otsu.
        let binary = match threshold(
            &gray,
            ThresholdMethod::Otsu,
            ThresholdMode::Binary,
            0.0,
            255.0,
        ) {
            Ok((image, _)) => image,
            Err(e) => panic!("{e}"),
        };
        let inputs: [(&str, &Image); 4] = [
            ("u8 gray", &gray),
            ("u8 RGB", &rgb),
            ("f32 gray", &gray_f32),
            ("u8 binary", &binary),
        ];
        for (op, kinds, run) in cases() {
            if only.as_deref().is_some_and(|o| !op.contains(o)) {
                continue;
            }
            for (kind, image) in inputs {
                if !kinds.split(',').any(|k| k == kind) {
                    continue;
                }
                // OpenCV's rows name the binary input after the gray image it comes from.
                let input = format!("{tag} {}", kind.replace("u8 binary", "u8 gray"));
                for &t in &threads {
                    let pool = match rayon::ThreadPoolBuilder::new().num_threads(t).build() {
                        Ok(pool) => pool,
                        Err(e) => panic!("thread pool: {e}"),
                    };
                    let ms = pool.install(|| median_ms(|| run(image)));
                    let cv = opencv.get(&(op.to_string(), input.clone(), t));
                    let (cv_text, ratio) = match cv {
                        Some(cv) => (format!("{cv:.3}"), format!("{:.2}×", ms / cv)),
                        None => ("–".into(), "–".into()),
                    };
                    println!("| {op} | {input} | {t} | {ms:.3} | {cv_text} | {ratio} |");
                }
            }
        }
    }
}

/// The operations, named exactly as the anchors name them, with the input kinds they take.
fn cases() -> Vec<Case> {
    let open = match StructuringElement::new(Shape::Rect, 5, 5) {
        Some(element) => element,
        None => panic!("5×5 rectangle"),
    };
    vec![
        (
            "GaussianBlur 5x5 s=1.5",
            "u8 gray,u8 RGB,f32 gray",
            Box::new(|i| {
                black_box(gaussian_blur(
                    i,
                    1.5,
                    1.5,
                    5,
                    5,
                    BorderMode::Reflect101,
                    0.0,
                ));
            }),
        ),
        (
            "boxFilter 7x7 (normalized)",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                black_box(box_filter(i, 7, 7, true, BorderMode::Reflect101, 0.0));
            }),
        ),
        (
            "medianBlur 5",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                black_box(median_blur(i, 5, BorderMode::Clamp, 0.0));
            }),
        ),
        (
            "Sobel dx ksize=3 (u8->f32)",
            "u8 gray",
            Box::new(|i| {
                black_box(sobel(i, 1, 0, 3, 1.0, 0.0, BorderMode::Reflect101, 0.0));
            }),
        ),
        (
            "bilateralFilter d=9 sc=75 ss=75",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                let radius = radius_for(9, 75.0).unwrap_or(4);
                black_box(bilateral_filter(
                    i,
                    radius,
                    75.0,
                    75.0,
                    BorderMode::Reflect101,
                    0.0,
                ));
            }),
        ),
        (
            "resize 0.5x INTER_AREA",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                let target = Target::Size(i.width() / 2, i.height() / 2);
                black_box(resize(i, target, Interpolation::Area).ok());
            }),
        ),
        (
            "resize 2x INTER_LINEAR",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                let target = Target::Size(i.width() * 2, i.height() * 2);
                black_box(resize(i, target, Interpolation::Bilinear).ok());
            }),
        ),
        (
            "pyrDown",
            "u8 gray,u8 RGB",
            Box::new(|i| {
                black_box(pyr_down(i).ok());
            }),
        ),
        (
            "morphologyEx OPEN rect 5x5",
            "u8 gray,u8 RGB",
            Box::new(move |i| {
                black_box(morphology(
                    i,
                    Operation::Open,
                    &open,
                    1,
                    MorphBorder::Neutral,
                ));
            }),
        ),
        (
            "Canny 50/150 (aperture 3, L1)",
            "u8 gray",
            Box::new(|i| {
                if let Some(gray) = i.as_u8() {
                    black_box(canny(gray, i.width(), i.height(), 50.0, 150.0, 3, false));
                }
            }),
        ),
        (
            "connectedComponents 8-conn (Otsu binary)",
            "u8 binary",
            Box::new(|i| {
                black_box(connected_components(i, true, false).ok());
            }),
        ),
        (
            "connectedComponentsWithStats 8-conn",
            "u8 binary",
            Box::new(|i| {
                black_box(connected_components(i, true, true).ok());
            }),
        ),
        (
            "threshold OTSU",
            "u8 gray",
            Box::new(|i| {
                black_box(
                    threshold(i, ThresholdMethod::Otsu, ThresholdMode::Binary, 0.0, 255.0).ok(),
                );
            }),
        ),
        (
            "integral (u8->f64)",
            "u8 gray",
            Box::new(|i| {
                black_box(integral(i));
            }),
        ),
        (
            "cvtColor RGB2HSV",
            "u8 RGB",
            Box::new(|i| {
                black_box(convert_color(i, Conversion::RgbToHsv).ok());
            }),
        ),
        (
            "cvtColor RGB2GRAY",
            "u8 RGB",
            Box::new(|i| {
                black_box(grayscale(i, LumaStandard::Bt601).ok());
            }),
        ),
    ]
}

/// Median wall time of `f` in milliseconds, with the anchors' repeat policy.
fn median_ms(f: impl Fn()) -> f64 {
    f();
    let start = Instant::now();
    let mut times = Vec::new();
    loop {
        let t0 = Instant::now();
        f();
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        if times.len() >= MAX_REPEATS || (times.len() >= MIN_REPEATS && start.elapsed() >= TARGET) {
            break;
        }
    }
    times.sort_by(f64::total_cmp);
    let n = times.len();
    if n % 2 == 1 {
        times[n / 2]
    } else {
        (times[n / 2 - 1] + times[n / 2]) / 2.0
    }
}

/// OpenCV medians from the anchors' JSON lines, keyed by (op, input, threads); the last line
/// for a key wins.
fn load_opencv(path: &Path) -> HashMap<(String, String, usize), f64> {
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) => panic!("{}: {e}", path.display()),
    };
    let mut medians = HashMap::new();
    for line in text.lines() {
        let Ok(record) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let (Some(op), Some(input), Some(threads), Some(ms)) = (
            record["op"].as_str(),
            record["input"].as_str(),
            record["threads"].as_u64(),
            record["median_ms"].as_f64(),
        ) else {
            continue;
        };
        medians.insert((op.to_string(), input.to_string(), threads as usize), ms);
    }
    medians
}
