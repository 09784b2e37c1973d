//! Speed–accuracy tables of the decomposition operators (ignored by default; run with
//! `cargo test -p ocellus-nodes --lib analyze::decompose_tables -- --ignored --nocapture`).
//! Times are medians of 5 runs in the test profile (opt-level 2), on whatever pool rayon uses.

use std::time::Instant;

use super::face_set::face_set;
use super::fbp::{RampWindow, fbp};
use super::pca::{ComponentSelection, pca};
use super::phantom::{MODIFIED_SHEPP_LOGAN, phantom};
use super::quality::psnr_db;
use super::radon::{Geometry, covering_bins, radon};
use super::svd_compress::low_rank;
use crate::capture::pattern::{Drawing, render};
use crate::segment::kmeans::{KmeansConfig, kmeans, quantize};
use ocellus_engine::value::{Channels, Depth, PixelFormat};

fn median_ms<T>(mut f: impl FnMut() -> T) -> (f64, T) {
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..5 {
        let t = Instant::now();
        last = Some(f());
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    (times[2], last.unwrap())
}

fn mse(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>() / a.len() as f64
}

#[test]
#[ignore]
fn tables() {
    println!("### PCA, 40 faces 32×32: components vs error and time");
    println!(
        "| components | explained variance | rmse | PSNR dB | fit ms | project+reconstruct ms |"
    );
    println!("|---|---|---|---|---|---|");
    let faces = face_set(40, 32, 32, 0.0, 3);
    let data: Vec<Vec<f64>> = faces
        .iter()
        .map(|(_, p)| p.iter().map(|&v| f64::from(v)).collect())
        .collect();
    let (fit_ms, model) = median_ms(|| pca(&data).unwrap());
    for k in [1, 2, 4, 8, 16, 24, 39] {
        let k = model.select(ComponentSelection::Fixed(k));
        let (ms, rebuilt) = median_ms(|| model.reconstruct(&model.project(&data, k), k));
        let e: f64 = data
            .iter()
            .zip(&rebuilt)
            .map(|(a, b)| mse(a, b))
            .sum::<f64>()
            / data.len() as f64;
        println!(
            "| {k} | {:.4} | {:.4} | {:.2} | {fit_ms:.2} | {ms:.3} |",
            model.explained(k),
            e.sqrt(),
            psnr_db(e, 1.0).unwrap_or(f64::INFINITY)
        );
    }

    println!("\n### SVD, gray test card 128×96: rank vs PSNR and storage");
    println!("| rank | storage ratio | relative Frobenius error | PSNR dB | ms |");
    println!("|---|---|---|---|---|");
    let format = |channels| PixelFormat {
        channels,
        depth: Depth::U8,
    };
    let card_gray = render(
        Drawing::TestCard { square: 16 },
        128,
        96,
        format(Channels::Gray),
    )
    .unwrap();
    // Gray levels scaled to 0–1 so the PSNR peak is 1.
    let gray: Vec<f64> = super::pca::image_samples_f64(&card_gray)
        .iter()
        .map(|v| v / 255.0)
        .collect();
    let norm2: f64 = gray.iter().map(|v| v * v).sum();
    for k in [1, 2, 4, 8, 12, 16, 32, 64, 96] {
        let (ms, r) = median_ms(|| low_rank(&gray, 128, 96, k));
        let e = mse(&gray, &r.approximation);
        println!(
            "| {k} | {:.3} | {:.4} | {:.2} | {ms:.2} |",
            (k * (128 + 96 + 1)) as f64 / (128.0 * 96.0),
            (e * gray.len() as f64 / norm2).sqrt(),
            psnr_db(e, 1.0).unwrap_or(f64::INFINITY)
        );
    }

    println!("\n### Radon + FBP, phantom 96×96: angles (and window) vs PSNR and time");
    println!("| angles | window | PSNR dB | radon ms | fbp ms |");
    println!("|---|---|---|---|---|");
    let n = 96;
    let truth: Vec<f64> = phantom(&MODIFIED_SHEPP_LOGAN, n)
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    let mut cases: Vec<(usize, RampWindow)> = [10, 20, 45, 90, 180, 360]
        .iter()
        .map(|&a| (a, RampWindow::Hann))
        .collect();
    cases.extend(
        [
            RampWindow::RamLak,
            RampWindow::SheppLogan,
            RampWindow::Cosine,
            RampWindow::Hamming,
        ]
        .map(|w| (180, w)),
    );
    for (angles, window) in cases {
        let g = Geometry {
            angles,
            range_deg: 180.0,
            bins: covering_bins(n, n),
        };
        let (radon_ms, sino) = median_ms(|| radon(&truth, n, n, &g, 0.5));
        let (fbp_ms, recon) = median_ms(|| fbp(&sino, &g, window, n));
        println!(
            "| {angles} | {} | {:.2} | {radon_ms:.2} | {fbp_ms:.2} |",
            window.name(),
            psnr_db(mse(&truth, &recon), 1.0).unwrap_or(f64::INFINITY)
        );
    }

    println!("\n### k-means colour quantization, RGB test card 128×96: k vs PSNR and time");
    println!("| k | PSNR dB | ms |");
    println!("|---|---|---|");
    let image = render(
        Drawing::TestCard { square: 16 },
        128,
        96,
        format(Channels::Rgb),
    )
    .unwrap();
    let original: Vec<f64> = super::pca::image_samples_f64(&image);
    for k in [2, 4, 8, 16, 32, 64] {
        let config = KmeansConfig {
            k,
            max_iterations: 20,
            epsilon: 0.5,
            attempts: 3,
            seed: 1,
        };
        let (ms, q) = median_ms(|| quantize(&image, &kmeans(&image, &config).unwrap()).unwrap());
        let e = mse(&original, &super::pca::image_samples_f64(&q));
        println!(
            "| {k} | {:.2} | {ms:.1} |",
            psnr_db(e, 255.0).unwrap_or(f64::INFINITY)
        );
    }
}
