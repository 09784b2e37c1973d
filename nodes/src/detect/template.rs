//! `detect.template_match`: template matching by sum of squared differences, normalized
//! cross-correlation or zero-mean normalized cross-correlation (OpenCV `matchTemplate` with
//! `TM_SQDIFF`, `TM_CCORR_NORMED`, `TM_CCOEFF_NORMED`).
//!
//! [`match_template`] computes the raw correlation `Σ T·I` directly, as row-wise multiply-adds
//! over contiguous output rows (vectorizable), in fixed bands of output rows run in parallel;
//! window sums and energies come from f64 integral images. Every output value is computed by the
//! same arithmetic whatever the thread count.

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Channels, Image, Metrics, Value};
use ocellus_engine::{param_enum, params};
use rayon::prelude::*;

use super::corners::gray_plane;

/// Output rows per parallel band.
const BAND_ROWS: usize = 16;

param_enum! {
    /// Matching score.
    pub enum MatchMethod {
        /// Sum of squared differences Σ(T − I)² (OpenCV TM_SQDIFF); best = minimum.
        Ssd = "ssd",
        /// Σ T·I / √(Σ T² · Σ I²) (OpenCV TM_CCORR_NORMED); best = maximum.
        Ncc = "ncc",
        /// Zero-mean NCC, the Pearson correlation of T and the window (OpenCV
        /// TM_CCOEFF_NORMED); best = maximum.
        Zncc = "zncc",
    }
}

#[allow(clippy::derivable_impls)]
impl Default for MatchMethod {
    fn default() -> Self {
        MatchMethod::Zncc
    }
}

/// Integral image (f64) of `f(v)` over a `w × h` plane: `(w + 1) × (h + 1)`.
fn integral(src: &[f32], w: usize, h: usize, f: impl Fn(f64) -> f64) -> Vec<f64> {
    let s = w + 1;
    let mut out = vec![0.0; s * (h + 1)];
    for y in 0..h {
        let mut run = 0.0;
        for x in 0..w {
            run += f(f64::from(src[y * w + x]));
            out[(y + 1) * s + x + 1] = out[y * s + x + 1] + run;
        }
    }
    out
}

/// Sum of the `tw × th` window at (x, y) from an integral image of stride `s`.
fn window(ii: &[f64], s: usize, x: usize, y: usize, tw: usize, th: usize) -> f64 {
    ii[(y + th) * s + x + tw] - ii[y * s + x + tw] - ii[(y + th) * s + x] + ii[y * s + x]
}

/// Scores of template `t` (`tw × th`) at every position of `img` (`w × h`): an
/// `(w − tw + 1) × (h − th + 1)` plane, position (x, y) = template's top-left corner. Empty if
/// the template is larger than the image or empty.
pub fn match_template(
    img: &[f32],
    w: usize,
    h: usize,
    t: &[f32],
    tw: usize,
    th: usize,
    method: MatchMethod,
) -> (Vec<f32>, usize, usize) {
    if tw == 0 || th == 0 || tw > w || th > h {
        return (Vec::new(), 0, 0);
    }
    let (ow, oh) = (w - tw + 1, h - th + 1);
    let n = (tw * th) as f64;
    let t_sum: f64 = t.iter().map(|&v| f64::from(v)).sum();
    let t_sq: f64 = t.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
    let t_var = (t_sq - t_sum * t_sum / n).max(0.0);
    let s = w + 1;
    let ii = integral(img, w, h, |v| v);
    let ii2 = integral(img, w, h, |v| v * v);
    let mut out = vec![0.0f32; ow * oh];
    out.par_chunks_mut(ow * BAND_ROWS)
        .enumerate()
        .for_each(|(b, band)| {
            let mut corr = vec![0.0f64; ow];
            for (r, out_row) in band.chunks_exact_mut(ow).enumerate() {
                let y = b * BAND_ROWS + r;
                corr.fill(0.0);
                let mut acc = vec![0.0f32; ow];
                for j in 0..th {
                    let row = &img[(y + j) * w..(y + j + 1) * w];
                    let trow = &t[j * tw..(j + 1) * tw];
                    acc.fill(0.0);
                    for (i, &tv) in trow.iter().enumerate() {
                        for (a, &p) in acc.iter_mut().zip(&row[i..i + ow]) {
                            *a += tv * p;
                        }
                    }
                    for (c, &a) in corr.iter_mut().zip(&acc) {
                        *c += f64::from(a);
                    }
                }
                for (x, (o, &c)) in out_row.iter_mut().zip(&corr).enumerate() {
                    let wsum = window(&ii, s, x, y, tw, th);
                    let wsq = window(&ii2, s, x, y, tw, th);
                    let v = match method {
                        MatchMethod::Ssd => (wsq - 2.0 * c + t_sq).max(0.0),
                        MatchMethod::Ncc => normalize(c, (wsq.max(0.0) * t_sq).sqrt()),
                        MatchMethod::Zncc => {
                            let num = c - wsum * t_sum / n;
                            let wvar = (wsq - wsum * wsum / n).max(0.0);
                            normalize(num, (wvar * t_var).sqrt())
                        }
                    };
                    *o = v as f32;
                }
            }
        });
    (out, ow, oh)
}

/// `num / den` clamped as OpenCV does for near-zero denominators: |num| < den → num/den;
/// |num| < 1.125 den → ±1; otherwise 0.
fn normalize(num: f64, den: f64) -> f64 {
    if num.abs() < den {
        num / den
    } else if num.abs() < den * 1.125 {
        num.signum()
    } else {
        0.0
    }
}

/// Best position: minimum for SSD, maximum otherwise; first in raster order on ties.
pub fn best_location(
    scores: &[f32],
    ow: usize,
    method: MatchMethod,
) -> Option<(usize, usize, f32)> {
    let mut best: Option<(usize, f32)> = None;
    for (i, &v) in scores.iter().enumerate() {
        let better = match (best, method) {
            (None, _) => true,
            (Some((_, b)), MatchMethod::Ssd) => v < b,
            (Some((_, b)), _) => v > b,
        };
        if better {
            best = Some((i, v));
        }
    }
    best.map(|(i, v)| (i % ow, i / ow, v))
}

params! {
    /// Parameters of `detect.template_match`.
    pub struct TemplateMatchParams {
        /// Score: "ssd" (TM_SQDIFF, lower is better), "ncc" (TM_CCORR_NORMED) or "zncc"
        /// (TM_CCOEFF_NORMED, default; higher is better).
        method: MatchMethod = MatchMethod::Zncc,
    }
}

/// Template matching (`detect.template_match`). See [`match_template`].
#[derive(Debug, Clone)]
pub struct TemplateMatch {
    method: MatchMethod,
}

impl Op for TemplateMatch {
    type Params = TemplateMatchParams;
    const ID: &'static str = "detect.template_match";
    const SUMMARY: &'static str =
        "Slides a template over an image and scores every position (SSD, NCC or ZNCC).";
    const DOC: &'static str = r#"
For every position (x, y) of the template's top-left corner in the image, with the window W of
the template's size there and n its pixel count:
- ssd:  Σ (T − W)² = ΣW² − 2 ΣTW + ΣT²                (OpenCV TM_SQDIFF)
- ncc:  ΣTW / √(ΣW² · ΣT²)                             (TM_CCORR_NORMED)
- zncc: (ΣTW − ΣW ΣT / n) / √((ΣW² − (ΣW)²/n)(ΣT² − (ΣT)²/n))   (TM_CCOEFF_NORMED)
ΣW and ΣW² come from f64 integral images; ΣTW is computed directly (f32 products summed per
template row, rows summed in f64). As OpenCV, a normalized score with a (near-)zero
denominator is num/den if |num| < den, ±1 if |num| < 1.125·den, else 0 (so flat windows score 0).

Inputs: gray image and gray template (u8, u16 or f32 samples, used as values). The template must
fit in the image. Outputs: `scores` (gray f32, (W − w + 1) × (H − h + 1)), `location` (Points2D
with one point: the best top-left corner, minimum for ssd, maximum otherwise, first in raster
order on ties) and `metrics` (score, x, y).

Differences from OpenCV: OpenCV switches to a DFT-based correlation for large templates; this
operator always correlates directly (cost ∝ image area × template area), so very large
templates are slow.

Reference: J. P. Lewis, "Fast normalized cross-correlation", Vision Interface 1995; OpenCV
cv::matchTemplate.

Example:
    "find": (op: "detect.template_match",
             inputs: { "image": "frame.image", "template": "logo.image" },
             params: (method: "zncc")),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new("image", PortType::Image, "Gray image to search."),
            PortSpec::new(
                "template",
                PortType::Image,
                "Gray template, at most the image's size.",
            ),
        ]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "scores",
                PortType::Image,
                "Score of every position, gray f32.",
            ),
            PortSpec::new(
                "location",
                PortType::Points2D,
                "Best top-left position (one point).",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "score, x, y of the best position.",
            ),
        ]
    }

    fn new(p: TemplateMatchParams) -> Result<Self, String> {
        Ok(TemplateMatch { method: p.method })
    }
}

impl Operator for TemplateMatch {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let templ = inputs.image("template")?;
        let (img, _) = gray_plane(image, Self::ID)?;
        let (t, _) = gray_plane(templ, Self::ID).map_err(|_| {
            OpError::input(
                "template",
                format!("needs a gray template, got {}", templ.format()),
            )
        })?;
        let (w, h, tw, th) = (image.width(), image.height(), templ.width(), templ.height());
        if tw == 0 || th == 0 || tw > w || th > h {
            return Err(OpError::input(
                "template",
                format!(
                    "the template ({tw}×{th}) must be non-empty and fit in the image ({w}×{h})"
                ),
            ));
        }
        let (scores, ow, oh) = match_template(&img, w, h, &t, tw, th, self.method);
        let best = best_location(&scores, ow, self.method);
        let mut metrics = Metrics::new();
        let mut location = Vec::new();
        if let Some((x, y, v)) = best {
            metrics.insert("score".into(), f64::from(v));
            metrics.insert("x".into(), x as f64);
            metrics.insert("y".into(), y as f64);
            location.push([x as f64, y as f64]);
        }
        let scores = Image::from_f32(ow, oh, Channels::Gray, scores)
            .map_err(|e| OpError::failed(e.to_string()))?;
        Ok(Outputs::new()
            .with("scores", Value::image(scores))
            .with("location", Value::Points2D(location.into()))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(w: usize, h: usize, seed: u64) -> Vec<f32> {
        crate::filter::test_support::randoms(seed, w * h)
            .iter()
            .map(|&v| (v * 255.0).floor() as f32)
            .collect()
    }

    #[test]
    fn finds_cut_template_exactly() {
        let (w, h) = (60, 45);
        let img = random(w, h, 3);
        let (tx, ty, tw, th) = (17, 9, 11, 8);
        let t: Vec<f32> = (0..th)
            .flat_map(|j| img[(ty + j) * w + tx..(ty + j) * w + tx + tw].to_vec())
            .collect();
        for m in [MatchMethod::Ssd, MatchMethod::Ncc, MatchMethod::Zncc] {
            let (s, ow, oh) = match_template(&img, w, h, &t, tw, th, m);
            assert_eq!((ow, oh), (w - tw + 1, h - th + 1));
            let (x, y, v) = best_location(&s, ow, m).unwrap();
            assert_eq!((x, y), (tx, ty), "{m:?}");
            match m {
                MatchMethod::Ssd => assert!(v.abs() < 1e-2, "{v}"),
                _ => assert!((v - 1.0).abs() < 1e-5, "{v}"),
            }
        }
    }

    #[test]
    fn hand_computed_scores() {
        // Image 3×1 [1, 2, 4], template 2×1 [1, 2].
        let img = [1.0, 2.0, 4.0];
        let t = [1.0, 2.0];
        let (s, ow, oh) = match_template(&img, 3, 1, &t, 2, 1, MatchMethod::Ssd);
        assert_eq!((ow, oh), (2, 1));
        assert_eq!(s, vec![0.0, 5.0]); // (1−2)² + (2−4)²
        let (s, _, _) = match_template(&img, 3, 1, &t, 2, 1, MatchMethod::Ncc);
        // [1,2]·[2,4] = 10, √(20 · 5) = 10.
        assert!(
            (s[0] - 1.0).abs() < 1e-6 && (s[1] - 1.0).abs() < 1e-6,
            "{s:?}"
        );
        let img = [1.0, 2.0, 4.0, 0.0];
        let t = [0.0, 1.0, 3.0];
        let (s, _, _) = match_template(&img, 4, 1, &t, 3, 1, MatchMethod::Zncc);
        // Pearson of [1,2,4] and [0,1,3] is 1; of [2,4,0] and [0,1,3]: −0.6546537.
        assert!((s[0] - 1.0).abs() < 1e-6, "{s:?}");
        assert!((s[1] + 0.654_653_7).abs() < 1e-6, "{s:?}");
    }

    #[test]
    fn flat_window_scores_zero() {
        let img = vec![5.0f32; 20];
        let t = [1.0, 2.0, 3.0, 4.0];
        let (s, _, _) = match_template(&img, 5, 4, &t, 2, 2, MatchMethod::Zncc);
        assert!(s.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn template_too_large_is_empty() {
        let (s, ow, oh) = match_template(&[1.0], 1, 1, &[1.0, 2.0], 2, 1, MatchMethod::Ssd);
        assert!(s.is_empty() && ow == 0 && oh == 0);
        let (s, _, _) = match_template(&[7.0], 1, 1, &[7.0], 1, 1, MatchMethod::Ssd);
        assert_eq!(s, vec![0.0]);
    }

    #[test]
    fn deterministic_across_threads() {
        let img = random(70, 90, 5);
        let t = random(9, 7, 6);
        let many = match_template(&img, 70, 90, &t, 9, 7, MatchMethod::Zncc);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(
            pool.install(|| match_template(&img, 70, 90, &t, 9, 7, MatchMethod::Zncc)),
            many
        );
    }
}
